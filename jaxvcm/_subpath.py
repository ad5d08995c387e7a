"""One tracer for camera and light subpaths -> fixed-shape vertex records [D, N].

The same per-ray step serves both directions; only the transport mode differs (camera
paths carry radiance: refraction scales by 1/eta^2; light paths carry importance: it does
not) and what is recorded about emitters. Per vertex v_j the record holds position,
normal or medium flag, the direction back to v_{j-1}, the throughput arriving at v_j, and
the pdfs that explicit-sum MIS needs (`_mis`):
    pdf_fwd  p(v_j | v_{j-1}) in area (surface) / volume (medium) measure, or solid angle
             for a vertex at infinity (escaped to the sky),
    pdf_rev  p(v_{j-1} | v_j): the reverse pdf of the previous vertex, known once v_j has
             sampled its own continuation,
both without Russian roulette: the survival probability of a vertex depends on its index
along whichever subpath generates it, so `q` (the vertex's local survival probability)
is stored and the MIS assembly applies rr(index, q) for either direction.
The distance-sampling pdfs of the water (p_scatter for a medium end, P_pass for a surface
end; `_media.py`) are part of the area/volume pdfs of segments that run through water.

Delta vertices. A vertex sampled by a delta lobe (or sampling its predecessor by one) has
a Dirac in its solid-angle pdf; both subpath directions through a delta vertex carry the
same Dirac, so it cancels in every ratio of two techniques and is stored as 1. The
conversion to the next vertex's measure (cos / d^2, and the water's distance factor) is
kept: the camera-side pdf of x_0 reached through a delta x_1 is cos_0 / d_01^2, the
light-side pdf of x_2 reached through it cos_2 / d_12^2, and in the ratio of merging at
x_2 to the camera hitting the light x_0 the distances d_01, d_12 cancel against those of
the non-delta pdfs at x_1. (pbrt's BDPT remaps the converted pdf itself to 1, which drops
cos / d^2 and leaves a stray (d_12 / d_01)^2 in that ratio: harmless among connections,
which never join at a delta vertex, but with merging it misweights techniques, e.g. the
camera's hit of a pool's light through the water against merging at wall points near the
waterline, whose rare samples then carry many times the pixel mean. docs/design/mis.md,
"Delta vertices".)
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _geometry as geometry
from . import _lights as lights
from . import _materials as materials
from . import _media as media
from ._mis import _recursive as mis_recursive
from . import _vec as vec
from ._config import RenderConfig
from ._queue import Packed, first_true, round_width
from ._scene import MAT_DIFFUSE, MAT_GLOSSY, MAT_NAMES, Scene, Water
from ._uniforms import Uniforms
from ._vec import Vec3

# vertex kind of a scattering event in the water: after every MAT_* kind, never equal to one
# (a material vertex taken for a medium vertex at the joins would lose the cosine of its
# area pdfs and merge with the volume kernel)
KIND_MEDIUM = max(MAT_NAMES) + 1
assert KIND_MEDIUM not in MAT_NAMES
KIND_NONE = -1
N_UNIFORMS = 6  # per bounce: channel, distance, direction (2), lobe, roulette
Q_SPECULAR = 0.95  # local RR survival at delta and medium vertices
WATER_SPLIT = 4  # rounds per sweep of a trace round's water queue (`geometry.water_hits`)
TAIL_MIN = 512  # narrowest tail round of the trace (`tail_width`)


class Vertex(NamedTuple):
    p: Vec3  # position (for an escaped vertex: the direction to the sky)
    n: Vec3  # geometric normal (surface vertices)
    wo: Vec3  # unit direction from this vertex back to the previous one
    beta: Array  # [C] throughput arriving at the vertex (before it scatters)
    pdf_fwd: Array  # p(v_j | v_{j-1}), RR-free, Diracs as 1 (see module doc)
    pdf_rev: Array  # p(v_{j-1} | v_j), RR-free, Diracs as 1
    kind: Array  # MAT_* of the surface, KIND_MEDIUM, or KIND_NONE
    mat: Array  # material id (surfaces)
    light: Array  # light id of an emitting surface hit (-1 otherwise)
    Le: Array  # [C] emitted radiance towards wo (camera paths: emitter / sky hits)
    q: Array  # local Russian-roulette survival probability of the vertex
    seg_water: Array  # the segment arriving at this vertex ran through the water
    delta: Array  # the vertex scatters by a delta lobe
    escaped: Array  # vertex at infinity (the ray left the scene)
    alive: Array  # the vertex exists
    dispersed: Array  # beta went through a dispersive refraction: hero only, times C
    mis: Any = None  # `_mis._recursive.Record` (mis_form "recursive"), else None


class WalkState(NamedTuple):
    o: Vec3  # origin of the current ray (offset off its surface)
    p_prev: Vec3  # the vertex the ray left
    n_prev: Vec3  # its normal
    d: Vec3  # unit direction of the current ray
    beta: Array  # [C] throughput
    alive: Array  # path still being extended
    in_water: Array  # the current ray travels in the water
    pdf_w: Array  # pdf of d at p_prev: solid angle, or perpendicular area if prev_inf
    prev_delta: Array  # p_prev scattered by a delta lobe
    prev_medium: Array  # p_prev is a medium vertex
    prev_inf: Array  # p_prev is a light vertex at infinity (sun / sky disk)
    prev_conv: Array  # p_prev's reverse pdf needs no area conversion (camera, infinite light)
    dispersed: Array  # beta went through a dispersive refraction (hero channel only, x C)
    # what the pass's route carries along the walk: the recursive MIS form's
    # `_mis._recursive.Carry`, PT's in-trace techniques' `_inline.Carry`, or None
    carry: Any = None


def rr(index, q, cfg: RenderConfig):
    """Survival probability for continuing from a vertex with `index` segments before it."""
    return jnp.where(index >= cfg.rr_depth, q, 1.0)


def local_q(kind, albedo):
    """Local survival probability: the largest channel of the reflectance (diffuse; glossy:
    k_d + k_s, passed as `albedo`) clipped to [0.05, 0.95]; Q_SPECULAR at delta vertices."""
    q_d = jnp.clip(jax.lax.stop_gradient(jnp.max(albedo, axis=-1)), 0.05, 0.95)
    return jnp.where((kind == MAT_DIFFUSE) | (kind == MAT_GLOSSY), q_d, Q_SPECULAR)


def _glossy(scene: Scene, mat):
    """(k_s [C], n) of material `mat` if the scene has a glossy material, else (None, None)
    (the glossy lobes are then not in the compiled program)."""
    if MAT_GLOSSY not in scene.materials.kind:
        return None, None
    return scene.materials.glossy[mat], scene.materials.exponent[mat]


def _front(scene: Scene, mat):
    """True where material `mat` is one-sided, or None if none is (the check is then not
    in the compiled program)."""
    if not any(scene.materials.one_sided):
        return None
    return jnp.asarray(scene.materials.one_sided, bool)[mat]


def dist_pdf(water: Water, seg_water, target_medium, d):
    """Distance-sampling factor of a segment of length d: p_scatter(d) if it ends in a medium
    vertex, P_pass(d) if it ends on a surface; 1 outside the water."""
    if not water.enabled:
        return jnp.ones_like(d)
    ss = jax.lax.stop_gradient(water.sigma_s)
    f = jnp.where(target_medium, media.scatter_pdf(ss, d), media.pass_prob(ss, d))
    return jnp.where(seg_water, f, 1.0)


def to_area(pdf_w, target_medium, target_n: Vec3, w: Vec3, d, seg_water, water: Water,
            infinite_source=False):
    """Solid-angle pdf of direction w (towards the target, distance d) -> area/volume pdf of
    the target vertex. From an infinite source the pdf is already per perpendicular area."""
    cos = jnp.where(target_medium, 1.0, jnp.abs(vec.dot(target_n, w)))
    g = jnp.where(infinite_source, cos, cos / jnp.maximum(d * d, 1e-30))
    return pdf_w * g * dist_pdf(water, seg_water, target_medium, d)


def bsdf_pdf(scene: Scene, kind, mat, medium_d: Vec3, wo: Vec3, wi: Vec3, n: Vec3):
    """Solid-angle pdf of sampling wi at a vertex with outgoing-side direction wo (pointing
    away from it), for the non-delta kinds; delta kinds return 0 (callers remap)."""
    albedo = scene.materials.albedo[jnp.maximum(mat, 0)]
    _, pdf_s = materials.eval_bsdf(kind, albedo, wo, wi, n,
                                   *_glossy(scene, jnp.maximum(mat, 0)),
                                   front=_front(scene, jnp.maximum(mat, 0)))
    if scene.water.enabled:
        # phase functions: mu between the propagation direction (-wo) and wi
        ph = media.phase_eval(scene.water.phase_kind, scene.water, vec.dot(-wo, wi))
        pdf_s = jnp.where(kind == KIND_MEDIUM, jax.lax.stop_gradient(ph), pdf_s)
    return pdf_s


def eval_f(scene: Scene, kind, mat, wo: Vec3, wi: Vec3, n: Vec3):
    """Scattering factor of a connection at a vertex: f |cos(wi)| on surfaces, the phase
    function in the medium (sigma_s is already in the throughput). [C]"""
    C = scene.channels
    albedo = scene.materials.albedo[jnp.maximum(mat, 0)]
    f, _ = materials.eval_bsdf(kind, albedo, wo, wi, n, *_glossy(scene, jnp.maximum(mat, 0)),
                               front=_front(scene, jnp.maximum(mat, 0)))
    if scene.water.enabled:
        ph = media.phase_eval(scene.water.phase_kind, scene.water, vec.dot(-wo, wi))
        f = jnp.where(kind == KIND_MEDIUM, ph * jnp.ones((C,), ph.dtype), f)
    return f


def offset(p: Vec3, n: Vec3, w: Vec3) -> Vec3:
    scale = 1.0 + jnp.maximum(jnp.maximum(jnp.abs(p.x), jnp.abs(p.y)), jnp.abs(p.z))
    eps = 1e-4 * scale
    s = jnp.where(vec.dot(w, n) >= 0, eps, -eps)
    return p + n * s


def spawn(p: Vec3, n: Vec3, medium, w: Vec3) -> Vec3:
    return vec.where(medium, p, offset(p, n, w))


def step(scene: Scene, cfg: RenderConfig, radiance: bool, index, s: WalkState, u,
         t_water=None, mis_ctx=None) -> tuple[WalkState, Vertex]:
    """Extend one subpath by one segment; `index` = segments before the new vertex minus 1.
    `t_water`: the water's distance along the ray, when the caller computed it for the
    batch (`geometry.water_hits`); None: computed here. With the recursive MIS form's carry
    in `s.carry` the step also carries the recursion one vertex on
    (`_mis._recursive.carry_step`, `mis_ctx` its per-pass `Context`)."""
    water = scene.water
    dt = s.o.x.dtype
    C = scene.channels
    kinds = jnp.asarray(scene.materials.kind, jnp.int32)

    # ---- intersect, free flight ----
    hit = geometry.intersect_scene(scene, s.o, s.d, 0.0, jnp.inf, cfg.march_steps,
                                   t_water=t_water)
    if water.enabled:
        ff = media.sample_free_flight(water, hit.t, u[0], u[1])
        # the basin is closed: a ray in the water meets a surface. One that meets none has
        # slipped past a wall where it meets the waterline (float32) and would scatter
        # metres outside the scene (a photon far outside it would defeat the hash grid's
        # precision); it gets no medium vertex and the lane ends (an escaped ray in the
        # water).
        scatter = s.alive & s.in_water & ff.scatter & jnp.isfinite(hit.t)
        beta = jnp.where(s.in_water, s.beta * ff.weight, s.beta)
        t = jnp.where(s.in_water, ff.t, hit.t)
    else:
        scatter = jnp.zeros((), bool)
        beta = s.beta
        t = hit.t
    surf = ~scatter & jnp.isfinite(hit.t)
    esc = ~scatter & ~jnp.isfinite(hit.t)
    p = s.o + s.d * jnp.where(jnp.isfinite(t), t, 0.0)
    wo = -s.d
    n = hit.n
    dist = jnp.where(esc, 1.0, vec.length(p - s.p_prev))
    mat = jnp.maximum(hit.mat, 0)
    kind = jnp.where(scatter, KIND_MEDIUM, jnp.where(surf, kinds[mat], KIND_NONE))
    albedo = scene.materials.albedo[mat]
    ior = scene.materials.ior[mat]

    # ---- forward pdf of this vertex ----
    fwd_area = to_area(s.pdf_w, scatter, n, s.d, dist, s.in_water, water, s.prev_inf)
    pdf_fwd = jnp.where(esc, s.pdf_w, fwd_area)
    # after a delta vertex: its Dirac (solid angle) is 1, the conversion to this vertex's
    # area / volume measure is kept (module doc: the distances then cancel between
    # techniques; an escaped vertex keeps solid angle: 1)
    geo = to_area(jnp.ones_like(s.pdf_w), scatter, n, s.d, dist, s.in_water, water,
                  s.prev_inf)
    pdf_fwd = jnp.where(s.prev_delta, jnp.where(esc, 1.0, geo), pdf_fwd)

    # ---- emission seen by camera paths ----
    if radiance is False:
        Le = jnp.zeros((C,), dt)
        v_alive = s.alive & (scatter | surf)
    else:  # True, or a traced per-lane flag (camera and light lanes in one trace)
        Le_s, _ = lights.emitted_surface(scene, hit.light, wo, n, dist)
        Le_e, _ = lights.emitted_escape(scene, s.d)
        Le = jnp.where(surf, Le_s, jnp.where(esc & ~s.in_water, Le_e, 0.0))
        v_alive = s.alive & (scatter | surf | (esc & ~s.in_water))
        if radiance is not True:
            Le = jnp.where(radiance, Le, 0.0)
            v_alive = jnp.where(radiance, v_alive, s.alive & (scatter | surf))
    light_id = jnp.where(surf, hit.light, -1)
    p_rec = vec.where(esc, s.d, p)  # escaped: store the direction to the sky

    # ---- sample the continuation ----
    ks, n_exp = _glossy(scene, mat)
    bs = materials.sample_bsdf(kind, albedo, ior, wo, n, u[2], u[3], u[4], radiance=radiance,
                               glossy=ks, exponent=n_exp, front=_front(scene, mat))
    if water.enabled:
        wi_ph, pdf_ph = media.phase_sample(water.phase_kind, water, s.d, u[2], u[3])
        wi = vec.where(scatter, wi_ph, bs.wi)
        beta_next = jnp.where(scatter, beta, beta * bs.weight)
        pdf_w = jnp.where(scatter, pdf_ph, bs.pdf)
    else:
        wi, beta_next, pdf_w = bs.wi, beta * bs.weight, bs.pdf
    delta = ~scatter & bs.delta & surf

    # ---- reverse pdf of the previous vertex (sampling wo at this vertex, coming from wi) ----
    rev_w = bsdf_pdf(scene, kind, mat, scatter, wi, wo, n)
    rev = to_area(rev_w, s.prev_medium, s.n_prev, wo, dist, s.in_water, water, False)
    rev = jnp.where(s.prev_conv, rev_w, rev)
    # a delta vertex samples the previous one by a Dirac: 1, converted to its measure
    geo_r = to_area(jnp.ones_like(rev_w), s.prev_medium, s.n_prev, wo, dist, s.in_water,
                    water, False)
    rev = jnp.where(delta, jnp.where(s.prev_conv, 1.0, geo_r), rev)

    # ---- Russian roulette (local survival probability, applied by index) ----
    q_loc = jnp.where(scatter, Q_SPECULAR,
                      local_q(kind, albedo if ks is None else albedo + ks))
    q = rr(index + 1, q_loc, cfg)
    # ---- dispersion (hero-wavelength termination, `_materials` doc) ----
    # the first dispersive refraction of the subpath turns beta into the hero's
    # single-wavelength estimate: x C on channel 0 (the other channels are already 0).
    # A full path whose two subpaths both carry the factor divides one C out (`_connect`).
    first = bs.disperse & ~scatter & surf & ~s.dispersed
    beta_next = beta_next * jnp.where(first, float(C), 1.0).astype(dt)
    dispersed = s.dispersed | (bs.disperse & ~scatter & surf)
    alive = v_alive & ~esc & jnp.any(beta_next > 0) & (u[5] < q)
    if cfg.techniques.merging == "first" and radiance is not False:
        # ppm reads a camera subpath up to its first non-delta vertex only (the gather
        # vertex, and the emission along the delta prefix before it: `_merge.photon_gather`):
        # the lane ends there instead of tracing vertices nothing reads
        gather = v_alive & ~delta
        alive = alive & ~(gather if radiance is True else radiance & gather)
    beta_next = beta_next / q

    # ---- the recursive MIS quantities, carried on from the pdfs just computed ----
    mis_carry = mis_rec = None
    if isinstance(s.carry, mis_recursive.Carry):
        sg = jax.lax.stop_gradient
        mis_carry, mis_rec = mis_recursive.carry_step(
            cfg, s.carry, mis_ctx, radiance, index, sg(pdf_fwd), sg(rev), sg(q_loc), sg(q),
            delta, scatter, s.prev_delta)

    vertex = Vertex(p_rec, n, wo, beta, jax.lax.stop_gradient(pdf_fwd),
                    jax.lax.stop_gradient(rev), kind, mat, light_id, Le, q_loc, s.in_water,
                    delta, esc & v_alive, v_alive, s.dispersed, mis_rec)

    # ---- spawn ----
    o = spawn(p, n, scatter, wi)
    in_water = (scatter | geometry.inside_water(water, o)) if water.enabled else s.in_water
    state = WalkState(o, p, n, wi, beta_next, alive, in_water, jax.lax.stop_gradient(pdf_w),
                      delta, scatter, jnp.zeros((), bool), jnp.zeros((), bool), dispersed,
                      mis_carry)
    return state, vertex


def trace(scene: Scene, cfg: RenderConfig, radiance, s0: WalkState, u, n_steps: int,
          limit=None, mis_ctx=None, v0: Vertex | None = None, estimate=None):
    """Trace L subpaths from batched start states; u: [n_steps, L, N_UNIFORMS], an array or
    a `_uniforms.Uniforms` table (hashed per round for the round's lanes).
    `radiance`: True (camera subpaths), False (light subpaths) or an [L] per-lane flag
    (`trace_both`); `limit`: optional [L] per-lane step count (<= n_steps).
    Returns the records [n_steps, L] (dead records hold `_dead_records`' values) and each
    lane's y_0 / z_0 reverse pdf p(v_0 | v_1) (1 where v_1 does not exist).

    A queue of lanes, not a loop over depths: each round advances the first
    L / cfg.tuning.trace_split lanes (`_queue.round_width`) that are still alive by one
    vertex (gather, `step`, scatter back), so the work follows the vertices that exist, not
    L x n_steps. Rounds with no live lane left are skipped (`lax.cond` on a scalar); there
    are enough rounds for every lane to run every step (n_steps L / W full ones and n_steps
    more), so nothing is ever dropped. Each lane sees the same uniforms (u[its depth, its
    lane]) as in a loop over depths: the live records do not
    depend on the round width. A batch of at most one round per step (W >= L) runs the
    plain loop over depths (`_trace_all`). `mis_ctx`: the recursive MIS form's per-pass
    `_mis._recursive.Context` (when `s0.carry` carries its recursion).

    `v0` ([L] records of the start vertices): the records come back with it as row 0
    ([n_steps + 1, L]; vertex k in row k + 1) and the reverse pdf p(v_0 | v_1) written
    into row 0 for the light lanes (not radiance); camera lanes keep v0's. The records
    are then the subpaths' `PathEnds` as they are (`ends`): no copy of every field to
    prepend the start vertex.

    `estimate` (`_inline.estimate` bound to its scene, config and uniforms): evaluate
    techniques at each vertex as a round makes it, `estimate(kg, g, live, s, s_new, v)
    -> (s_new, values [W, C], non-finite count, live vertices)` for the round's lanes g
    (`live`: not padding) and their states before / after the step. The trace then keeps
    no records and returns (the values summed per lane [L, C], the non-finite count, the
    number of live vertices)."""
    static = isinstance(radiance, bool)
    L = s0.alive.shape[0]
    if v0 is not None:
        rev_to0 = (jnp.full((L,), not radiance) if static else ~radiance)
    limit = jnp.full((L,), n_steps, jnp.int32) if limit is None else limit
    W = round_width(L, cfg.tuning.trace_split)  # lanes per round
    # Enough rounds for every lane to run every step: a round either advances W lanes (at
    # most n_steps L / W such rounds) or every lane that still has a step to take, and a
    # lane takes at most n_steps steps, so at most n_steps rounds are not full (ceil(n_steps
    # L / W) alone would not do: when the last lanes to start are fewer than W, the rounds
    # would run out before their last steps). Rounds with no live lane are skipped.
    rounds = (n_steps * L) // W + n_steps
    if W >= L and estimate is not None:
        return _trace_all(scene, cfg, radiance, s0, u, n_steps, mis_ctx, estimate)
    if W >= L:
        verts, rev0 = _trace_all(scene, cfg, radiance, s0, u, n_steps, mis_ctx)
        if v0 is None:
            return verts, rev0
        return with_start(v0._replace(pdf_rev=jnp.where(rev_to0, rev0, v0.pdf_rev)),
                          verts), None
    if isinstance(u, Uniforms) and not u.lazy:  # no lazy draws: gather from the table
        u = u.dense()
    vstep = jax.vmap(lambda sc, c, r, i, st, ui, tw: step(sc, c, r, i, st, ui, tw, mis_ctx),
                     in_axes=(None, None, None if static else 0, 0, 0, 0, 0))
    # records and lane states packed per dtype: one gather / scatter per dtype and round
    off = 0 if v0 is None else 1  # row of vertex k: k + off
    n_rows = n_steps + off
    # the record buffer: every row the lane's dead record, packed at [L, F] and then
    # broadcast over the rows (one write of the buffer; packing the broadcast rows
    # materialised each field's broadcast first)
    rec_pack = Packed(_dead_records(s0, None, scene.channels), 1)
    state_pack = Packed(s0, 1)
    rev_col = rec_pack.column(_leaf(rec_pack, "pdf_rev"))
    alive_col = state_pack.column(_leaf(state_pack, "alive"))[1]
    rev0 = jnp.ones((L,), s0.pdf_w.dtype)
    k0 = jnp.zeros((L,), jnp.int32)  # vertices recorded so far, per lane
    keep = estimate is None  # the records are kept (else the estimates' sums)

    def advance(carry, width=W):
        S, k, V, rev0, E = carry
        lane = first_true(S["bool"][:, alive_col] & (k < limit), width)
        g = jnp.minimum(lane, L - 1)  # padding lanes compute lane L-1's step; dropped below
        kg = jnp.minimum(k[g], n_steps - 1)
        s_g = state_pack.unpack({d: a[g] for d, a in S.items()})
        mode = radiance if static else radiance[g]
        # the water's closest hits only for the rays that meet its box (`water_hits`)
        tw = (geometry.water_hits(scene.water, s_g.o, s_g.d, lane < L, cfg.march_steps,
                                  WATER_SPLIT) if scene.water.enabled else None)
        # this round's uniforms: hashed for its lanes alone (`_uniforms`), or gathered
        ug = u.rows_at(kg, g, lane[0] < L) if isinstance(u, Uniforms) else u[kg, g]
        s_new, v = vstep(scene, cfg, mode, kg, s_g, ug, tw)
        if not keep:  # the techniques at the new vertices, added into their lanes
            s_new, c, n_bad, n_v = estimate(kg, g, lane < L, s_g, s_new, v)
            E = (E[0].at[lane].add(c, mode="drop"), E[1] + n_bad, E[2] + n_v)
        S = {d: S[d].at[lane].set(x, mode="drop") for d, x in state_pack.pack(s_new).items()}
        k = k.at[lane].add(1, mode="drop")
        if not keep:
            return S, k, V, rev0, E
        # v_k's record at (k, lane); the pdf_rev it computed belongs to v_{k-1} (y_0 / z_0
        # for k = 0)
        row = jnp.where(lane < L, kg + off, n_rows)
        rec = v._replace(pdf_rev=jnp.ones_like(v.pdf_rev))  # set when v_{k+1} is traced
        V = {d: V[d].at[row, lane].set(x, mode="drop") for d, x in rec_pack.pack(rec).items()}
        to_prev = kg > 0 if v0 is None else (kg > 0) | rev_to0[g]
        prev = jnp.where(to_prev & (lane < L), kg - 1 + off, n_rows)
        d, c = rev_col
        V[d] = V[d].at[prev, lane, c].set(v.pdf_rev, mode="drop")
        rev0 = rev0.at[jnp.where(kg == 0, lane, L)].set(v.pdf_rev, mode="drop")
        return S, k, V, rev0, E

    Wt = tail_width(W, cfg, static)

    def sweep(carry, width, more, n_rounds):  # rounds of `width` lanes while more(n_live)
        def body(c, _):
            live = c[0]["bool"][:, alive_col] & (c[1] < limit)
            go = more(jnp.sum(live, dtype=jnp.int32))
            return jax.lax.cond(go, lambda c_: advance(c_, width), lambda c_: c_, c), None

        return jax.lax.scan(body, carry, None, length=n_rounds)[0]

    V0 = {d: jnp.broadcast_to(a[None], (n_rows,) + a.shape) for d, a in rec_pack.arrays.items()}
    if v0 is not None and keep:  # row 0: the start vertices
        P0 = rec_pack.pack(v0)
        V0 = {d: a.at[0].set(P0[d]) for d, a in V0.items()}
    E0 = None
    if not keep:  # no records: the estimates' sums instead
        V0 = rev0 = None
        zero = jnp.zeros((), jnp.int32)
        E0 = (jnp.zeros((L, scene.channels), s0.beta.dtype), zero, zero)
    carry = (state_pack.arrays, k0, V0, rev0, E0)
    if Wt is None:
        carry = sweep(carry, W, lambda n: n > 0, rounds)
    else:  # the tail: once at most Wt lanes are left (it stays so: lanes only die), each
        # round advances all of them, at most n_steps rounds, a step Wt wide
        carry = sweep(carry, W, lambda n: n > Wt, rounds)
        carry = sweep(carry, Wt, lambda n: n > 0, n_steps)
    _, _, V, rev0, E = carry
    if not keep:
        return E
    if v0 is not None:  # the records, and the same packed (`VertexTable`)
        return rec_pack.unpack(V), (rec_pack, V)
    return rec_pack.unpack(V), rev0


def tail_width(W: int, cfg: RenderConfig, single: bool) -> int | None:
    """Width of the trace's tail rounds (`trace`), or None for none: W / cfg.tuning.trace_tail
    lanes, when that is at least TAIL_MIN, in single-direction traces (`single`).

    The queue's last rounds are not full: once fewer than W lanes are alive, each round
    advances all of them by one vertex, yet a W-wide round costs its width whatever it
    holds. With Russian roulette the survivors thin out geometrically, so these rounds
    grow with the maximum depth, not with the vertices. A second copy of the step, Wt
    wide, runs the rounds with at most Wt lanes left. The copy costs compile time, so by
    default it is there only from max_depth 3 rr_depth on (`Tuning.trace_tail` 0), where
    the tail rounds are many, and only in single-direction traces (PT, light tracing),
    not in `trace_both`, whose program is already the largest to compile
    (docs/design/performance.md)."""
    tail = cfg.tuning.trace_tail or (8 if cfg.max_depth >= 3 * cfg.rr_depth else 1)
    if not single or tail <= 1:
        return None
    Wt = W // tail
    return Wt if Wt >= TAIL_MIN else None


def _trace_all(scene: Scene, cfg: RenderConfig, radiance, s0: WalkState, u, n_steps: int,
               mis_ctx=None, estimate=None):
    """One round per step (every lane every step, dead or alive): the plain loop over
    depths, without the queue's gathers and scatters. Dead lanes' records hold whatever
    their masked-out steps computed (and light lanes of `trace_both` run n_cam steps).
    With `estimate` (`trace`'s): its sums instead of records."""
    static = isinstance(radiance, bool)
    vstep = jax.vmap(lambda sc, c, r, i, st, ui: step(sc, c, r, i, st, ui, None, mis_ctx),
                     in_axes=(None, None, None if static else 0, None, 0, 0))
    if estimate is not None:
        L = s0.alive.shape[0]
        lanes, live = jnp.arange(L, dtype=jnp.int32), jnp.ones((L,), bool)

        def body_e(carry, x):
            st, (acc, bad, n) = carry
            i, ui = x
            s_new, v = vstep(scene, cfg, radiance, i, st, ui)
            s_new, c, n_bad, n_v = estimate(jnp.full((L,), i), lanes, live, st, s_new, v)
            return (s_new, (acc + c, bad + n_bad, n + n_v)), None

        uu = u.dense() if isinstance(u, Uniforms) else u
        zero = jnp.zeros((), jnp.int32)
        E0 = (jnp.zeros((L, scene.channels), s0.beta.dtype), zero, zero)
        (_, E), _ = jax.lax.scan(body_e, (s0, E0),
                                 (jnp.arange(n_steps, dtype=jnp.int32), uu[:n_steps]))
        return E

    def body(s, x):
        i, ui = x
        return vstep(scene, cfg, radiance, i, s, ui)

    idx = jnp.arange(n_steps, dtype=jnp.int32)
    if isinstance(u, Uniforms):  # every lane every step: the dense table
        u = u.dense()
    _, verts = jax.lax.scan(body, s0, (idx, u[:n_steps]))
    # pdf_rev was computed at v_{j+1} for v_j: shift it back by one vertex
    rev_next = jnp.concatenate([verts.pdf_rev[1:], jnp.ones_like(verts.pdf_rev[:1])], axis=0)
    return verts._replace(pdf_rev=rev_next), verts.pdf_rev[0]


def _leaf(packed: Packed, field: str) -> int:
    """Leaf number of NamedTuple field `field` (a scalar per lane) in `packed`'s tree."""
    t = jax.tree.unflatten(packed.treedef, list(range(len(packed.meta))))
    return getattr(t, field)


def _dead_records(s0: WalkState, n_steps: int | None, C: int) -> Vertex:
    """Records of vertices that are never traced: not alive, zero throughput, unit pdfs;
    positions, normals and directions from the lane's start (finite, so that masked-out
    geometry downstream stays finite). [n_steps, L], or [L] (one row) for n_steps None."""
    L = s0.alive.shape[0]
    dt = s0.pdf_w.dtype
    lead = (L,) if n_steps is None else (n_steps, L)

    def full(x, dtype=None):
        x = jnp.asarray(x, dtype)
        return jnp.broadcast_to(x, lead + x.shape[1:] if x.ndim else lead)

    f = full(False)
    mis = None
    if isinstance(s0.carry, mis_recursive.Carry):  # never read: a dead vertex takes part
        K = s0.carry.rec.shape[-1]                   # in no technique
        mis = mis_recursive.Record(jnp.zeros(lead + (K,), dt), f)
    return Vertex(
        jax.tree.map(full, s0.o), jax.tree.map(full, s0.n_prev), jax.tree.map(full, -s0.d),
        jnp.zeros(lead + (C,), dt), full(jnp.ones((), dt)), full(jnp.ones((), dt)),
        full(KIND_NONE, jnp.int32), full(0, jnp.int32), full(-1, jnp.int32),
        jnp.zeros(lead + (C,), dt), full(jnp.ones((), dt)), f, f, f, f, f, mis)


def trace_both(scene: Scene, cfg: RenderConfig, cam0: WalkState, u_cam, n_cam: int,
               light0: WalkState, u_light, n_light: int, mis_ctx=None, v0=None):
    """Camera and light subpaths in one trace (one copy of `step` in the compiled program):
    the 2N lanes carry their transport mode as a per-lane flag, and each lane computes
    exactly what its own `trace` would (its uniforms, its mode, its number of steps).
    Returns (camera records [n_cam, N], (light records [n_light, N], y_0's reverse pdf))."""
    if isinstance(u_cam, Uniforms):  # side by side, hashed where used (`_uniforms`)
        N = u_cam.lanes
        assert u_cam.rows == (n_cam,) and u_light.rows == (n_light,)
        u = u_cam.beside(u_light)
    else:
        N = u_cam.shape[1]
        pad = jnp.zeros((n_cam - n_light,) + u_light.shape[1:], u_light.dtype)
        u = jnp.concatenate([u_cam[:n_cam], jnp.concatenate([u_light[:n_light], pad])], axis=1)
    s0 = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), cam0, light0)
    mode = jnp.arange(2 * N) < N
    if v0 is not None:  # (z_0, y_0) records: rows 0 of both (`trace`'s v0)
        v0 = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), *v0)
        verts, packed = trace(scene, cfg, mode, s0, u, n_cam,
                              jnp.where(mode, n_cam, n_light), mis_ctx, v0)
        cverts = jax.tree.map(lambda a: a[:, :N], verts)
        lverts = jax.tree.map(lambda a: a[:n_light + 1, N:], verts)
        lverts = lverts._replace(pdf_rev=lverts.pdf_rev.at[-1].set(1.0))
        tables = (None, None) if packed is None else (
            VertexTable(packed[0], packed[1], 0, False), VertexTable(packed[0], packed[1], N, True))
        return (cverts, tables[0]), (lverts, tables[1])
    verts, rev0 = trace(scene, cfg, mode, s0, u, n_cam, jnp.where(mode, n_cam, n_light),
                        mis_ctx)
    cverts = jax.tree.map(lambda a: a[:, :N], verts)
    lverts = jax.tree.map(lambda a: a[:n_light, N:], verts)
    # the light records end at n_light: their last reverse pdf is set by a connection
    lverts = lverts._replace(pdf_rev=lverts.pdf_rev.at[-1].set(1.0))
    return cverts, (lverts, rev0[N:])


