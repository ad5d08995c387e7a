"""Full paths from two subpaths: the per-vertex pdfs of a path formed by joining a light
subpath to a camera subpath (by a connection or a merge), and its MIS weight.

A technique (s, t) joins light vertices y_0..y_{s-1} to camera vertices z_{t-1}..z_0; the
full path x_0..x_k (k = s + t - 1) takes its light-side pdfs A and camera-side pdfs B from
the stored subpaths, except the four the join changes (pbrt's `MISWeight`):
    A(z_{t-1}), A(z_{t-2})  light-side pdfs of the two camera vertices nearest the join,
    B(y_{s-1}), B(y_{s-2})  camera-side pdfs of the two light vertices nearest the join.
`weight` hands the assembled arrays to the explicit sums (`_mis.py`) or to the recursive
form (`_mis_recursive.py`). The renderer does not assemble (except for ppm): the explicit
form builds each subpath's partial sums once (`light_partials`, `camera_partials`), the
recursive form carries dVCM / dVC / dVM along each subpath as it is traced (`carried`),
and each technique adds its join (`mis_join(cfg)`, `family_join_weights`);
`joins_partials(cfg)` says which.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _mis, _mis_partial, _mis_recursive
from . import _subpath as subpath
from ._config import RenderConfig
from ._subpath import PathEnds
from ._vec import Vec3, length


def both_dispersed(C: int, a, b):
    """1/C where both subpaths carry the dispersion factor C (it counts once per full path:
    `_materials` doc), else 1. [...] -> [..., 1] to scale [..., C] contributions."""
    return jnp.where(a & b, 1.0 / C, 1.0)[..., None]


class Pdfs(NamedTuple):
    """The part of a subpath the MIS assembly needs (per lane: [V])."""

    A: Array
    B: Array
    q: Array
    delta: Array
    medium: Array


def pdfs(e: PathEnds) -> Pdfs:
    return Pdfs(e.A, e.B, e.q, e.delta, e.medium)


def reverse_pdf(scene, kind, mat, n: Vec3, p: Vec3, w_from: Vec3, w_to: Vec3, q: Vec3,
                q_medium, q_n: Vec3, seg_water):
    """p(q | v) in q's area (volume) measure, for one lane: the BSDF / phase pdf at the
    vertex v = (kind, mat, n, p) of scattering a path that arrives from direction `w_from`
    into `w_to` (pointing at q), times the solid angle -> area factor at q
    (`_subpath.to_area`; `seg_water`: the segment v-q runs through the water). Returns
    (area pdf, solid-angle pdf). This is the pdf through the neighbouring vertex that every
    join re-evaluates on both sides."""
    pdf_w = subpath.bsdf_pdf(scene, kind, mat, None, w_from, w_to, n)
    dv = q - p
    d = length(dv)
    return pdf_w * subpath.to_area(1.0, q_medium, q_n, dv / jnp.maximum(d, 1e-30), d,
                                   seg_water, scene.water), pdf_w


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


def log_n_light_tracing(cfg: RenderConfig, n_paths, dtype):
    """log of light tracing's sample count relative to the camera techniques, per pixel:
    each of the N = pixels * spp light paths splats once (n = N per pixel, Veach 1997
    10.3.4) while a pixel has spp camera paths, so n_LT / n_camera = N / spp = pixels.
    `n_paths` is a chunk's count: every chunk's light paths splat (`RenderConfig.chunks`)."""
    return jnp.log(jnp.asarray(n_paths * cfg.chunks // cfg.spp, dtype))


def weight(cfg: RenderConfig, s, t, lig: Pdfs, cam: Pdfs, A_s, A_s1, B_s1, B_s2,
           delta_light, infinite_light, log_n_lt, log_eta_surf=0.0, log_eta_med=0.0,
           merge=False):
    """MIS weight of technique (s, t) for one path (all arguments per lane); with `merge`
    the technique is merging at x_s (camera vertex z_{t-1} with the photon y_s)."""
    a, b, delta, medium = path_pdfs(cfg, s, t, lig, cam, A_s, A_s1, B_s1, B_s2)
    beta = 2.0 if cfg.mis == "power" else 1.0
    k = s + t - 1
    log_eta = jnp.where(medium, log_eta_med, log_eta_surf)
    mis_fn = _mis_recursive.mis_weight_recursive if cfg.mis_form == "recursive" else _mis.mis_weight
    w = mis_fn(jax.lax.stop_gradient(a), jax.lax.stop_gradient(b), delta, k, s,
               delta_light, infinite_light, log_n_lt, cfg.algorithm, beta,
               jax.lax.stop_gradient(log_eta), merge)
    return jax.lax.stop_gradient(w)


def family_weights(cfg, s, t, lig: Pdfs, lig_axis, cam: Pdfs, cam_axis, A_s, A_s1, B_s1, B_s2,
                   delta_light, infinite_light, log_n_lt, etas=(0.0, 0.0)):
    """Weights [J, N] for a family of connection techniques: s, t [J]; overrides [J, N];
    subpath pdfs with their lane axis given (an axis spec of (outer J, inner N) for each);
    etas: `log_etas(radius, N)` for algorithms with merging."""
    inner = jax.vmap(weight, in_axes=(None, None, None, lig_axis[1], cam_axis[1], 0, 0, 0, 0,
                                      0, 0, None, None, None))
    outer = jax.vmap(inner, in_axes=(None, 0, 0, lig_axis[0], cam_axis[0], 0, 0, 0, 0, 0, 0,
                                     None, None, None))
    J, N = A_s.shape
    bc = lambda x: jnp.broadcast_to(x, (J, N))  # noqa: E731
    return outer(cfg, jnp.asarray(s, jnp.int32), jnp.asarray(t, jnp.int32), lig, cam, A_s,
                 bc(A_s1), bc(B_s1), bc(B_s2), bc(delta_light), bc(infinite_light), log_n_lt,
                 etas[0], etas[1])


# ---------------------------------------------------------------- O(1) per technique
def joins_partials(cfg: RenderConfig) -> bool:
    """The renderer weights each technique at its join from per-subpath quantities: the
    explicit form's partial sums (`_mis_partial.py`) or the recursive form's records
    carried along the subpaths (`_mis_recursive.carry_step`), except for ppm (merging at
    the first non-delta camera vertex only), which assembles its paths."""
    return cfg.techniques.merging != "first"


def mis_join(cfg: RenderConfig):
    """The module whose `entries`, `start_entries`, `join` and `join_weight` weight the
    techniques at their joins: `_mis_partial` (explicit) or `_mis_recursive` (recursive);
    the same signatures."""
    return _mis_recursive if cfg.mis_form == "recursive" else _mis_partial


def carried(cfg: RenderConfig, ends: PathEnds, etas=(0.0, 0.0)):
    """`_mis_recursive.Carried` of a subpath traced with the recursive form's carry."""
    sg = jax.lax.stop_gradient
    return _mis_recursive.carried(cfg, sg(ends.mis.rec), ends.mis.zero, sg(ends.q), ends.delta,
                                  ends.medium, sg(etas))


