"""Passes on several devices and processes (jaxvcm/_devices.py, _hosts.py).

With 4 CPU devices (`--xla_force_host_platform_device_count=4`, in a subprocess: the flag
must be set before jax starts), `render(..., devices=N)` for N = 1 and 4 gives the same
image for the same passes, for PT and VCM, with a partial last batch (5 passes on 4
devices: a batch of 4 and a batch of 1). The
tolerance is rtol 1e-5: one device adds the per-pass float32 images on the host in float64;
several keep a Kahan-compensated float32 sum per device and `psum` the sums in float32, so
a pixel's total carries a few float32 roundings (6e-8 each), never an error that grows with
the pass count; a wrong key, pass index or a dropped or doubled pass changes a pixel by
O(1/passes), 4 orders of magnitude more. A time-budgeted render on 4 devices records the
passes it averaged (a multiple of 4) and equals the one-device render of that many passes;
a render resumed on 4 devices from a 1-device output set equals the uninterrupted one (from
the stored float32 mean: the same tolerance); a resume with another seed is refused in one
line. Two processes on loopback (`jax.distributed`, gloo) equal one process through the
CLI.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxvcm
from jaxvcm import _devices
from jaxvcm.cli import main

ROOT = Path(__file__).resolve().parents[2]
SKY = ROOT / "scenes" / "pool_sky.toml"
RTOL = 1e-5

CHILD = r"""
import json, os, sys
import numpy as np, jax
# the persistent cache configured as the parent's harness does (tests/conftest.py), so the
# CLI below runs the same jitted passes as the renders before it instead of exporting and
# compiling its own (exported warm starts: tests/host/test_warm.py)
jax.config.update("jax_compilation_cache_dir", os.environ["JAXVCM_CACHE_DIR"])
import jaxvcm
from jaxvcm.cli import main
assert len(jax.local_devices()) == 4, jax.local_devices()
scene = jaxvcm.load_scene(sys.argv[1], width=8, height=6)
d = sys.argv[2]
out = {}
def rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(a)))
for alg in ("pt", "vcm"):
    cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=3)
    imgs = [jaxvcm.render(scene, alg, passes=5, config=cfg, progress=False, devices=n)
            for n in (1, 4)]
    one4 = jaxvcm.render(scene, alg, passes=4, config=cfg, progress=False, devices=1)
    out[alg] = {"d4": rel(imgs[0], imgs[1]),
                "peak": float(np.abs(imgs[0]).max()), "p4_vs_p5": rel(imgs[0], one4)}
cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=3)
# a time budget on 4 devices: the record's pass count is what was averaged
tb = os.path.join(d, "tb.exr")
a = jaxvcm.render(scene, "vcm", time=1.0, config=cfg, progress=False, devices=4, out=tb)
n = json.load(open(os.path.join(d, "tb.json")))["passes"]
b = jaxvcm.render(scene, "vcm", passes=n, config=cfg, progress=False, devices=1)
out["time"] = {"passes": n, "rel": rel(b, a), "exr": rel(b, jaxvcm.read_exr(tb))}
# snapshots on 4 devices (each one a psum of the device sums): 3 batches, snapshots after
# the second; the final set checks out and equals one device
sn = os.path.join(d, "sn.exr")
a = jaxvcm.render(scene, "vcm", passes=12, config=cfg, progress=False, devices=4, out=sn,
                  snapshot_every=1e-6)
b = jaxvcm.render(scene, "vcm", passes=12, config=cfg, progress=False, devices=1)
out["snap"] = {"rel": rel(b, a), "exr": rel(b, jaxvcm.read_exr(sn)),
               "problems": jaxvcm.check_outputs(sn),
               "passes": json.load(open(os.path.join(d, "sn.json")))["passes"]}
# resume: 3 passes on 1 device, then up to 7 on 4 devices
r = os.path.join(d, "r.exr")
jaxvcm.render(scene, "vcm", passes=3, config=cfg, progress=False, devices=1, out=r)
c = jaxvcm.render(scene, "vcm", passes=7, config=cfg, progress=False, devices=4, out=r,
                  resume=True)
e = jaxvcm.render(scene, "vcm", passes=7, config=cfg, progress=False, devices=1)
out["resume"] = {"rel": rel(e, c), "passes": json.load(open(os.path.join(d, "r.json")))["passes"]}
try:
    jaxvcm.render(scene, "vcm", passes=9, config=cfg, progress=False, seed=1, out=r,
                  resume=True)
    out["resume_seed"] = None
except ValueError as ex:
    out["resume_seed"] = str(ex)
for n in (1, 4):
    rc = main(["render", sys.argv[1], "--algorithm", "pt", "--passes", "3", "--width", "8",
               "--height", "6", "--max-depth", "3", "--quiet", "--devices", str(n),
               "--out", os.path.join(d, f"d{n}.exr")])
    assert rc == 0