def camera_start(scene: Scene, o: Vec3, d: Vec3, pdf_w) -> WalkState:
    dt = o.x.dtype
    C = scene.channels
    f = jnp.zeros((), bool)
    return WalkState(o, o, vec.from_array(scene.camera.forward), d, jnp.ones((C,), dt),
                     jnp.ones((), bool), geometry.inside_water(scene.water, o), pdf_w, f, f, f,
                     jnp.ones((), bool), f)


def light_start(scene: Scene, e: lights.Emission) -> WalkState:
    return WalkState(e.o, e.p, e.n, e.d, e.beta1, jnp.any(e.beta1 > 0),
                     geometry.inside_water(scene.water, e.o), e.pdf_dir, jnp.zeros((), bool),
                     jnp.zeros((), bool), e.infinite, e.infinite, jnp.zeros((), bool))


# ---------------------------------------------------------------- subpaths with their start vertex
class PathEnds(NamedTuple):
    """Per-vertex arrays of one subpath including its start vertex (index 0): [D+1, N, ...]."""

    p: Vec3
    n: Vec3
    wo: Vec3
    beta: Array  # [D+1, N, C]
    A: Array  # light-side pdf (RR-free)
    B: Array  # camera-side pdf (RR-free)
    q: Array  # local RR survival probability
    delta: Array
    medium: Array
    kind: Array
    mat: Array
    seg_water: Array
    alive: Array
    disp: Array  # beta carries the hero-only x C of a dispersive refraction (`_subpath`)
    mis: Any = None  # `_mis._recursive.Record` [D+1, N, ...] (mis_form "recursive")
    table: Any = None  # `VertexTable`: the same records as the trace packed them


