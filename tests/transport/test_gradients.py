"""Gradients of rendered radiance w.r.t. water coefficients vs central finite differences.

Sampling is detached (distances, directions, pdfs, MIS weights) and the estimator weights
carry the gradient, so `jax.grad` of a pass is an unbiased estimate of d E[L] / d theta.
Central differences with common random numbers (the same keys at theta +- h) estimate the
same derivative up to O(h^2). Both are noisy: compare their means over independent keys
within K standard errors of the per-key difference, plus the O(h^2) allowance.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig

from .. import _analytic as A

K = 4.5


def mean_floor(scene, sigma_a, sigma_s, key, cfg):
    scene = eqx.tree_at(lambda s: (s.water.sigma_a, s.water.sigma_s), scene, (sigma_a, sigma_s))
    img, _ = jaxvcm.render_pass(scene, key, cfg)
    H, W = img.shape[:2]
    # central floor region (the walls and rim excluded)
    return jnp.mean(img[H // 4: 3 * H // 4, W // 4: 3 * W // 4], axis=(0, 1))


@pytest.fixture(scope="module")
def setup():
    """The scene, the functions and the AD gradients shared by both parameters: one
    reverse-mode program gives d/d sigma_a and d/d sigma_s of a key's pass together (one
    compilation and 32 passes instead of two of each)."""
    scene = jaxvcm.load_scene("scenes/pool_sky.toml", width=48, height=48)
    cfg = RenderConfig(max_depth=6, rr_depth=100)
    sa0 = scene.water.sigma_a
    ss0 = scene.water.sigma_s + jnp.asarray([0.3, 0.2, 0.1], sa0.dtype)  # make scattering matter

    def f(sa, ss, key):
        # sum over channels of the mean floor radiance, weighted per channel so a single
        # scalar exercises every channel's derivative
        return jnp.sum(mean_floor(scene, sa, ss, key, cfg) * jnp.asarray([1.0, 2.0, 3.0], sa.dtype))

    # 32 gradients and 384 finite-difference passes: the optimised programs (tests/_analytic.py)
    grad_f = A.long_run_jit(jax.grad(f, argnums=(0, 1)))
    keys = [jaxvcm.pass_key(7, i) for i in range(32)]
    g = [grad_f(sa0, ss0, k) for k in keys]
    g = {p: np.stack([np.asarray(gk[i]) for gk in g]) for i, p in enumerate(("sigma_a", "sigma_s"))}
    return sa0, ss0, A.long_run_jit(f), keys, g  # g: {param: [keys, C]}


@pytest.mark.parametrize("param", ["sigma_a", "sigma_s"])
def test_grad_matches_central_differences(param, setup):
    sa0, ss0, f_j, keys, grads = setup
    C = sa0.shape[0]
    g = grads[param]  # [keys, C]
    # sigma_s moves the sampled distances, so its CRN differences are discontinuous and
    # their variance grows like 1/h: use a wider step there. The O(h^2) error stays small
    # because E[L] is smooth: (h sigma d)^2 / 6 < 1e-3 for h = 20%, sigma d < 0.5.
    h = (0.05 if param == "sigma_a" else 0.2) * (sa0 if param == "sigma_a" else ss0)
    fd = []
    for k in keys:
        row = []
        for c in range(C):
            e = jnp.zeros(C, sa0.dtype).at[c].set(h[c])
            if param == "sigma_a":
                fp, fm = f_j(sa0 + e, ss0, k), f_j(sa0 - e, ss0, k)
            else:
                fp, fm = f_j(sa0, ss0 + e, k), f_j(sa0, ss0 - e, k)
            row.append(float((fp - fm) / (2 * h[c])))
        fd.append(row)
    fd = np.array(fd)
    diff = g - fd
    se = diff.std(0, ddof=1) / np.sqrt(len(keys))
    # O(h^2) allowance: relative curvature of exp(-sigma d) over h = 5% is ~ (0.05 sigma d)^2/6
    allow = 0.02 * np.abs(fd.mean(0)) + 1e-6
    err = np.abs(diff.mean(0))
    assert np.all(np.isfinite(g))
    assert np.all(err <= K * se + allow), (param, g.mean(0), fd.mean(0), se, allow)
    # the derivative is non-trivial (the test can fail): absorption darkens every channel
    if param == "sigma_a":
        assert np.all(g.mean(0) < -10 * (g.std(0) / np.sqrt(len(keys))))
