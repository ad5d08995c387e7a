"""Statistics of independent passes (per-pixel means and standard errors). The test scenes
are in `_scenes`."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm._render import render_pass, with_retry


def _passes_fn(scene, keys, config, _n):
    # lax.map, not vmap: a batched predicate would turn the renderer's lax.cond work-queue
    # skips into selects (every round runs, and the program compiles ~25 % longer)
    return jax.lax.map(lambda k: render_pass(scene, k, config), keys)


# The suite compiles at XLA's backend optimisation level 0 without fusion emitters
# (tests/conftest.py): most of its programs run for less time than their compilation takes.
# A statistics run of many paths is the other way round: at level 2 a 64 x 64 VCM pool pass
# (depth 8) runs 3.7x faster (71 ms vs 264 ms) for 3.8 s more compilation (13.6 s vs
# 9.8 s), so runs of at least 2^16 paths get the optimised program (test_delta_medium,
# 160 passes of 8 x 8 x 16 paths: 74 -> 38 s for the file; test_cornell, test_glossy_mis
# and test_caustics 159 -> 139 s on two workers). So do runs of many small
# passes, whose time is the per-pass work of the queues' rounds more than the paths: 1536
# passes of 8 x 8 paths (test_aim's view-guided pool) 70 -> 28 s for vcm and ppm. Same
# arithmetic either way.
OPTIMISED = {"xla_backend_optimization_level": 2}
LONG_RUN_PATHS = 2**16
LONG_RUN_PASSES = 512
_passes = jax.jit(_passes_fn, static_argnums=(2, 3))
_passes_optimised = jax.jit(_passes_fn, static_argnums=(2, 3), compiler_options=OPTIMISED)
_host_pass_optimised = jax.jit(render_pass, static_argnums=(2,), compiler_options=OPTIMISED)


def long_run_jit(fun, **kw):
    """`jax.jit` at XLA's default optimisation level, for a test's program that runs many
    passes (see `_passes_optimised`)."""
    return jax.jit(fun, compiler_options=OPTIMISED, **kw)


def render_pass_long(scene, key, config, pass_index=0):
    """`jaxvcm._render.render_pass_host` (the host's merge-capacity re-run included) with
    the optimised program, for loops of many passes."""
    return with_retry(_host_pass_optimised, scene, key, config, pass_index, lambda d: d, scene)


def render_stats(scene, config, passes, seed=0, batch=8):
    """Per-pixel samples of `passes` independent passes -> (mean image, per-pixel standard
    error of the mean, images [P, H, W, C], total non-finite count)."""
    imgs, bad = [], 0
    H, W = scene.camera.height, scene.camera.width
    long = passes * H * W * config.spp >= LONG_RUN_PATHS or passes >= LONG_RUN_PASSES
    run = _passes_optimised if long else _passes
    for b0 in range(0, passes, batch):
        n = min(batch, passes - b0)
        keys = jnp.stack([jaxvcm.pass_key(seed, b0 + i) for i in range(n)])
        img, diag = run(scene, keys, config, n)
        # merging results with an overflowed hash-grid gather are not estimates: refuse them
        # (raise config.tuning.merge_capacity; the host driver render_pass_host does that itself)
        assert not np.any(np.asarray(diag.merge_overflow)), "merge capacity overflow"
        imgs.append(np.asarray(img, np.float64))
        bad += int(np.sum(np.asarray(diag.nonfinite)))
    imgs = np.concatenate(imgs)
    mean = imgs.mean(0)
    se = imgs.std(0, ddof=1) / np.sqrt(imgs.shape[0])
    return mean, se, imgs, bad


def pooled(imgs):
    """Treat every pixel of every pass as one i.i.d. sample (valid when all pixels share the
    same expectation): (per-channel mean, per-channel standard error)."""
    x = imgs.reshape(-1, imgs.shape[-1])
    return x.mean(0), x.std(0, ddof=1) / np.sqrt(x.shape[0])