@jax.tree_util.register_pytree_node_class
class VertexTable:
    """A subpath's records as the trace packed them (`_queue.Packed`: one [rows, lanes, F]
    array per dtype, the start vertex in row 0), lanes `lane0`.. of them: one vertex is one
    gather per dtype. (`trace_both` packs camera and light lanes side by side.)"""

    def __init__(self, layout: Packed, arrays: dict, lane0: int, light: bool):
        self.layout, self.arrays, self.lane0, self.light = layout, arrays, lane0, light

    def tree_flatten(self):
        return (self.arrays,), (self.layout, self.lane0, self.light)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(aux[0], children[0], aux[1], aux[2])

    def record(self, i, n) -> Vertex:
        """The record of vertex i of lane n (row i: the start vertex is row 0)."""
        return self.layout.unpack({d: a[i, n + self.lane0] for d, a in self.arrays.items()})

    def at(self, i, n) -> PathEnds:
        return ends(self.record(i, n), self.light)


def vertex_table(ends: PathEnds):
    """`at(i, n) -> PathEnds` of vertex i of lane n (traced indices, any batch shape). The
    records packed per dtype (`_queue.Packed`: one [D+1, N, F] array each; the trace's
    own `VertexTable` when the ends carry it, else packed here), so a vertex is one
    gather per dtype, not one per field (a join kernel reads some twenty fields, and on
    the CPU backend each gather is a kernel of its own and a cache miss of its own)."""
    if ends.table is not None:  # the trace's own packing: no copy
        return ends.table.at
    pk = Packed(ends, 2)

    def at(i, n) -> PathEnds:
        return pk.unpack({d: a[i, n] for d, a in pk.arrays.items()})

    return at