def no_light_partials(cfg: RenderConfig, N: int, dt, etas=(0.0, 0.0)):
    """Light partials standing in for an empty light subpath (s = 0 reads none of it)."""
    if cfg.mis_form == "recursive":
        return _mis_recursive.lone_start(cfg, (N,), dt)
    one = jnp.ones((1, N), dt)
    f = jnp.zeros((1, N), bool)
    return light_partials(cfg, Pdfs(one, one, one, f, f), jnp.zeros((N,), bool), etas)


def pinhole_partials(cfg: RenderConfig, log_n_lt, dt, etas=(0.0, 0.0)):
    """Camera partials of the pinhole z_0 alone (light tracing's camera side), [1, 1] lanes."""
    if cfg.mis_form == "recursive":
        return _mis_recursive.lone_start(cfg, (1,), dt)
    N0 = jnp.ones((1, 1), dt)
    f0 = jnp.zeros((1, 1), bool)
    return camera_partials(cfg, Pdfs(N0, N0, N0, f0, f0), log_n_lt, etas)


def light_partials(cfg: RenderConfig, lig: Pdfs, delta_light, etas=(0.0, 0.0)):
    """`_mis_partial.Partials` of light subpaths: lig fields [M, *lanes] -> [..., *lanes]."""
    sg = jax.lax.stop_gradient
    return _mis_partial.light(cfg, sg(lig.A), sg(lig.B), sg(lig.q), lig.delta, lig.medium,
                              delta_light, sg(etas))


def camera_partials(cfg: RenderConfig, cam: Pdfs, log_n_lt, etas=(0.0, 0.0)):
    """`_mis_partial.Partials` of camera subpaths: cam fields [M, *lanes] -> [..., *lanes]."""
    sg = jax.lax.stop_gradient
    return _mis_partial.camera(cfg, sg(cam.A), sg(cam.B), sg(cam.q), cam.delta, cam.medium,
                               sg(log_n_lt), sg(etas))


def both_partials(cfg: RenderConfig, lig: Pdfs, cam: Pdfs, delta_light, log_n_lt,
                  etas=(0.0, 0.0)):
    """(light, camera) partials in one call over both subpaths' lanes (one copy of the
    builder in the compiled program): the light subpaths [M_l, N] are padded to the camera
    subpaths' length [M_c, N] (the padding is never read)."""
    Ml, N = lig.A.shape
    Mc = cam.A.shape[0]
    sg = jax.lax.stop_gradient

    def cat(a, b, fill):
        pad = jnp.full((Mc - Ml, N), fill, a.dtype)
        return jnp.concatenate([jnp.concatenate([a, pad]), b], axis=1)

    P = _mis_partial.subpath(
        cfg, sg(cat(lig.A, cam.A, 1)), sg(cat(lig.B, cam.B, 1)), sg(cat(lig.q, cam.q, 1)),
        cat(lig.delta, cam.delta, False), cat(lig.medium, cam.medium, False),
        jnp.arange(2 * N) >= N,
        jnp.concatenate([jnp.broadcast_to(delta_light, (N,)), jnp.zeros((N,), bool)]),
        sg(log_n_lt), sg(etas))
    return (jax.tree.map(lambda a: a[..., :N], P), jax.tree.map(lambda a: a[..., N:], P))


def family_join_weights(cfg: RenderConfig, s, t, L, C, A_s, A_s1, B_s1, B_s2, delta_light,
                        infinite_light, log_n_lt):
    """Weights [J, N] of a family of connection techniques by `_mis_partial.join`: s, t [J]
    (static: each technique's entries are static slices of the partials); overrides
    [J, N]; C, L: camera and light partials with fields [..., N]. (Emitter hits; the
    queued techniques of `_connect` take `_mis_partial.join_weight` per item.)"""
    s = np.asarray(s, np.int32)
    t = np.asarray(t, np.int32)
    sg = jax.lax.stop_gradient
    mj = mis_join(cfg)
    Le = mj.entries(cfg, L, s, t)
    Ce = mj.entries(cfg, C, t, s)
    w = mj.join(cfg, s[:, None], t[:, None], Le, Ce, sg(A_s), sg(A_s1), sg(B_s1),
                sg(B_s2), delta_light, infinite_light, sg(log_n_lt))
    return sg(w)
