"""Passes in bounded memory (`RenderConfig.tuning.chunks`, jaxvcm/_memory.py).

A chunked pass traces its paths in `chunks` groups one after the other: chunk c's camera
vertices merge with chunk c's photons only (eta = pi r^2 N/chunks), while every chunk's
light paths splat onto the whole film with 1/N (light tracing's count stays N). It is a
different unbiased estimator of the same image, so the test is statistical: the image mean
of VCM (every technique: emitter hits, NEE, light tracing, connections, merging) over 400
independent passes, chunks = 4 against chunks = 1, agrees within 4 combined standard
errors, and each standard error is below 1/4 of 5 % of the mean, so a 5 % bias (say, light
tracing counted once per chunk, a 4x error, or merges normalised by N instead of N/chunks)
would fail. The memory budget's chunk count comes from XLA's memory analysis of a probe
chunk; a budget too small for one chunk is one error line. On the CPU the budget is the
host's available memory (mocked small here), less the image's host buffers; an image
whose buffers or film cannot fit is refused in one line before anything is compiled.
Every index is int32 (x64 off): a chunk's largest index space is `index_factor` items per
path (checked against the traced program's array sizes), so the largest image of the
format lowers in the chunks `min_chunks` gives, and one chunk of it is refused.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import _memory
from jaxvcm._config import MAX_DEPTH
from jaxvcm._integrator import fewest_chunks, index_factor, max_chunk_paths, min_chunks
from jaxvcm._io._schema import MAX_PIXELS
from jaxvcm._render import pass_key, render_pass
from jaxvcm.cli import main

from .. import _analytic as A

ROOT = Path(__file__).resolve().parents[2]
SKY = ROOT / "scenes" / "pool_sky.toml"
PASSES = 400


def _pass_means(scene, cfg, n):
    """Image means of n passes (one jitted pass at a time: under vmap the queues' conds
    would become selects and every round would run); hundreds of passes: the optimised
    program (tests/_analytic.py)."""
    f = A.long_run_jit(render_pass, static_argnums=2)
    means = []
    for i in range(n):
        img, diag = f(scene, pass_key(11, i), cfg, jnp.int32(i))
        assert not bool(diag.merge_overflow) and int(diag.nonfinite) == 0
        means.append(float(np.mean(np.asarray(img, np.float64))))
    m = np.asarray(means)
    return m.mean(), m.std(ddof=1) / np.sqrt(n), int(diag.light_paths)


def test_chunked_vcm_agrees_with_one_chunk():
    scene = jaxvcm.load_scene(SKY, width=16, height=12)
    res = {}
    for ch in (1, 4):
        cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=4).tuned(chunks=ch)
        res[ch] = _pass_means(scene, cfg, PASSES)
    (m1, s1, n1), (m4, s4, n4) = res[1], res[4]
    assert n1 == n4 == 16 * 12  # the same light paths per pass, in 4 chunks of 48
    for m, s in ((m1, s1), (m4, s4)):
        assert m > 0 and s < 0.05 * m / 4, (m, s)  # a 5 % difference is > 4 SE
    z = (m4 - m1) / np.hypot(s1, s4)
    assert abs(z) < 4, f"chunks=4 mean {m4:.5g} vs one chunk {m1:.5g}: {z:.2f} SE"


def test_chunks_must_divide_the_paths():
    scene = jaxvcm.load_scene(SKY, width=16, height=12)
    cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2).tuned(chunks=5)
    with pytest.raises(ValueError,
                       match=r"^config.tuning.chunks: 5 does not divide the pass's 192 "):
        render_pass(scene, pass_key(0, 0), cfg)


@pytest.mark.parametrize("text,value", [("512", 512), ("4K", 4096), ("1.5m", 1572864),
                                        ("2GB", 2 << 30), (" 1t ", 1 << 40)])
def test_parse_bytes(text, value):
    assert _memory.parse_bytes(text) == value


@pytest.mark.parametrize("text", ["", "4Q", "-1G", "0", "1e9", "G"])
def test_parse_bytes_rejects(text):
    with pytest.raises(ValueError, match="^memory: "):
        _memory.parse_bytes(text)


@pytest.mark.parametrize("budget,chunks", [
    (768 * 1000, 1),  # 32 x 24 = 768 paths at 1000 B each: the whole pass fits
    (384 * 1000, 2),  # 384 paths per chunk
    (300 * 1000, 3),  # 256 paths: the fewest chunks dividing 768 with <= 300 paths
])
def test_chunks_for_memory_is_the_fewest_that_fit(budget, chunks):
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    assert _memory.chunks_for_memory(scene, cfg, budget, model=(0.0, 1000.0)) == chunks


def test_chunks_for_memory_below_the_smallest_chunk():
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    with pytest.raises(ValueError, match=r"^memory: 200000 bytes is too small for one "
                                         r"chunk: 256 paths need about 256000 bytes"):
        _memory.chunks_for_memory(scene, cfg, 200_000, model=(0.0, 1000.0))


def test_memory_budget_too_small_is_one_line(capsys, tmp_path, monkeypatch):
    """Through the CLI, with the real probe (XLA's memory analysis of PT at depth 2)."""
    monkeypatch.chdir(tmp_path)
    rc = main(["render", str(SKY), "--algorithm", "pt", "--passes", "1", "--width", "16",
               "--height", "12", "--max-depth", "2", "--quiet", "--memory", "1K"])
    _, err = capsys.readouterr()
    assert rc == 2, err
    assert err.startswith("jaxvcm: error: memory: 1024 bytes is too small for one chunk: ")
    assert len(err.strip().splitlines()) == 1
    scene = jaxvcm.load_scene(SKY, width=16, height=12)
    fixed, per = _memory.memory_model(scene, jaxvcm.RenderConfig(algorithm="pt", max_depth=2))
    assert fixed == 0.0 and 100 < per < 1e6  # 192 paths: one probe, all charged per path


class _Dev:
    def __init__(self, stats):
        self.stats = stats

    def memory_stats(self):
        return self.stats


@pytest.mark.parametrize("stats", [None, {}, {"bytes_limit": 0}])
def test_no_device_memory_means_one_chunk(stats):
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    assert _memory.device_budget(_Dev(stats)) is None
    assert _memory.auto_chunks(scene, cfg, _Dev(stats)) == 1


def test_device_memory_sets_the_chunks(monkeypatch):
    """A device reporting 80 GB: a 32x24 VCM pass fits (no probe); one reporting 1 MB: the
    probe (here a fixed 1000 B per path) gives 768 paths / 800 paths' room -> 1 chunk, and
    with 375 kB (a 300 kB budget) -> 256-path chunks (3)."""
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: (0.0, 1000.0))
    assert _memory.auto_chunks(scene, cfg, _Dev({"bytes_limit": 80 << 30})) == 1
    assert _memory.device_budget(_Dev({"bytes_limit": 10**6})) == 800_000
    assert _memory.auto_chunks(scene, cfg, _Dev({"bytes_limit": 10**6})) == 1
    assert _memory.auto_chunks(scene, cfg, _Dev({"bytes_limit": 375_000})) == 3