def with_start(v0: Vertex, verts: Vertex) -> Vertex:
    """Records [n, N] with the start vertices' records v0 [N] prepended as row 0 (what
    `trace` returns when given v0; for records traced without it)."""
    return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), v0, verts)


def camera_ends(scene: Scene, cam_o: Vec3, verts: Vertex, n_paths: int, mis0=None) -> PathEnds:
    """z_0 (the pinhole) followed by the camera records [D, N] (traced without v0)."""
    return ends(with_start(camera_start_record(scene, cam_o, n_paths, mis0), verts), False)


def light_ends(scene: Scene, e: lights.Emission, rev0, verts: Vertex, n_paths: int,
               mis0=None) -> PathEnds:
    """y_0 (on the light, or at infinity; B = rev0) followed by the light records."""
    v0 = light_start_record(scene, e, mis0)
    return ends(with_start(v0._replace(pdf_rev=rev0), verts), True)


def camera_start_record(scene: Scene, cam_o: Vec3, n_paths: int, mis0=None) -> Vertex:
    """z_0's record (row 0 of `trace`'s v0): the pinhole, B = A = 1, never a delta vertex."""
    return _start_record(scene, cam_o, vec.from_array(jnp.broadcast_to(
        scene.camera.forward, (n_paths, 3))), None, None, 1.0, 1.0, mis0)


