"""Passes on several devices (issue 11, devices; jaxvcm/_devices.py): with 2 CPU devices
(`--xla_force_host_platform_device_count=2`, in a subprocess: the flag must be set before
jax starts) `render(..., devices=2)` gives the same image bit for bit as `devices=1`: the
same keys `pass_key(seed, i)`, the same pass indices (VCM's radius schedule), added in the
same order; an odd pass count ends with a partial batch; the CLI's --devices gives the
same EXR."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxvcm import _devices
from jaxvcm.cli import main

ROOT = Path(__file__).resolve().parent.parent
SKY = ROOT / "scenes" / "pool_sky.toml"

CHILD = r"""
import json, os, sys
import numpy as np, jax
import jaxvcm
from jaxvcm.cli import main
assert len(jax.local_devices()) == 2, jax.local_devices()
scene = jaxvcm.load_scene(sys.argv[1], width=8, height=6)
out = {}
for alg in ("pt", "vcm"):
    cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=3)
    a = jaxvcm.render(scene, alg, passes=5, config=cfg, progress=False, devices=1)
    b = jaxvcm.render(scene, alg, passes=5, config=cfg, progress=False, devices=2)
    out[alg] = [bool(np.array_equal(a, b)), float(np.abs(a).max())]
d = sys.argv[2]
for n in (1, 2):
    rc = main(["render", sys.argv[1], "--algorithm", "pt", "--passes", "3", "--width", "8",
               "--height", "6", "--max-depth", "3", "--quiet", "--devices", str(n),
               "--out", os.path.join(d, f"d{n}.exr")])
    assert rc == 0
a, b = (jaxvcm.read_exr(os.path.join(d, f"d{n}.exr")) for n in (1, 2))
out["cli"] = bool(np.array_equal(a, b))
out["meta"] = json.load(open(os.path.join(d, "d2.json")))
print("RESULT " + json.dumps(out))
"""


def test_two_devices_equal_one(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") +
                          " --xla_force_host_platform_device_count=2").strip(),
               JAXVCM_CACHE_DIR=str(ROOT / ".jax_cache"),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", CHILD, str(SKY), str(tmp_path)], env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.split("RESULT ", 1)[1])
    for alg in ("pt", "vcm"):
        same, peak = res[alg]
        assert same and peak > 0, (alg, res[alg])
    assert res["cli"]
    assert res["meta"]["devices"] == 2 and res["meta"]["passes"] == 3


@pytest.mark.parametrize("bad", [0, 99, "two", True, []])
def test_bad_devices(bad):
    with pytest.raises(ValueError, match="^devices: "):
        _devices.resolve_devices(bad)


def test_cli_devices_out_of_range(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(["render", str(SKY), "--passes", "1", "--devices", "64"])
    _, err = capsys.readouterr()
    assert rc == 2 and err.startswith("jaxvcm: error: devices: must lie in [1, ")
    assert len(err.splitlines()) == 1
    assert not list(tmp_path.iterdir())  # checked before anything is written