a, b = (jaxvcm.read_exr(os.path.join(d, f"d{n}.exr")) for n in (1, 4))
out["cli"] = rel(a, b)
# the fit's Jacobian (scenes x regions x keys) with its 8 passes spread over 4 devices
from jaxvcm._fit._model import Region, region_colours_fn
small = jaxvcm.load_scene(sys.argv[1], width=8, height=8)
regs = [Region("r", 0, (1, 4, 7, 8), (0.1, 0.1, 0.1)), Region("s", 0, (0, 0, 8, 3), (0.1,) * 3)]
fcfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=4, rr_depth=100)  # floor via the surface
theta = np.log(np.array([0.3, 0.1, 0.03, 0.05, 0.02, 0.05], np.float32))
jac = [np.asarray(jax.jit(jax.jacfwd(lambda t: region_colours_fn([small], regs, fcfg, 8, 3,
                                                                 devices=ds)(t)[0]))(theta))
       for ds in ([jax.local_devices()[0]], None)]
out["fit_jac"] = {"rel": rel(jac[0], jac[1]), "peak": float(np.abs(jac[0]).max())}
out["meta"] = json.load(open(os.path.join(d, "d4.json")))
print("RESULT " + json.dumps(out))
"""


def _env(devices: int | None = None) -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAXVCM_CACHE_DIR=str(ROOT / ".jax_cache"),
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if devices:
        env["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                            f" --xla_force_host_platform_device_count={devices}").strip()
    return env


def test_one_two_four_devices_agree(tmp_path):
    p = subprocess.run([sys.executable, "-c", CHILD, str(SKY), str(tmp_path)], env=_env(4),
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.split("RESULT ", 1)[1])
    for alg in ("pt", "vcm"):
        r = res[alg]
        assert r["peak"] > 0, (alg, r)
        assert r["d4"] <= RTOL, (alg, r)
        # the tolerance has teeth: dropping one of the 5 passes is far outside it
        assert r["p4_vs_p5"] > 1e3 * RTOL, (alg, r)
    t = res["time"]
    assert t["passes"] >= 4 and t["passes"] % 4 == 0, t
    assert t["rel"] <= RTOL and t["exr"] <= RTOL, t
    sn = res["snap"]
    assert sn["passes"] == 12 and sn["problems"] == [] and max(sn["rel"], sn["exr"]) <= RTOL, sn
    assert res["resume"]["passes"] == 7 and res["resume"]["rel"] <= RTOL, res["resume"]
    assert res["resume_seed"] is not None and res["resume_seed"].startswith("resume: "), res
    assert "seed" in res["resume_seed"] and "\n" not in res["resume_seed"]
    assert res["cli"] <= RTOL
    j = res["fit_jac"]
    assert j["peak"] > 0 and j["rel"] <= RTOL, j  # the passes' mean: a reduction over devices
    assert res["meta"]["devices"] == 4 and res["meta"]["passes"] == 3


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(args: list[str], out: str) -> list[tuple[str, str]]:
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, *args, "--out", out, "--coordinator",
                               f"127.0.0.1:{port}", "--num-processes", "2", "--process-id",
                               str(i)], env=_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in (0, 1)]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (_, se) in zip(procs, outs):
        assert p.returncode == 0, se[-3000:]
    return outs


def test_two_processes_equal_one(tmp_path):
    """Two processes on loopback (`--coordinator`, gloo collectives), one CPU device each:
    process 0 writes the set, process 1 writes nothing; 3 passes, then `--resume` up to 5
    (process 0 reads the set and broadcasts it), equal the one-process render of the same
    5 passes (rtol 1e-5, as above). PT: what the processes share (keys, pass indices, the
    sums, the set) does not depend on the algorithm; VCM on several devices is the test
    above."""
    args = ["-m", "jaxvcm", "render", str(SKY), "--algorithm", "pt", "--width", "8",
            "--height", "6", "--max-depth", "3", "--quiet"]
    two, one = str(tmp_path / "two.exr"), str(tmp_path / "one.exr")
    outs = _two_processes(args + ["--passes", "3"], two)
    # (gloo prints its own "connected" line to stdout)
    assert outs[0][0].strip().splitlines()[-1] == two and two not in outs[1][0]
    assert json.load(open(tmp_path / "two.json"))["passes"] == 3
    _two_processes(args + ["--passes", "5", "--resume"], two)
    meta = json.load(open(tmp_path / "two.json"))
    assert meta["processes"] == 2 and meta["devices"] == 2 and meta["passes"] == 5
    assert main(args[2:] + ["--passes", "5", "--out", one]) == 0
    a, b = jaxvcm.read_exr(one), jaxvcm.read_exr(two)
    assert np.abs(a).max() > 0
    assert np.max(np.abs(a - b)) <= RTOL * np.abs(a).max()


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
