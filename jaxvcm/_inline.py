"""PT's techniques evaluated inside the camera trace: emitter hits (s = 0) and next-event
estimation (s = 1) at each vertex as the trace round makes it, added into the path's
pixel value; no vertex records, no MIS tables, no technique queues.

With only PT's two techniques the explicit MIS sum of a technique at z_j has two terms,
both pdfs of the path's last vertex (`_mis._explicit.pt_weight`, derived there from the
general `join`): the camera's pdf of z_j with its roulette (carried one vertex along the
walk: `Carry`) against the light's pdf of the point. So the whole weight is known when
z_j is made, and a pass that only wants the image (`_integrator.integrate`) needs nothing
of the vertex once the round has moved on. The recorded route (`subpath.trace` records
[D, N], the per-subpath MIS state, the queued `_connect` techniques) costs every lane
per row of D: the record buffer's writes, the partial tables, the queues' masks and their
[D, N, C] outputs; this route has none of them (docs/design/performance.md). The
recorded route serves `technique_images` (one image per technique), the recursive MIS
form and every other algorithm.

Same samples, same image: every value is computed from the same quantities by the same
functions as on the recorded route (`_connect.emitter_hit_join_pdfs`, `nee_join_pdfs`,
the light sample's uniforms `u_nee[j - 1, n]`), and the weight equals `join`'s to the bit;
only the order in which a path's techniques are added differs (float32 round-off; the
inline tests, tests/subpath/test_inline.py, compare the two routes at fixed keys).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _connect as connect
from . import _geometry as geometry
from . import _lights as lights
from ._mis import _explicit as mis_partial
from . import _subpath as subpath
from . import _vec as vec
from ._config import RenderConfig
from ._queue import masked_map
from ._scene import DELTA_LIGHTS, Scene
from ._uniforms import Uniforms

NEE_SPLIT = 8  # rounds per sweep of a trace round's shadow-ray queue


class Carry(NamedTuple):
    """Per camera lane, carried by the walk (`subpath.WalkState.carry`): the roulette
    survival probability applied on the way to the next vertex (rr(j, q_j) leaving z_j:
    `subpath.step`'s q) and whether a pdf of the path so far is zero (`_mis._explicit`'s
    `Partials.zero`: the techniques at later vertices are then impossible)."""

    q_in: Array
    zero: Array


class _Z(NamedTuple):  # the fields of a camera vertex the join pdfs read
    p: vec.Vec3
    n: vec.Vec3
    wo: vec.Vec3
    kind: Array
    mat: Array
    medium: Array
    seg_water: Array


class _Prev(NamedTuple):  # z_{j-1}, as the walk state knows it
    p: vec.Vec3
    n: vec.Vec3
    medium: Array


def enabled(cfg: RenderConfig) -> bool:
    """The pass can evaluate its techniques in the trace: PT's techniques only (camera
    subpaths, emitter hits and / or next-event estimation), the explicit MIS form, no
    glints and no manifold next-event estimation (the emitter hits' share of their paths
    is evaluated at the emitter-hit stage)."""
    tech = cfg.techniques
    return (tech.camera_paths and not tech.light_paths and tech.merging is None
            and cfg.mis_form == "explicit" and not cfg.glints and not cfg.manifold_nee)


def start(s0: subpath.WalkState) -> subpath.WalkState:
    """The camera lanes' start states with the carry of z_0 (the pinhole: no roulette
    before z_1, its pdf 1)."""
    one = jnp.ones_like(s0.pdf_w)
    return s0._replace(carry=Carry(one, jnp.zeros(one.shape, bool)))


def uniforms(u_nee):
    """The light samples' uniforms as the rounds read them: hashed per item (lazy), or the
    table drawn once outside the trace's loop."""
    if u_nee is None or (isinstance(u_nee, Uniforms) and u_nee.lazy):
        return u_nee
    return u_nee.dense() if isinstance(u_nee, Uniforms) else u_nee