def test_a_512_vcm_pass_in_a_budget_has_the_untiled_mean():
    """A 512x512 VCM pass (pool_sky, depth 2: emitter hits, NEE, light tracing, merging)
    under a 48 MiB budget: `chunks_for_memory` (two probe compiles) picks more than one
    chunk, and the pass completes without overflow or non-finite values. Its image agrees
    with 16 untiled passes at 128x128, where one chunk fits: a pixel is the box over its
    film area, so row block c (8 rows at 512, rows 2c, 2c + 1 at 128) has the same
    expected mean at both sizes, and the differences d_c of the 64 block means (spatial
    variation cancels) give z = mean(d) / SE(d) within 4, with SE(d) below 1.25 % of the
    mean so that a 5 % bias fails."""
    big = jaxvcm.load_scene(SKY, width=512, height=512)
    cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=2)
    k = _memory.chunks_for_memory(big, cfg, 48 << 20)
    assert k > 1 and (512 * 512) % k == 0
    f = jax.jit(render_pass, static_argnums=2)
    img, diag = f(big, pass_key(21, 0), jaxvcm.RenderConfig(algorithm="vcm", max_depth=2
                                                           ).tuned(chunks=k), jnp.int32(0))
    assert not bool(diag.merge_overflow) and int(diag.nonfinite) == 0
    a = np.asarray(img, np.float64).reshape(64, -1).mean(axis=1)
    small = jaxvcm.load_scene(SKY, width=128, height=128)
    ref = np.mean([np.asarray(f(small, pass_key(22, i), cfg, jnp.int32(i))[0], np.float64)
                   for i in range(16)], axis=0)
    b = ref.reshape(64, -1).mean(axis=1)
    d = a - b
    se = d.std(ddof=1) / np.sqrt(len(d))
    assert se < 0.05 * b.mean() / 4, (se, b.mean())
    z = d.mean() / se
    assert abs(z) < 4, f"512x512 in {k} chunks: mean {a.mean():.5g} vs {b.mean():.5g}, {z:.2f} SE"


