"""The full-path MIS oracle: a technique's path assembled from two subpaths' stored pdfs
(with the four pdfs its join re-evaluates) and weighted by the full-path sums
(`jaxvcm._mis.mis_weight`, or `mis_weight_recursive` for mis_form "recursive"). The
renderer never assembles paths: it weights each technique at its join
(`jaxvcm._mis.AbstractMIS`); the tests check those weights against this.

A technique (s, t) joins light vertices y_0..y_{s-1} to camera vertices z_{t-1}..z_0; the
full path x_0..x_k (k = s + t - 1) takes its light-side pdfs A and camera-side pdfs B from
the stored subpaths, except the four the join changes (pbrt's `MISWeight`):
    A(z_{t-1}), A(z_{t-2})  light-side pdfs of the two camera vertices nearest the join,
    B(y_{s-1}), B(y_{s-2})  camera-side pdfs of the two light vertices nearest the join.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from jaxvcm import _subpath as subpath
from jaxvcm._config import RenderConfig
from jaxvcm._mis import mis_weight, mis_weight_recursive


class Pdfs(NamedTuple):
    """The part of a subpath the MIS assembly needs (per lane: [V])."""

    A: Array
    B: Array
    q: Array
    delta: Array
    medium: Array


def pdfs(e) -> Pdfs:
    return Pdfs(e.A, e.B, e.q, e.delta, e.medium)


def path_pdfs(cfg: RenderConfig, s, t, lig: Pdfs, cam: Pdfs, A_s, A_s1, B_s1, B_s2):
    """Full-path (a, b, delta) [Lmax] of technique (s, t) for one path: gather the stored
    subpath pdfs, apply the join overrides (A[s], A[s+1] if t >= 3, B[s-1] if s >= 1,
    B[s-2] if s >= 2) and the Russian roulette of each direction: a vertex's survival
    probability counts from whichever end generates the next vertex."""
    Lmax = cfg.max_depth + 1
    k = s + t - 1
    i = jnp.arange(Lmax, dtype=jnp.int32)
    li = jnp.clip(i, 0, lig.A.shape[0] - 1)
    ci = jnp.clip(k - i, 0, cam.A.shape[0] - 1)
    from_l = i < s

    def g(fl, fc):
        return jnp.where(from_l, fl[li], fc[ci])

    A, B, q, delta = g(lig.A, cam.A), g(lig.B, cam.B), g(lig.q, cam.q), g(lig.delta, cam.delta)
    medium = g(lig.medium, cam.medium)
    A = jnp.where(i == s, A_s, A)
    A = jnp.where((i == s + 1) & (t >= 3), A_s1, A)
    B = jnp.where((i == s - 1) & (s >= 1), B_s1, B)
    B = jnp.where((i == s - 2) & (s >= 2), B_s2, B)
    q_prev = jnp.concatenate([jnp.ones((1,), q.dtype), q[:-1]])
    q_next = jnp.concatenate([q[1:], jnp.ones((1,), q.dtype)])
    a = A * jnp.where(i >= 1, subpath.rr(i - 1, q_prev, cfg), 1.0)
    b = B * jnp.where(i < k, subpath.rr(k - i - 1, q_next, cfg), 1.0)
    return a, b, delta & (i <= k), medium


def weight(cfg: RenderConfig, s, t, lig: Pdfs, cam: Pdfs, A_s, A_s1, B_s1, B_s2,
           delta_light, infinite_light, log_n_lt, log_eta_surf=0.0, log_eta_med=0.0,
           merge=False):
    """MIS weight of technique (s, t) for one path (all arguments per lane); with `merge`
    the technique is merging at x_s (camera vertex z_{t-1} with the photon y_s)."""
    a, b, delta, medium = path_pdfs(cfg, s, t, lig, cam, A_s, A_s1, B_s1, B_s2)
    beta = 2.0 if cfg.mis == "power" else 1.0
    k = s + t - 1
    log_eta = jnp.where(medium, log_eta_med, log_eta_surf)
    mis_fn = mis_weight_recursive if cfg.mis_form == "recursive" else mis_weight
    w = mis_fn(jax.lax.stop_gradient(a), jax.lax.stop_gradient(b), delta, k, s,
               delta_light, infinite_light, log_n_lt, cfg.algorithm, beta,
               jax.lax.stop_gradient(log_eta), merge)
    return jax.lax.stop_gradient(w)
