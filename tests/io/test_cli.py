"""The command line: one-line errors on malformed scenes, render outputs (EXR + PNG + JSON),
snapshots that survive SIGKILL / SIGINT, export and info."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxvcm import _io
from jaxvcm.cli import main

ROOT = Path(__file__).resolve().parents[2]
POOL = str(ROOT / "scenes" / "pool.toml")
BAD = sorted((ROOT / "tests" / "data" / "bad").glob("*.toml"))
TINY = ["--width", "16", "--height", "16", "--max-depth", "3"]
META_KEYS = {"scene", "scene_sha256", "scene_name", "algorithm", "config", "passes", "seconds",
             "seed", "nonfinite", "snapshot", "version", "width", "height"}


def _expected_field(path: Path) -> str:
    first = path.read_text().splitlines()[0]
    assert first.startswith("# expect: "), f"{path.name}: first line must be '# expect: FIELD'"
    return first[len("# expect: "):].strip()


def _env():
    env = dict(os.environ)
    env["JAXVCM_CACHE_DIR"] = str(ROOT / ".jax_cache")  # shared with conftest's cache
    env.setdefault("JAX_PLATFORMS", "cpu")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _one_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].strip(), f"expected one line on stderr, got {err!r}"
    return lines[0]


# ------------------------------------------------------------------ malformed scenes
def test_bad_corpus_is_large_enough():
    assert len(BAD) >= 10


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_scene_one_line_error(path, capsys, tmp_path):
    field = _expected_field(path)
    rc = main(["render", str(path), "--passes", "1", "--out", str(tmp_path / "x.exr")])
    out, err = capsys.readouterr()
    assert rc == 2
    line = _one_line(err)
    assert line.startswith(f"jaxvcm: error: {path}: {field}: "), line
    assert path.name in line and field in line
    assert not list(tmp_path.iterdir())  # nothing rendered or written


def test_bad_scene_subprocess_one_line():
    path = ROOT / "tests" / "data" / "bad" / "negative_sigma_a.toml"
    p = subprocess.run([sys.executable, "-m", "jaxvcm.cli", "info", str(path)],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert p.returncode == 2
    line = _one_line(p.stderr)
    assert line.startswith(f"jaxvcm: error: {path}: water.sigma_a[0]: "), line
    assert p.stdout == ""


@pytest.mark.parametrize("args", [
    ["render", POOL, "--passes", "0"],
    ["render", POOL, "--time", "-1"],
    ["render", POOL, "--passes", "2", "--time", "3"],
    ["render", POOL, "--algorithm", "nope"],
    ["render", POOL, "--out", "x.png"],
    ["render", "does/not/exist.toml", "--passes", "1"],
    ["info"],
    ["export", POOL, "pool.stl"],
    ["frobnicate"],
], ids=["passes0", "time-neg", "passes+time", "algorithm", "out-ext", "missing-file",
        "info-noarg", "export-ext", "command"])
def test_bad_arguments_one_line(args, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(args)
    _, err = capsys.readouterr()
    assert rc == 2
    assert _one_line(err).startswith("jaxvcm: error: ")
    assert not list(tmp_path.iterdir())


def _setup_out(kind: str, d: Path) -> str:
    """An --out of each bad kind, made in d; the expected start of its message."""
    if kind == "empty":
        return ""
    if kind == "dir":
        (d / "x.exr").mkdir()
        return "x.exr"
    if kind == "under-file":
        (d / "f").write_text("")
        return "f/x.exr"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind,msg", [
    ("empty", "--out: empty"), ("dir", "x.exr: is a directory"),
    ("under-file", "f/x.exr: cannot write: "),
], ids=["empty", "dir", "under-file"])
def test_bad_out_refused_before_any_work(kind, msg, capsys, tmp_path, monkeypatch):
    # every output path is checked before the scene is even loaded (the scene named here
    # does not exist: a check after loading would report the scene instead)
    monkeypatch.chdir(tmp_path)
    out = _setup_out(kind, tmp_path)
    rc = main(["render", "does/not/exist.toml", "--out", out, "--passes", "1"])
    _, err = capsys.readouterr()
    assert rc == 2 and _one_line(err).startswith(f"jaxvcm: error: {msg}"), err


def test_second_render_to_a_held_out_is_refused(capsys, tmp_path, monkeypatch):
    # a render holds its output set (an flock the system drops with the process): another
    # to the same --out is refused in one line, before any work; once released, it is free
    monkeypatch.chdir(tmp_path)
    with _io.output_lock(str(tmp_path / "x.exr")):
        rc = main(["render", "does/not/exist.toml", "--out", "x.exr", "--passes", "1"])
        _, err = capsys.readouterr()
        assert rc == 2 and "another render is writing this output set" in _one_line(err)
        with pytest.raises(_io.OutputError, match="another render"):  # in-process too
            with _io.output_lock(str(tmp_path / "x.exr")):
                pass
    assert not list(tmp_path.iterdir())  # the lock file goes with the lock
    rc = main(["render", "does/not/exist.toml", "--out", "x.exr", "--passes", "1"])
    _, err = capsys.readouterr()
    assert rc == 2 and "does/not/exist.toml" in err  # past the output checks


@pytest.mark.parametrize("out,msg", [("", "--out: empty"), ("f/sub", "--out: 'f/sub': ")],
                         ids=["empty", "under-file"])
def test_fit_out_checked_before_the_fit(out, msg, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "f").write_text("")
    cfg = ROOT / "fits" / "recover_rgb" / "fit.toml"
    rc = main(["fit", str(cfg), "--out", out, "--quiet"])
    _, err = capsys.readouterr()
    assert rc == 2 and _one_line(err).startswith(f"jaxvcm: error: {msg}"), err


def test_version(capsys):
    import jaxvcm

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxvcm {jaxvcm.__version__}"


def test_bench_missing_or_delegated(capsys, monkeypatch, tmp_path):
    # `jaxvcm bench` runs benchmarks/bench.py of the checkout beside jaxvcm/ ...
    import benchmarks.bench

    from jaxvcm import cli

    calls = []
    monkeypatch.setattr(benchmarks.bench, "main", lambda argv: calls.append(argv) or 0)
    assert main(["bench", "--foo", "1"]) == 0
    assert calls == [["--foo", "1"]]
    # ... and fails with one line when there is none (an install without the checkout)
    monkeypatch.setattr(cli, "_benchmarks_dir", lambda: tmp_path / "benchmarks")
    rc = main(["bench"])
    _, err = capsys.readouterr()
    assert rc == 2
    assert _one_line(err).startswith("jaxvcm: error: bench: ")


# ------------------------------------------------------------------ film
def test_write_outputs_atomic_on_failure(tmp_path, monkeypatch):
    import OpenEXR

    out = tmp_path / "a.exr"
    img = np.random.default_rng(0).random((5, 7, 3), dtype=np.float32)
    _io.write_outputs(str(out), img, {"k": 1}, exposure=1.0)
    assert np.array_equal(_io.read_exr(out), img)

    class Broken:
        def __init__(self, *a, **k):
            pass

        def write(self, path):
            Path(path).write_bytes(b"v/1\x01 truncated")
            raise KeyboardInterrupt

    monkeypatch.setattr(OpenEXR, "File", Broken)
    with pytest.raises(KeyboardInterrupt):
        _io.write_outputs(str(out), img * 2, {"k": 2})
    monkeypatch.undo()
    assert np.array_equal(_io.read_exr(out), img)  # the old file is intact
    assert json.loads((tmp_path / "a.json").read_text())["k"] == 1
    assert _io.check_outputs(str(out)) == []  # and the set still belongs together
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.json", "a.png"]


def test_progress_throttled():
    s = io.StringIO()
    bar = _io.Progress(total=100, time_budget=None, stream=s)
    for i in range(1, 101):
        bar.update(i, i * 1e-3)
    bar.close()
    text = s.getvalue()
    assert text.endswith("\n") and text.count("\n") == 1
    assert 1 <= text.count("\r") <= 3  # first, final, maybe one more
    assert "100/100" in text and "passes/s" in text and "ETA" in text
    s2 = io.StringIO()
    quiet = _io.Progress(total=None, time_budget=5.0, enabled=False, stream=s2)
    quiet.update(1, 0.1)
    quiet.close()
    assert s2.getvalue() == ""


def test_progress_says_compiling_first():
    # until the first pass (which includes the compilation) is done the line says so
    s = io.StringIO()
    bar = _io.Progress(total=4, time_budget=None, stream=s)
    bar.start()
    assert s.getvalue() == "\rrender: compiling (the first pass includes the compilation) ..."
    bar.update(1, 30.0)
    bar.close()
    last = s.getvalue().split("\r")[-1]
    assert last.startswith("render: 1/4 passes") and "compiling" not in last


def test_snapshot_clock_starts_after_first_pass(tmp_path, monkeypatch):
    # a first pass of 0.6 s (the compilation) then fast passes, snapshots every 0.3 s: the
    # first snapshot comes 0.3 s after the first pass, never right after it (with the
    # clock started at t0 it would be the 1-pass image: 0.6 s >= 0.3 s)
    import jaxvcm._render as R

    writes = []
    monkeypatch.setattr(R._io, "write_outputs",
                        lambda out, img, meta, exposure=0.0, layers=None: writes.append(meta["passes"]))

    def run_pass(i):
        time.sleep(0.6 if i == 0 else 0.05)
        return np.ones((2, 2, 3)), 0

    R.progressive(run_pass, lambda m: m, lambda n, *a: {"passes": n}, passes=12,
                  out=str(tmp_path / "s.exr"), snapshot_every=0.3, progress=False)
    assert writes[-1] == 12 and len(writes) >= 2  # snapshots, then the final set
    assert writes[0] >= 2


# ------------------------------------------------------------------ render
def _check_outputs(exr: Path, shape=(16, 16, 3), snapshot=None) -> dict:
    import matplotlib.image as mpimg
    import OpenEXR

    img = _io.read_exr(exr)
    assert img.shape == shape and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    f = OpenEXR.File(str(exr))
    px = f.channels()["RGB"].pixels
    assert px.shape == shape and px.dtype == np.float32 and np.array_equal(px, img)
    png = mpimg.imread(exr.with_suffix(".png"))
    assert png.shape[:2] == shape[:2] and png.shape[2] in (3, 4)
    meta = json.loads(exr.with_suffix(".json").read_text())
    assert META_KEYS <= set(meta)
    assert meta["width"] == shape[1] and meta["height"] == shape[0] and meta["passes"] >= 1
    if snapshot is not None:
        assert meta["snapshot"] is snapshot
    return meta


def _visible(d: Path) -> set[str]:
    return {p.name for p in d.iterdir() if not p.name.startswith(".")}


def test_render_tiny_default_out(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    rc = main(["render", POOL, *TINY, "--passes", "2", "--seed", "3", "--exposure", "-1"])
    out, _ = capsys.readouterr()
    assert rc == 0
    exr = tmp_path / "out" / "pool.exr"
    assert out.strip() == os.path.join("out", "pool.exr")
    meta = _check_outputs(exr, snapshot=False)
    # vcm is the default algorithm
    assert meta["passes"] == 2 and meta["seed"] == 3 and meta["algorithm"] == "vcm"
    assert meta["config"]["max_depth"] == 3 and meta["scene"] == POOL
    assert meta["nonfinite"] == 0
    assert _visible(tmp_path / "out") == {"pool.exr", "pool.png", "pool.json"}
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]


def _start_render(out: Path, log: Path):
    args = [sys.executable, "-m", "jaxvcm.cli", "render", POOL, *TINY, "--algorithm", "pt",
            "--time", "120",
            "--snapshot-every", "0.5", "--out", str(out)]
    # The child starts with SIGINT at its default disposition whatever the harness does: a
    # test run started as a shell's background job ignores SIGINT, children inherit
    # "ignored", and Python then installs no KeyboardInterrupt handler. (pytest-xdist
    # workers keep the default handler. A render that runs to its time limit after SIGINT
    # is a different failure: a signal mask left blocked on the thread, which
    # `_io._images._signals_held` must not do.)
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=open(log, "w"),
                            env=_env(), cwd=out.parent,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(proc, path: Path, log: Path, timeout=90.0):
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"render exited with {proc.returncode}: {log.read_text()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            pytest.fail(f"no snapshot after {timeout} s: {log.read_text()}")
        time.sleep(0.05)


def _check_dir_after_kill(d: Path, name="pool"):
    assert _visible(d) == {f"{name}.exr", f"{name}.png", f"{name}.json"}
    for p in d.iterdir():  # an orphaned temp file may remain, but never under a real name;
        if p.name.startswith("."):  # and a killed render's (released) lock file
            assert (".tmp" in p.name and not p.name.endswith((".exr", ".png", ".json"))
                    or p.name == f".{name}.exr.lock"), p.name


def test_render_sigkill_leaves_snapshot(tmp_path):
    out = tmp_path / "pool.exr"
    log = tmp_path / "log.txt"
    proc = _start_render(out, log)
    try:
        _wait_for(proc, out, log)
        time.sleep(2.0)
        assert proc.poll() is None, log.read_text()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    log.unlink()
    _check_dir_after_kill(tmp_path)
    _check_outputs(out, snapshot=True)
    _io.recover_outputs(str(out))  # what the next render to `out` does first
    assert _io.check_outputs(str(out)) == []
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_render_sigint_exits_130_with_snapshot(tmp_path):
    out = tmp_path / "pool.exr"
    log = tmp_path / "log.txt"
    proc = _start_render(out, log)
    try:
        _wait_for(proc, out, log)
        time.sleep(1.0)
        rc = _stop(proc, signal.SIGINT, log)
    finally:
        _reap(proc)
    err = log.read_text()
    assert rc == 130, err
    last = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip()][-1]
    assert last.startswith("jaxvcm: interrupted"), err
    assert "Traceback" not in err
    log.unlink()
    _check_dir_after_kill(tmp_path)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # cleaned up
    # the set on disk is the interrupted render's own, of every pass it did (not the last
    # snapshot's); SIGINT is held back while it is written: the set is whole
    assert _check_outputs(out, snapshot=False)["interrupted"] == "SIGINT"
    assert _io.check_outputs(str(out)) == []


def _start_plain_render(out: Path, log: Path):
    """`_start_render` without snapshots: nothing is on disk until the render ends."""
    args = [sys.executable, "-m", "jaxvcm.cli", "render", POOL, *TINY, "--algorithm", "pt",
            "--time", "120", "--snapshot-every", "1e9", "--out", str(out)]
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=open(log, "w"),
                            env=_env(), cwd=out.parent,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _passes_shown(log: Path) -> int:
    done = re.findall(r"render: (\d+) passes", log.read_text())
    return int(done[-1]) if done else 0


def _reap(proc) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def _stop(proc, sig, log: Path) -> int:
    proc.send_signal(sig)
    try:
        return proc.wait(timeout=150)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"no exit 150 s after {sig!r}: {log.read_text()}")


@pytest.mark.parametrize("sig,status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["sigint", "sigterm"])
def test_render_signal_keeps_the_passes_it_has(tmp_path, sig, status):
    # no snapshot is due (one every 1e9 s): the image set on disk after the signal is the
    # one the interrupted render writes of its own passes, at least the ones shown before
    # the signal; exit 128 + the signal's number, one line saying what was kept
    out, log = tmp_path / "pool.exr", tmp_path / "log.txt"
    proc = _start_plain_render(out, log)
    try:
        t0 = time.monotonic()
        while _passes_shown(log) < 2:
            if proc.poll() is not None:
                pytest.fail(f"render exited with {proc.returncode}: {log.read_text()}")
            if time.monotonic() - t0 > 90:
                pytest.fail(f"no pass after 90 s: {log.read_text()}")
            time.sleep(0.05)
        assert not out.exists()
        shown = _passes_shown(log)
        rc = _stop(proc, sig, log)
    finally:
        _reap(proc)
    err = log.read_text()
    assert rc == status, err
    last = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip()][-1]
    name = signal.Signals(sig).name
    assert re.fullmatch(rf"jaxvcm: interrupted \({name}\) after \d+ passes: .*pool\.exr",
                        last), err
    assert "Traceback" not in err
    log.unlink()
    _check_dir_after_kill(tmp_path)
    meta = _check_outputs(out, snapshot=False)
    assert meta["passes"] >= shown and meta["interrupted"] == name
    assert f"after {meta['passes']} passes" in last
    assert _io.check_outputs(str(out)) == []


def test_render_signals_at_random_moments_are_never_lost(tmp_path):
    # SIGINT at random moments once the command runs (compiling, mid-pass, writing; before
    # that, Python is still importing jax and its own handler applies): the render always
    # ends, 130, with either nothing written (before its first pass) or a whole set of the
    # passes it had; never a run to the time limit (a lost signal)
    rng = np.random.default_rng(7)
    for k, delay in enumerate(rng.uniform(0.0, 6.0, 3)):
        d = tmp_path / f"r{k}"
        d.mkdir()
        out, log = d / "pool.exr", d / "log.txt"
        proc = _start_plain_render(out, log)
        try:
            t0 = time.monotonic()
            while "render: " not in log.read_text():
                if proc.poll() is not None or time.monotonic() - t0 > 90:
                    pytest.fail(f"render not started ({proc.poll()}): {log.read_text()}")
                time.sleep(0.02)
            time.sleep(delay)
            if proc.poll() is not None:
                pytest.fail(f"render exited with {proc.returncode}: {log.read_text()}")
            t0 = time.monotonic()
            rc = _stop(proc, signal.SIGINT, log)
            assert time.monotonic() - t0 < 60, log.read_text()
        finally:
            _reap(proc)
        err = log.read_text()
        assert rc == 130, err
        assert "Traceback" not in err
        if out.exists():
            assert _check_outputs(out, snapshot=False)["interrupted"] == "SIGINT"
            assert _io.check_outputs(str(out)) == []
        else:
            assert "nothing written" in err, err


# ------------------------------------------------------------------ export / info
@pytest.mark.parametrize("ext", ["glb", "ply", "obj"])
def test_export(ext, tmp_path, capsys):
    import trimesh

    path = tmp_path / f"pool.{ext}"
    assert main(["export", POOL, str(path)]) == 0
    mesh = trimesh.load(str(path), force="mesh")
    assert len(mesh.faces) > 0
    lo, hi = mesh.bounds
    assert np.allclose(lo, [-1.0, -1.2, -1.0], atol=1e-4)
    assert hi[1] == pytest.approx(3.0, abs=1e-4)  # the light
    if ext == "glb":
        sc = trimesh.load(str(path))
        assert "water" in sc.geometry and len(sc.geometry) == 7  # 5 basin + light + water
        water = sc.geometry["water"]
        assert np.all(water.face_normals[:, 1] > 0)
        assert abs(water.vertices[:, 1]).max() <= 0.0281


def test_info(capsys):
    assert main(["info", POOL]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert "pool" in out and "light 0: rect" in out and "1200" in out
    assert "sigma_a" in out and "ior 1.33" in out and "isotropic" in out
    assert "bounds" in out and "256 x 256" in out
