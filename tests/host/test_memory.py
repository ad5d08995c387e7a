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
chunk; a budget too small for one chunk is one error line.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import _memory
from jaxvcm._render import pass_key, render_pass
from jaxvcm.cli import main

ROOT = Path(__file__).resolve().parents[2]
SKY = ROOT / "scenes" / "pool_sky.toml"
PASSES = 400


def _pass_means(scene, cfg, n):
    """Image means of n passes (one jitted pass at a time: under vmap the queues' conds
    would become selects and every round would run)."""
    f = jax.jit(render_pass, static_argnums=2)
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
    assert _memory.device_budget(jax.devices("cpu")[0]) is None  # the CPU reports none


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