def estimate(scene: Scene, cfg: RenderConfig, u_nee, kg, g, live, s: subpath.WalkState,
             s_new: subpath.WalkState, v: subpath.Vertex):
    """The techniques at the vertices z_j (j = kg + 1) just made by a trace round for its
    lanes g ([W]; `live`: the lane is real, not padding): s = 0 if z_j sees emission, s = 1
    from z_j (j <= max_depth - 1). `s` / `s_new`: the lanes' walk states before and after
    the step (s.carry: the carry up to z_{j-1}); `u_nee`: the light samples' uniforms
    [D - 1, N, 3] (`uniforms`), None without next-event estimation.
    Returns (s_new with the carry moved on to z_j, each lane's contribution [W, C] with
    non-finite elements zeroed, their count, the number of live vertices)."""
    tech = cfg.techniques
    D = cfg.max_depth
    dt = v.pdf_fwd.dtype
    NEG = mis_partial.NEG
    lpos = mis_partial._log_pos
    sg = jax.lax.stop_gradient
    j = kg + 1
    real = v.alive & live

    # ---- the camera side of z_j: its pdf with the roulette before it, the zero flag ----
    # (`_mis._explicit.subpath`: local = B_j rr(j - 1, q_{j-1}); zero[j + 1])
    local = v.pdf_fwd * s.carry.q_in
    zero = s.carry.zero | ~(local > 0)
    lp = lpos(local, 0.0)
    s_new = s_new._replace(carry=Carry(subpath.rr(j, v.q, cfg), zero))
    z = _Z(v.p, v.n, v.wo, v.kind, v.mat, v.kind == subpath.KIND_MEDIUM, v.seg_water)
    zp = _Prev(s.p_prev, s.n_prev, s.prev_medium)

    def clean(c):  # the film's rule: non-finite elements zeroed and counted
        ok = jnp.isfinite(c)
        return jnp.where(ok, c, 0.0), jnp.sum(~ok, dtype=jnp.int32)

    # ---- s = 0: z_j on an emitter, or escaped to the sky (`_connect.emitter_hits`) ----
    total, bad = jnp.zeros(v.beta.shape, dt), jnp.zeros((), jnp.int32)
    if tech.emitter_hits:
        esc = v.escaped
        lid = jnp.where(esc, connect._sky_id(scene), jnp.maximum(v.light, 0))
        A_s = jax.vmap(lambda z_, zp_, l_, e_: connect.emitter_hit_join_pdfs(
            scene, z_, zp_, l_, e_).A_s)(z, zp, lid, esc)
        # NEE from z_{j-1} could have sampled z_j (j = 1: that would be light tracing)
        other = tech.nee & (j >= 2) & ~s.prev_delta
        w = sg(mis_partial.pt_weight(cfg, lp, lpos(sg(A_s), NEG), other, ~zero))
        hit = real & jnp.any(v.Le > 0, axis=-1)
        c, b = clean(jnp.where(hit[:, None], v.beta * v.Le * w[:, None], 0.0))
        total, bad = total + c, bad + b

    # ---- s = 1: next-event estimation from z_j (`_connect._next_event_queued`) ----
    if tech.nee and D >= 2 and u_nee is not None:
        water = scene.water
        is_delta = jnp.asarray([k in DELTA_LIGHTS for k in scene.lights.kind])
        kn = jnp.minimum(kg, D - 2)  # row j - 1 of the light samples' uniforms
        want = real & ~v.delta & ~v.escaped & (j <= D - 1)
        u = (u_nee.rows_at(kn, g, jnp.any(want)) if isinstance(u_nee, Uniforms)
             else u_nee[kn, g])
        ls = jax.vmap(lambda p_, u_: lights.sample_light(scene, p_, u_[0], u_[1], u_[2]))(v.p, u)
        inf = ~jnp.isfinite(ls.dist)
        y = v.p + ls.wi * jnp.where(inf, 0.0, ls.dist)
        oz = jax.vmap(subpath.spawn)(v.p, v.n, z.medium, ls.wi)
        tmax = jnp.where(inf, jnp.inf, vec.length(y - oz) * (1.0 - 1e-4))
        worth = want & ls.valid
        if water.enabled:  # a shadow ray whose ends lie on opposite sides of the surface
            worth = worth & ~jax.vmap(lambda o_, w_, t_: geometry.crosses_water(
                water, o_, w_, 0.0, t_, cfg.march_steps))(oz, ls.wi, tmax)

        def item(j_, z_, zp_, ls_, oz_, tmax_, inf_, beta_, q_, zero_):
            f = subpath.eval_f(scene, z_.kind, z_.mat, z_.wo, ls_.wi, z_.n)
            vis = geometry.unoccluded(scene, oz_, ls_.wi, tmax_, cfg.march_steps)
            wseg = geometry.inside_water(water, oz_) if water.enabled else jnp.zeros((), bool)
            Tr = connect._tr_one(scene, wseg, jnp.where(inf_, jnp.inf, ls_.dist))
            contrib = beta_ * f * ls_.Le * Tr / ls_.pdf_w
            A0, pdfs = connect.nee_join_pdfs(scene, z_, zp_, ls_, wseg)
            # own: A(y_0), the light's pdf of the point; other: the camera continuing
            # from z_j to y_0, B(y_0) rr(j, q_j) (`join`'s lb1)
            other = lpos(sg(pdfs.B_s1) * mis_partial._rr(j_, q_, cfg.rr_depth), NEG)
            w = sg(mis_partial.pt_weight(cfg, lpos(sg(A0), 0.0), other,
                                         tech.emitter_hits & ~is_delta[ls_.light],
                                         ~zero_ & (A0 > 0)))
            return jnp.where(ls_.valid & vis, contrib * w, 0.0)

        # the shadow rays and joins of this round's worthwhile lanes only (`_queue`)
        c = masked_map(item, worth, (j, z, zp, ls, oz, tmax, inf, v.beta, v.q, zero),
                       0.0, NEE_SPLIT)
        c, b = clean(c)
        total, bad = total + c, bad + b
    return s_new, total, bad, jnp.sum(real, dtype=jnp.int32)