def light_start_record(scene: Scene, e: lights.Emission, mis0=None) -> Vertex:
    """y_0's record: on the light (or at infinity), A = p_pos; its B = p(y_0 | y_1) is
    written by the trace."""
    return _start_record(scene, e.p, e.n, -e.d, e.beta0, e.pdf_pos, 1.0, mis0)


def _start_record(scene, p0: Vec3, n0: Vec3, wo0, beta0, pdf_pos, pdf_b, mis0) -> Vertex:
    # the values `_ends` gave row 0 (kind KIND_NONE: no medium, no material)
    N = p0.x.shape[0]
    dt = p0.x.dtype
    f = jnp.zeros((N,), bool)
    wo0 = n0 if wo0 is None else wo0
    beta0 = jnp.ones((N, scene.channels), dt) if beta0 is None else beta0
    mis = None if mis0 is None else mis_recursive.Record(mis0.rec, mis0.zero)
    return Vertex(p0, n0, wo0, beta0, jnp.broadcast_to(jnp.asarray(pdf_pos, dt), (N,)),
                  jnp.broadcast_to(jnp.asarray(pdf_b, dt), (N,)),
                  jnp.full((N,), KIND_NONE, jnp.int32), jnp.zeros((N,), jnp.int32),
                  jnp.full((N,), -1, jnp.int32), jnp.zeros((N, scene.channels), dt),
                  jnp.ones((N,), dt), f, f, f, jnp.ones((N,), bool), f, mis)


def ends(verts: Vertex, light: bool, table: VertexTable | None = None) -> PathEnds:
    """A subpath's `PathEnds` from its records with the start vertex as row 0 (`trace`'s
    v0): the same fields, no copies (camera: A = pdf_rev, B = pdf_fwd; light: swapped)."""
    A, B = (verts.pdf_fwd, verts.pdf_rev) if light else (verts.pdf_rev, verts.pdf_fwd)
    return PathEnds(verts.p, verts.n, verts.wo, verts.beta, A, B, verts.q, verts.delta,
                    verts.kind == KIND_MEDIUM, verts.kind, verts.mat, verts.seg_water,
                    verts.alive, verts.dispersed, verts.mis, table)


def rows(ends: PathEnds, idx) -> PathEnds:
    """Rows idx ([J], static) of every field: [J, N, ...]."""
    idx = np.asarray(idx)
    return jax.tree.map(lambda a: a[idx], ends._replace(table=None))