# ---- the CPU's budget: the host's available memory
GIB = 1 << 30


def test_host_memory_is_read():
    """MemAvailable on Linux (at most the machine's memory), else the free pages."""
    avail = _memory.host_memory()
    assert avail is not None and 0 < avail
    with open("/proc/meminfo", encoding="ascii") as f:
        total = next(int(x.split()[1]) * 1024 for x in f if x.startswith("MemTotal:"))
    assert avail <= total


def test_host_memory_without_meminfo(monkeypatch):
    """No /proc/meminfo (another OS): the free pages of `os.sysconf`."""
    def no_file(*a, **k):
        raise OSError("no such file")

    monkeypatch.setattr(_memory, "open", no_file, raising=False)
    import os
    want = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    assert abs(_memory.host_memory() - want) < max(want // 4, 1 << 24)


def test_cpu_budget_is_the_hosts(monkeypatch):
    """The CPU, which reports no memory limit, gets DEVICE_SHARE of the host's available
    memory; a pass there that much less the image's host buffers, shared by the CPU
    devices that run at once."""
    cpu = jax.devices("cpu")[0]
    monkeypatch.setattr(_memory, "host_memory", lambda: 10 * GIB)
    assert _memory.device_budget(cpu) == int(0.8 * 10 * GIB)
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    host = _memory.host_bytes(scene)
    assert host == 24 * 32 * 24 * 3
    assert _memory.pass_budget(scene, cpu)[0] == int(0.8 * 10 * GIB) - host
    assert _memory.pass_budget(scene, cpu, devices=2)[0] == (int(0.8 * 10 * GIB) - host) // 2
    monkeypatch.setattr(_memory, "host_memory", lambda: None)
    assert _memory.device_budget(cpu) is None


def test_cpu_memory_sets_the_chunks(monkeypatch):
    """A host with little memory left: the probe (here a fixed 1000 B per path) gives
    chunks on the CPU as on a GPU: 768 paths in a 300 kB pass budget -> 3 chunks of 256;
    with plenty of memory the rough bound fits and nothing is probed."""
    scene = jaxvcm.load_scene(SKY, width=32, height=24)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    cpu = jax.devices("cpu")[0]
    probes = []
    monkeypatch.setattr(_memory, "memory_model",
                        lambda s, c: probes.append(1) or (0.0, 1000.0))
    host = _memory.host_bytes(scene)
    monkeypatch.setattr(_memory, "host_memory", lambda: int((300_000 + host) / 0.8) + 1)
    assert _memory.auto_chunks(scene, cfg, cpu) == 3 and probes == [1]
    monkeypatch.setattr(_memory, "host_memory", lambda: 64 * GIB)
    assert _memory.auto_chunks(scene, cfg, cpu) == 1 and probes == [1]


def test_cpu_render_in_chunks_from_host_memory(monkeypatch, tmp_path):
    """End to end on the CPU, with the real probe: a 32 x 32 PT pass (1024 paths) on a host
    whose memory leaves room for about 300 paths renders in 4 chunks of 256 (its record
    says so) to a finite, non-black image."""
    scene = jaxvcm.load_scene(SKY, width=32, height=32)
    cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2)
    fixed, per = _memory.memory_model(scene, cfg)
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: (fixed, per))
    need = fixed + 300 * per + _memory.host_bytes(scene)
    monkeypatch.setattr(_memory, "host_memory", lambda: int(need / 0.8) + 1)
    out = tmp_path / "c.exr"
    img = jaxvcm.render(scene, algorithm="pt", passes=1, config=cfg, out=str(out),
                        progress=False, devices=1)
    rec = json.loads(out.with_suffix(".json").read_text())
    assert rec["config"]["chunks"] == 4
    assert np.all(np.isfinite(img)) and img.mean() > 0


