"""Snapshot sets after a SIGKILL: OUT.exr, OUT.png and OUT.json belong together.

The three files cannot be replaced in one atomic step; the EXR is renamed first and holds
the JSON record in its header, the JSON (with the EXR's and PNG's SHA-256) last
(jaxvcm/_io/_images.py). So after a kill at ANY moment: the EXR is complete and matches its
own record, and `recover_outputs` (which the next render to OUT runs first) leaves a set
that `check_outputs` accepts, with no temp file of a dead process left. Kills land at
chosen points between the renames (deterministic) and at random moments of a writing loop.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxvcm import _io
from jaxvcm._io._images import _exr_record

ROOT = Path(__file__).resolve().parents[2]


def _writer(out: Path, start: int, kill_after: int | None = None):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               JAX_PLATFORMS="cpu")
    args = [sys.executable, "-m", "tests._snapshot_writer", str(out), str(start)]
    if kill_after is not None:
        args.append(str(kill_after))
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            cwd=ROOT, text=True)


def _exr_self_consistent(out: Path) -> int:
    # the EXR alone: readable, finite, and its pixels are the pass count its record names
    img = _io.read_exr(out)
    assert np.all(np.isfinite(img))
    passes = _exr_record(str(out))["passes"]
    assert np.all(img == passes)
    return passes


def _temps(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


def _after_kill(out: Path) -> tuple[int, bool]:
    passes = _exr_self_consistent(out)
    torn = bool(_io.check_outputs(str(out)))
    done = _io.recover_outputs(str(out))
    assert _io.check_outputs(str(out)) == [], done
    assert _temps(out.parent) == []  # the dead writer's temp files are gone
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["passes"] == passes and meta["exposure"] == 0.5
    return passes, torn


@pytest.mark.parametrize("k,torn", [(3 * 2 + 1, True), (3 * 2 + 2, True), (3 * 2 + 3, False)],
                         ids=["after-exr", "after-png", "after-json"])
def test_kill_between_renames(k, torn, tmp_path):
    # snapshots 0 and 1 complete; snapshot 2 killed after its EXR, its PNG or its JSON
    out = tmp_path / "snap.exr"
    p = _writer(out, 0, kill_after=k)
    p.wait(timeout=120)
    assert p.returncode == -signal.SIGKILL, p.stderr.read()
    assert _exr_self_consistent(out) == 2
    assert bool(_io.check_outputs(str(out))) is torn
    assert _after_kill(out) == (2, torn)


def test_kill_at_random_moments(tmp_path):
    # many kills of one writer loop into the same directory; each restart continues the
    # pass count, as a resumed render would
    rng = random.Random(14)
    out = tmp_path / "snap.exr"
    start, torn_seen = 0, 0
    for trial in range(8):
        p = _writer(out, start)
        assert p.stdout.readline().strip() == "ready", p.stderr.read()
        time.sleep(rng.uniform(0.05, 0.6))
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=60)
        if not out.exists():  # killed before its first set: nothing to check yet
            continue
        passes, torn = _after_kill(out)
        assert passes >= start - 1
        torn_seen += torn
        start = passes + 1
    assert start > 8  # the writer did write between kills


def test_progressive_recovers_first(tmp_path):
    # the next render to the same output starts by recovering: a torn set and a dead
    # process's temp file are both dealt with before its own first pass
    from jaxvcm._render import progressive

    out = tmp_path / "snap.exr"
    p = _writer(out, 5, kill_after=3 + 1)  # set 5 complete, set 6 torn after its EXR
    p.wait(timeout=120)
    assert _io.check_outputs(str(out))
    seen = []

    def run_pass(i):
        seen.append((_io.check_outputs(str(out)), _temps(tmp_path)))
        return np.ones((2, 3, 3)), 0

    progressive(run_pass, lambda m: m, lambda *a: {"passes": a[0]}, passes=1, out=str(out),
                progress=False)
    assert seen == [([], [".snap.exr.lock"])]  # only the render's own lock (held)
    assert _io.check_outputs(str(out)) == []
    assert _temps(tmp_path) == []  # and it goes with the render


def test_live_writer_temps_are_kept(tmp_path):
    # a temp file of a process that still runs is not touched by recovery
    out = tmp_path / "snap.exr"
    _io.write_outputs(str(out), np.zeros((2, 2, 3), np.float32), {"passes": 1})
    live = tmp_path / f".snap.png.tmp{os.getppid()}.abc"
    dead_pid = _dead_pid()
    dead = tmp_path / f".snap.png.tmp{dead_pid}.abc"
    live.write_bytes(b"x")
    dead.write_bytes(b"x")
    _io.recover_outputs(str(out))
    assert live.exists() and not dead.exists()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_time_budget_starts_after_the_first_pass(tmp_path):
    # The first pass compiles (here: 0.6 s of "compilation"), the others take 10 ms each.
    # A 0.3 s budget counted from the start would end after that first pass; counted after
    # it, it renders ~0.3 / 0.01 = 30 more (at least 10 on a loaded machine), and the
    # record says how long the first pass took (>= 0.6 s) and the whole run (>= 0.9 s)
    from jaxvcm._render import progressive

    def run_pass(i):
        time.sleep(0.6 if i == 0 else 0.01)
        return np.ones((2, 3, 3)), 0

    out = tmp_path / "t.exr"
    _, n, _ = progressive(run_pass, lambda m: m, lambda n, s, *a: {"passes": n, "seconds": s},
                          time=0.3, out=str(out), progress=False)
    assert n >= 10
    rec = json.loads(out.with_suffix(".json").read_text())
    assert rec["passes"] == n and rec["first_pass_seconds"] >= 0.6
    assert rec["seconds"] >= rec["first_pass_seconds"] + 0.3
