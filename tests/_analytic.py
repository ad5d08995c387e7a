"""Statistics of independent passes (per-pixel means and standard errors). The test scenes
are in `_scenes`."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm._render import render_pass


@functools.partial(jax.jit, static_argnums=(2, 3))
def _passes(scene, keys, config, _n):
    # lax.map, not vmap: a batched predicate would turn the renderer's lax.cond work-queue
    # skips into selects (every round runs, and the program compiles ~25 % longer)
    return jax.lax.map(lambda k: render_pass(scene, k, config), keys)


def render_stats(scene, config, passes, seed=0, batch=8):
    """Per-pixel samples of `passes` independent passes -> (mean image, per-pixel standard
    error of the mean, images [P, H, W, C], total non-finite count)."""
    imgs, bad = [], 0
    for b0 in range(0, passes, batch):
        n = min(batch, passes - b0)
        keys = jnp.stack([jaxvcm.pass_key(seed, b0 + i) for i in range(n)])
        img, diag = _passes(scene, keys, config, n)
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