def test_film_beyond_the_cpu_budget_is_refused(monkeypatch):
    """The host buffers fit but the film does not fit what is left: one line, no probe."""
    scene = jaxvcm.load_scene(SKY, width=64, height=64)
    cpu = jax.devices("cpu")[0]
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: pytest.fail("probed"))
    monkeypatch.setattr(_memory, "host_memory", lambda: 32 * 64 * 64 * 3)  # 24 B + 8 B
    with pytest.raises(ValueError, match=r"^camera.width, camera.height: a 64 x 64 image is "
                                         r"too large for this memory: its film alone needs "):
        _memory.auto_chunks(scene, jaxvcm.RenderConfig(algorithm="pt"), cpu)


def test_fixed_part_beyond_the_budget_is_refused(monkeypatch):
    """A fixed part (by the probe, here mocked) larger than the device's budget: however
    many chunks, the pass cannot fit: one line naming the image and the memory."""
    scene = jaxvcm.load_scene(SKY, width=64, height=64)
    cfg = jaxvcm.RenderConfig(algorithm="vcm")
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: (2e6, 1000.0))
    with pytest.raises(ValueError) as e:
        _memory.auto_chunks(scene, cfg, _Dev({"bytes_limit": 10**6}))
    msg = str(e.value)
    assert msg.startswith("camera.width, camera.height: a 64 x 64 image is too large for this "
                          "memory: a pass in chunks of 256 paths needs about "), msg
    assert "more than the 0.000745 GiB this device has for a pass (80%)" in msg
    assert "\n" not in msg


def test_host_buffers_beyond_the_host_are_refused_by_the_cli(monkeypatch, capsys, tmp_path):
    """The largest image of the format (16384 x 16384) on a host with 1 GiB available:
    exit 2 and one line before anything is compiled (the running sum alone is 6 GiB)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(_memory, "host_memory", lambda: GIB)
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: pytest.fail("probed"))
    rc = main(["render", str(SKY), "--passes", "1", "--width", "16384", "--height", "16384",
               "--quiet"])
    _, err = capsys.readouterr()
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("jaxvcm: error: camera.width, camera.height: a 16384 x 16384 image "
                          "is too large for this memory: its running sum, mean and outputs "
                          "need about 18 GiB of host memory"), err


# ---- int32 indices
def _largest_dim(jaxpr) -> int:
    """The largest array dimension the program makes, but the uniforms' tables (uint32
    counters, below 2^32 by `_uniforms.Uniforms.draw`'s own check)."""
    from jax.extend import core

    best = 0
    for e in jaxpr.eqns:
        tb = e.source_info.traceback
        files = [f.file_name for f in (tb.frames if tb else []) if "jaxvcm" in f.file_name]
        if not (files and files[0].endswith("_uniforms.py")):
            for v in e.outvars:
                best = max([best] + list(getattr(v.aval, "shape", ())))
        for p in e.params.values():
            for sub in (p if isinstance(p, (list, tuple)) else [p]):
                if isinstance(sub, core.ClosedJaxpr):
                    best = max(best, _largest_dim(sub.jaxpr))
                elif isinstance(sub, core.Jaxpr):
                    best = max(best, _largest_dim(sub))
    return best


def test_index_factor_bounds_the_traced_arrays():
    """VCM at depth 8 with glints and manifold NEE (connections, merging, every queue):
    no array of the traced pass is longer than `index_factor` items per path (+ 1: the
    hash grid's bucket starts), so INDEX_ITEMS bounds every index of a chunk. A queue or
    table added without its factor fails here."""
    scene = jaxvcm.load_scene(SKY, width=128, height=128)  # N = 2^14: tables are exact
    cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=8, glints=True, manifold_nee=True)
    jp = jax.make_jaxpr(lambda s, k: render_pass(s, k, cfg))(scene, jax.random.key(0))
    n = 128 * 128
    got = _largest_dim(jp.jaxpr)
    # vertex connection's queue: next-event estimation 7 + light tracing 8 + 21 (s, t >= 2)
    # pairs = 36 techniques of N items, the largest index space; the glints' queue of the
    # roots: 8 light points x (the centre's + 2 more) = 24 items per path
    assert index_factor(cfg) == 36
    assert 20 * n < got <= index_factor(cfg) * n + 1, (got / n, index_factor(cfg))


def test_fewest_chunks():
    assert fewest_chunks(1024, 2048) == 1
    assert fewest_chunks(1024, 300) == 4
    assert fewest_chunks(7 * 16381, 100) == 16381  # 16381 is prime
    assert fewest_chunks(13, 1) == 13


def test_the_largest_image_lowers_in_chunks():
    """16384 x 16384 at 7 spp (the most a pass may have there: 2^31 - 1 paths), VCM at depth
    64 with glints (the largest index factor): one chunk is refused in one line; the chunks
    `min_chunks` gives lower (not run) with x64 off, where an int32 overflow of a Python
    constant is an OverflowError. 8 spp is refused as more than int32 path numbers."""
    scene = jaxvcm.load_scene(SKY, width=MAX_PIXELS, height=MAX_PIXELS)
    cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=MAX_DEPTH, glints=True, spp=7)
    lower = jax.jit(render_pass, static_argnums=2).lower
    with pytest.raises(ValueError, match=r"^config.tuning.chunks: chunks of 1879048192 paths "
                                         r"\(16384 x 16384 x 7 spp in 1\) are more than the "
                                         r"516222 whose indices fit int32 .* use at least 4096 "
                                         r"chunks"):
        lower(scene, jax.random.key(0), cfg)
    k = min_chunks(scene, cfg)
    # 2^30 // (63 + 64 + 1953 vertex-connection techniques) = 516222 paths per chunk: the
    # fewest chunks dividing 7 x 2^28 paths with at most that many is 2^12
    assert k == 4096 and MAX_PIXELS**2 * 7 // k <= max_chunk_paths(cfg)
    with jax.enable_x64(False):
        lower(scene, jax.random.key(0), cfg.tuned(chunks=k))
    with pytest.raises(ValueError, match=r"^config.spp: a pass of 16384 x 16384 x 8 spp = "
                                         r"2147483648 paths is more than 2147483647 "):
        lower(scene, jax.random.key(0), dataclasses.replace(cfg, spp=8).tuned(chunks=k))


def test_the_largest_image_gets_its_chunks_on_a_large_device(monkeypatch):
    """A device with room for a whole 16384 x 16384 pass still gets the chunks that keep
    its indices within int32 (no probe)."""
    scene = jaxvcm.load_scene(SKY, width=MAX_PIXELS, height=MAX_PIXELS)
    cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=8)
    monkeypatch.setattr(_memory, "memory_model", lambda s, c: pytest.fail("probed"))
    # 2^30 // 36 items per path (vertex connection at depth 8) = 29,826,161 paths a chunk:
    # 2^28 paths need 9 chunks, the fewest dividing them 16
    assert _memory.auto_chunks(scene, cfg, _Dev({"bytes_limit": 1 << 50})) == 16


def test_a_queue_beyond_int32_is_refused():
    """The queues' own check, behind `check_chunks`: one line, nothing traced."""
    from jaxvcm._queue import first_true

    with pytest.raises(ValueError, match=r"^config.tuning.chunks: a work queue of 8 items "):
        first_true(jnp.zeros((8,), bool), 1 << 31)
