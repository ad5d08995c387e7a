"""Vertex connection: the (s, t) techniques of bidirectional path tracing.

Techniques (s light vertices, t camera vertices, path x_0 .. x_k with k = s + t - 1):
    s = 0          the camera subpath hits an emitter / escapes to the sky,
    s = 1          next-event estimation (a fresh light sample per camera vertex),
    t = 1          light tracing: light vertex -> pinhole, splatted into the film,
    s, t >= 2      camera vertex z_{t-1} joined to light vertex y_{s-1} of the light
                   subpath with the same index (one light subpath per pixel sample).
Each technique evaluates its contribution and the four pdfs its join changes, and takes
its MIS weight from the subpaths' per-subpath MIS state and its join (`parts`: (light,
camera), `_mis.AbstractMIS.subpaths`; `_mis.mis_form(cfg)` weights them).

Each technique is a work queue over (technique, lane) items (`_queue.masked_map`): only the
items whose vertices exist and can contribute (live and emitting; live and non-delta) run
the kernel, one item at a time vmapped, each gathering its vertices and its entries of the
MIS state, so the cost follows the live vertices, not D x N or D^2 x N slots.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _geometry as geometry
from . import _lights as lights
from . import _media as media
from . import _subpath as subpath
from . import _vec as vec
from ._camera import camera_importance
from ._config import RenderConfig
from ._glints import emitter_share as glint_share
from ._mnee import emitter_hit_factor as mnee_factor
from ._mis import mis_form
from ._path import both_dispersed, log_n_light_tracing, reverse_pdf
from ._queue import masked_map
from ._scene import DELTA_LIGHTS, LIGHT_BACKGROUND, LIGHT_SKY, Scene
from ._subpath import PathEnds, rows, vertex_table
from ._uniforms import Uniforms
from ._vec import Vec3


# ---------------------------------------------------------------- geometry helpers
def _segment(pa: Vec3, na: Vec3, ma, pb: Vec3, nb: Vec3, mb):
    """The segment a -> b: unit direction, distance, and its shadow ray (origin offset off
    a, direction, tmax short of b's offset point)."""
    dv = pb - pa
    d = vec.length(dv)
    w = dv / jnp.maximum(d, 1e-30)
    oa = subpath.spawn(pa, na, ma, w)
    ob = subpath.spawn(pb, nb, mb, -w)
    dd = ob - oa
    ddl = vec.length(dd)
    return w, d, oa, dd / jnp.maximum(ddl, 1e-30), ddl * (1.0 - 1e-5)


def _sky_id(scene: Scene) -> int:
    """The light an escaped camera vertex hits: the sky or the background (a scene has at
    most one of them, `_io`); 0 when there is none (then nothing is emitted there)."""
    for k, kind in enumerate(scene.lights.kind):
        if kind in (LIGHT_SKY, LIGHT_BACKGROUND):
            return k
    return 0


# ---------------------------------------------------------------- the pdfs at the joins
class JoinPdfs(NamedTuple):
    """The four pdfs a technique (s, t) re-evaluates at its join (`_path.reverse_pdf`), all
    RR-free, in the area (surface) / volume (medium) measure of the vertex they belong to,
    times the water's distance-sampling factor of the segment that reaches it
    (`_subpath.to_area`):
        A_s   A(x_s)     = A(z_{t-1}): the light side generating the camera's join vertex,
        A_s1  A(x_{s+1}) = A(z_{t-2}): ... and the one before it (read iff t >= 3),
        B_s1  B(x_{s-1}) = B(y_{s-1}): the camera side generating the light's join vertex,
        B_s2  B(x_{s-2}) = B(y_{s-2}): ... and the one before it (read iff s >= 2).
    The per-item functions below are the only place the renderer computes them, so the
    join-pdf tests (tests/mis) check the code that runs.
    Vertices (`z`, `zp`, `y`, `yp`) are one vertex of a `PathEnds` (fields p, n, wo, kind,
    mat, medium, seg_water read)."""

    A_s: Array
    A_s1: Array
    B_s1: Array
    B_s2: Array


def emitter_hit_join_pdfs(scene: Scene, z, zp, light, escaped) -> JoinPdfs:
    """s = 0: camera vertex z = z_j on light `light` (escaped: z.p is the direction to the
    sky), zp = z_{j-1}. A_s = A(z_j): the light's pdf of the point (selection included; sky:
    of the direction); A_s1 = A(z_{j-1}): the light emits from z_j towards z_{j-1}
    (emission pdf) -> area at z_{j-1} (from the sky: per perpendicular area, the cosine
    alone). No light vertex: B_s1 = B_s2 = 1 (never read)."""
    A_s = lights.light_point_pdf(scene, light, z.p)
    pe = lights.emission_pdf_dir(scene, light, z.n, z.wo, zp.p)  # sky: the line through z_{j-1}
    dv = zp.p - z.p
    d = vec.length(dv)
    a_area = pe * subpath.to_area(1.0, zp.medium, zp.n, dv / jnp.maximum(d, 1e-30), d,
                                  z.seg_water, scene.water)
    c_inf = jnp.where(zp.medium, 1.0, jnp.abs(vec.dot(zp.n, z.p)))
    one = jnp.ones_like(A_s)
    return JoinPdfs(A_s, jnp.where(escaped, pe * c_inf, a_area), one, one)


def nee_join_pdfs(scene: Scene, z, zp, ls: lights.LightSample, wseg):
    """s = 1, next-event estimation from z = z_j (zp = z_{j-1}) to the light sample `ls`
    (`lights.sample_light` at z.p: y_0 = z.p + ls.wi ls.dist, normal ls.n); wseg: the
    shadow segment runs through the water. Returns (A0, JoinPdfs): A0 = A(y_0), the
    light's pdf of the point (selection included; delta lights: the selection);
    A_s = A(z_j): y_0 emits towards z_j -> area at z_j; A_s1 = A(z_{j-1}): z_j scatters
    the light's direction -ls.wi towards z_{j-1} -> area at z_{j-1} (its own arrival
    segment's water); B_s1 = B(y_0): z_j samples ls.wi (its wo: z.wo) -> area at y_0 (a
    surface: P_pass in the water; sun / sky: the solid-angle pdf); B_s2 = 1 (no y_{-1})."""
    water = scene.water
    inf = ~jnp.isfinite(ls.dist)
    dist = jnp.where(inf, 0.0, ls.dist)
    A0 = lights.light_point_pdf(scene, ls.light, ls.wi)
    pe = lights.emission_pdf_dir(scene, ls.light, ls.n, -ls.wi, z.p)  # the line through z_j
    cos_z = jnp.where(z.medium, 1.0, jnp.abs(vec.dot(z.n, ls.wi)))
    g = jnp.where(inf, cos_z, cos_z / jnp.maximum(dist * dist, 1e-30))
    A_s = pe * g * subpath.dist_pdf(water, wseg, z.medium, ls.dist)  # A(z_j)
    A_s1, _ = reverse_pdf(scene, z.kind, z.mat, z.n, z.p, ls.wi, z.wo, zp.p, zp.medium, zp.n,
                          z.seg_water)  # z_{j-1} from z_j, coming from y
    pb = subpath.bsdf_pdf(scene, z.kind, z.mat, None, z.wo, ls.wi, z.n)  # y from z_j
    cos_y = jnp.abs(vec.dot(ls.n, ls.wi))
    B0 = jnp.where(inf, pb, pb * cos_y / jnp.maximum(dist * dist, 1e-30)
                   * subpath.dist_pdf(water, wseg, False, ls.dist))
    return A0, JoinPdfs(A_s, A_s1, B0, jnp.ones_like(B0))


def light_tracing_join_pdfs(scene: Scene, y, yp, w: Vec3, d, wseg, yp_infinite) -> JoinPdfs:
    """t = 1, light vertex y = y_i (yp = y_{i-1}) joined to the pinhole: w the unit
    direction pinhole -> y, d the distance, wseg: the segment runs through the water;
    yp_infinite: y_{i-1} is a light vertex at infinity (then B(y_{i-1}) stays a solid-angle
    pdf). B_s1 = B(y_i): the pinhole samples w (`camera_importance`'s pdf, 0 off the film)
    -> area at y_i; B_s2 = B(y_{i-1}): y_i scatters the camera's direction -w towards
    y_{i-1} -> area at y_{i-1}. The pinhole has no light-side pdf: A_s = A_s1 = 1."""
    imp = camera_importance(scene, w)[1]
    B_s1 = imp * subpath.to_area(1.0, y.medium, y.n, w, d, wseg, scene.water)
    b2, pr = reverse_pdf(scene, y.kind, y.mat, y.n, y.p, -w, y.wo, yp.p, yp.medium, yp.n,
                         y.seg_water)
    one = jnp.ones_like(B_s1)
    return JoinPdfs(one, one, B_s1, jnp.where(yp_infinite, pr, b2))


def connection_join_pdfs(scene: Scene, y, yp, z, zp, w: Vec3, d, wseg,
                         yp_infinite) -> JoinPdfs:
    """s, t >= 2: camera vertex z = z_{t-1} (zp = z_{t-2}) joined to light vertex
    y = y_{s-1} (yp = y_{s-2}); w the unit direction z -> y, d the distance, wseg: the
    segment runs through the water; yp_infinite: y_{s-2} is a light vertex at infinity.
    A_s = A(z_{t-1}): y scatters (from y.wo) towards z -> area at z; B_s1 = B(y_{s-1}):
    z scatters (from z.wo) towards y -> area at y; A_s1 = A(z_{t-2}): z scatters the
    light's direction w towards z_{t-2}; B_s2 = B(y_{s-2}): y scatters the camera's
    direction -w towards y_{s-2}; each -> area at its vertex, with the water of that
    vertex's own segment."""
    water = scene.water
    A_s = (subpath.bsdf_pdf(scene, y.kind, y.mat, None, y.wo, -w, y.n)
           * subpath.to_area(1.0, z.medium, z.n, w, d, wseg, water))
    B_s1 = (subpath.bsdf_pdf(scene, z.kind, z.mat, None, z.wo, w, z.n)
            * subpath.to_area(1.0, y.medium, y.n, w, d, wseg, water))
    A_s1, _ = reverse_pdf(scene, z.kind, z.mat, z.n, z.p, w, z.wo, zp.p, zp.medium, zp.n,
                          z.seg_water)
    b, p4 = reverse_pdf(scene, y.kind, y.mat, y.n, y.p, -w, y.wo, yp.p, yp.medium, yp.n,
                        y.seg_water)
    return JoinPdfs(A_s, A_s1, B_s1, jnp.where(yp_infinite, p4, b))


# ---------------------------------------------------------------- the techniques
def emitter_hits(scene: Scene, cfg: RenderConfig, cam: PathEnds, verts: subpath.Vertex,
                 etas, parts, pixel=None, mnee=False):
    """s = 0: z_j on an emitter or at infinity (sky), j = 1..D: {(0, j + 1): [N, C]}.
    `pixel` [N] (the paths' pixels): the glint technique runs, and the emitter hits of its
    paths take their share of them (`_glints.emitter_share`). `mnee`: manifold next-event
    estimation runs; an emitter hit through the water surface counts it in its sums
    (`_mnee.emitter_hit_factor`)."""
    val = _emitter_hits_queued(scene, cfg, cam, verts, parts, etas, pixel, mnee)
    return {(0, j + 1): val[j - 1] for j in range(1, cfg.max_depth + 1)}


def next_event(scene: Scene, cfg: RenderConfig, cam: PathEnds, u_nee, etas, parts):
    """s = 1: next-event estimation from z_j, j = 1..D-1: {(1, j + 1): [N, C]}."""
    js = np.arange(1, cfg.max_depth)
    val = _next_event_queued(scene, cfg, cam, u_nee, parts, js, etas)
    return {(1, int(j) + 1): val[i] for i, j in enumerate(js)}


def light_tracing(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: lights.Emission,
                  cam_o: Vec3, etas, parts):
    """t = 1: y_i -> pinhole, i = 0..D-1, splatted: {(i + 1, 1): (pixel [N], value [N, C])}."""
    idx = np.arange(0, cfg.max_depth)
    pix, val = _light_tracing_queued(scene, cfg, lig, e, cam_o, parts, idx, etas)
    return {(int(i) + 1, 1): (pix[j], val[j]) for j, i in enumerate(idx)}


def connections(scene: Scene, cfg: RenderConfig, lig: PathEnds, cam: PathEnds,
                e: lights.Emission, parts, summed: bool):
    """s, t >= 2: z_{t-1} joined to y_{s-1}, s + t - 1 <= D: {(s, t): [N, C]}; `summed`:
    the family's sum per path [N, C] and its count of non-finite values instead
    (`_queue.masked_map`'s summed mode: no [J, N, C] buffer, J ~ D^2 / 2)."""
    D = cfg.max_depth
    pairs = [(s, t) for s in range(2, D + 1) for t in range(2, D + 2 - s)]
    if not pairs:
        return {}
    ss = np.array([p[0] for p in pairs])
    ts = np.array([p[1] for p in pairs])
    val = _connections_queued(scene, cfg, lig, cam, e, parts, ss, ts, summed)
    return val if summed else {pr: val[i] for i, pr in enumerate(pairs)}


def _visible_one(scene: Scene, cfg: RenderConfig, pa: Vec3, na: Vec3, ma, pb: Vec3, nb: Vec3,
                 mb):
    """`_visible` for one item (its shadow ray traced here, not queued): visibility, the
    unit direction a -> b, the distance, whether the segment runs through the water."""
    w, d, oa, wd, tmax = _segment(pa, na, ma, pb, nb, mb)
    vis = geometry.unoccluded(scene, oa, wd, tmax, cfg.march_steps)
    wseg = (geometry.inside_water(scene.water, oa) if scene.water.enabled
            else jnp.zeros((), bool))
    return vis & (d > 1e-7), w, d, wseg


def _tr_one(scene: Scene, wseg, d):
    """`_tr` for one item: [C] transmittance of a segment of length d ([1] without water)."""
    if not scene.water.enabled:
        return jnp.ones((1,), d.dtype)
    return jnp.where(wseg, media.transmittance(scene.water, d), 1.0)


def _connections_queued(scene: Scene, cfg: RenderConfig, lig: PathEnds, cam: PathEnds,
                        e: lights.Emission, parts, ss, ts, summed=False):
    """The (s, t >= 2) connections [J, N, C] as one work queue over (technique, lane)
    items: only the pairs of live, non-delta vertices run the kernel (the shadow ray, both
    scattering factors, the four join pdfs and the join weight), each gathering its four
    vertices and its entries of the MIS state. In a pool few light vertices survive their
    first bounce, so few of the J x N pairs are live."""
    N = cam.A.shape[1]
    J = len(ss)
    dt = cam.A.dtype
    C = scene.channels
    log_n = log_n_light_tracing(cfg, N, dt)
    ok = (rows(lig, ss - 1).alive & ~rows(lig, ss - 1).delta
          & rows(cam, ts - 1).alive & ~rows(cam, ts - 1).delta)
    s_of = jnp.asarray(ss, jnp.int32)
    t_of = jnp.asarray(ts, jnp.int32)

    lig_at, cam_at = vertex_table(lig), vertex_table(cam)

    def item(j, n):
        s, t = s_of[j], t_of[j]
        y, yp, z, zp = lig_at(s - 1, n), lig_at(s - 2, n), cam_at(t - 1, n), cam_at(t - 2, n)
        # ---- visibility z -> y (both ends offset on their own sides) ----
        vis, w, d, wseg = _visible_one(scene, cfg, z.p, z.n, z.medium, y.p, y.n, y.medium)
        # ---- contribution ----
        fy = subpath.eval_f(scene, y.kind, y.mat, y.wo, -w, y.n)
        fz = subpath.eval_f(scene, z.kind, z.mat, z.wo, w, z.n)
        Tr = _tr_one(scene, wseg, d)
        contrib = y.beta * fy * fz * z.beta * Tr / jnp.maximum(d * d, 1e-30)
        contrib = contrib * both_dispersed(C, y.disp, z.disp).astype(dt)
        # ---- the four pdfs the join changes ----
        A_s, A_s1, B_s1, B_s2 = connection_join_pdfs(scene, y, yp, z, zp, w, d, wseg,
                                                     (s == 2) & e.infinite[n])
        sg = jax.lax.stop_gradient
        wgt = sg(mis_form(cfg).join_weight(cfg, s, t, parts[0], parts[1], sg(A_s), sg(A_s1),
                                           sg(B_s1), sg(B_s2), e.delta[n], e.infinite[n],
                                           sg(log_n), lanes=((n,), (n,))))
        return jnp.where(vis, contrib * wgt, 0.0)

    jj = jnp.broadcast_to(jnp.arange(J, dtype=jnp.int32)[:, None], (J, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (J, N))
    # every live pair is queued, those whose segment crosses the water surface included
    # (a first queue to drop them costs more than it saves); rounds of N items: a few live
    # pairs per path at most in the shipped scenes
    return masked_map(item, ok, (jj, nn), 0.0, J, summed=summed)


def _emitter_hits_queued(scene: Scene, cfg: RenderConfig, cam: PathEnds,
                         verts: subpath.Vertex, parts, etas, pixel=None, mnee=False):
    """Emitter hits [D, N, C] (z_j, j = 1..D) as one work queue over (vertex, lane) items:
    only the live vertices that see emission (a light, or the sky after an escape) evaluate
    the join; in a pool few camera vertices do."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    log_n = log_n_light_tracing(cfg, N, dt)
    L0 = mis_form(cfg).empty_light(cfg, dt, etas)  # s = 0: an empty light side (one lane)
    sky = _sky_id(scene)
    sg = jax.lax.stop_gradient
    cam_at = vertex_table(cam)
    if cam.table is not None:  # z_j's whole record from the packed table (one gather)
        rec_at = cam.table.record
    else:
        rec_at = lambda j, n: jax.tree.map(lambda a: a[j - 1, n], verts)  # noqa: E731

    def item(i, n):  # z_j, j = i + 1: technique (0, j + 1)
        z, zp, r = cam_at(i + 1, n), cam_at(i, n), rec_at(i + 1, n)
        esc = r.escaped
        lid = jnp.where(esc, sky, jnp.maximum(r.light, 0))
        A_s, A_s1, _, _ = emitter_hit_join_pdfs(scene, z, zp, lid, esc)
        one = jnp.ones((), dt)
        s0 = jnp.asarray(0, jnp.int32)
        if mnee:  # z_{j-1} on the water surface: the manifold connection z_{j-2} - z_{j-1}
            za = cam_at(jnp.maximum(i - 1, 0), n)
            c2 = mnee_factor(scene, za, zp, z, lid, esc, i + 1, sg(A_s1))
            mj = mis_form(cfg)
            w = sg(mj.join(cfg, s0, i + 2, mj.entries(cfg, L0, s0, i + 2, (0,)),
                           mj.entries(cfg, parts[1], i + 2, s0, (n,)), sg(A_s), sg(A_s1), one,
                           one, jnp.zeros((), bool), esc, sg(log_n), c2=c2))
        else:
            w = sg(mis_form(cfg).join_weight(cfg, s0, i + 2, L0, parts[1], sg(A_s), sg(A_s1),
                                             one, one, jnp.zeros((), bool), esc, sg(log_n),
                                             lanes=((0,), (n,))))
        if pixel is not None:  # the glints' paths: the emitter hit's share of them
            z0, z1 = cam_at(0, n), cam_at(1, n)
            w = w * glint_share(scene, cfg, z0.p, z1, z, lid, esc, i + 1, pixel[n])
        return z.beta * r.Le * w

    ok = verts.alive & jnp.any(verts.Le > 0, axis=-1)
    ii = jnp.broadcast_to(jnp.arange(D, dtype=jnp.int32)[:, None], (D, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (D, N))
    # narrow rounds (N / 8 items): a round costs its width whatever it holds, and the hits
    # are few (in a pool; with a sky, up to one per path)
    return masked_map(item, ok, (ii, nn), 0.0, 8 * D)


def _next_event_queued(scene: Scene, cfg: RenderConfig, cam: PathEnds, u_nee, parts, js,
                       etas):
    """Next-event estimation [J, N, C] from z_j (j = js) as one work queue over (vertex,
    lane) items: only live, non-delta camera vertices sample a light, trace the shadow ray
    and evaluate the join."""
    N = cam.A.shape[1]
    J = len(js)
    dt = cam.A.dtype
    water = scene.water
    log_n = log_n_light_tracing(cfg, N, dt)
    is_delta = jnp.asarray([k in DELTA_LIGHTS for k in scene.lights.kind])
    zs = rows(cam, js)
    j_of = jnp.asarray(js, jnp.int32)
    sg = jax.lax.stop_gradient

    cam_at = vertex_table(cam)
    if isinstance(u_nee, Uniforms) and not u_nee.lazy:  # (no per-item hash: the table)
        u_nee = u_nee.dense()

    def shadow_ray(i, n, z):  # the light sample of item (i, n) at z and its shadow ray
        p, nz, med = z.p, z.n, z.medium
        # the light sample's uniforms hashed for this item alone (`_uniforms`), not the
        # dense table of every (depth, lane) slot, dead or alive
        u = u_nee.at(i, n) if isinstance(u_nee, Uniforms) else u_nee[i, n]
        ls = lights.sample_light(scene, p, u[0], u[1], u[2])
        inf = ~jnp.isfinite(ls.dist)
        dist = jnp.where(inf, 0.0, ls.dist)
        y = p + ls.wi * dist
        oz = subpath.spawn(p, nz, med, ls.wi)
        tmax = jnp.where(inf, jnp.inf, vec.length(y - oz) * (1.0 - 1e-4))
        return ls, inf, dist, oz, tmax

    # (every vertex is read from the trace's packed table, `vertex_table`: per-field
    # columns [D+1, N] would each be a strided copy of the whole table)
    def worth(i, n):  # False: the item contributes 0 whatever the rest computes
        ls, _, _, oz, tmax = shadow_ray(i, n, cam_at(j_of[i], n))
        return ls.valid & ~geometry.crosses_water(water, oz, ls.wi, 0.0, tmax, cfg.march_steps)

    def item(i, n):
        j = j_of[i]
        z, zp = cam_at(j, n), cam_at(j - 1, n)
        ls, inf, _, oz, tmax = shadow_ray(i, n, z)
        is_delta_l = is_delta[ls.light]
        f = subpath.eval_f(scene, z.kind, z.mat, z.wo, ls.wi, z.n)
        vis = geometry.unoccluded(scene, oz, ls.wi, tmax, cfg.march_steps)
        wseg = geometry.inside_water(water, oz) if water.enabled else jnp.zeros((), bool)
        Tr = _tr_one(scene, wseg, jnp.where(inf, jnp.inf, ls.dist))
        contrib = z.beta * f * ls.Le * Tr / ls.pdf_w
        # ---- pdfs at the join ----
        A0, (A_s, A_s1, B0, B_s2) = nee_join_pdfs(scene, z, zp, ls, wseg)
        # the fresh light sample as a one-vertex light subpath: its entries in closed form
        # (`start_entries`), not built per item from a one-vertex subpath
        s1 = jnp.asarray(1, jnp.int32)
        mj = mis_form(cfg)
        Le_ = mj.start_entries(cfg, sg(A0), is_delta_l, sg(etas[0]))
        Ce_ = mj.entries(cfg, parts[1], j + 1, s1, (n,))
        w = sg(mj.join(cfg, s1, j + 1, Le_, Ce_, sg(A_s), sg(A_s1), sg(B0), sg(B_s2),
                       is_delta_l, inf, sg(log_n)))
        return jnp.where(ls.valid & vis, contrib * w, 0.0)

    ii = jnp.broadcast_to(jnp.arange(J, dtype=jnp.int32)[:, None], (J, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (J, N))
    want = zs.alive & ~zs.delta
    if water.enabled:
        # first the light samples alone: a shadow ray whose ends lie on opposite sides of
        # the water surface is blocked (a delta interface), known from two height
        # evaluations (`crosses_water`: the march's own answer); such items (most live
        # ones in a pool) skip the shadow ray and the join
        want = want & masked_map(worth, want, (ii, nn), False, 2 * J)
    # rounds of N / 2 items (a few live NEE vertices per path in the shipped scenes)
    return masked_map(item, want, (ii, nn), 0.0, 2 * J)


def _light_tracing_queued(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: lights.Emission,
                          cam_o: Vec3, parts, idx, etas):
    """Light tracing (pixel [J, N], value [J, N, C]) from y_i (i = idx) as one work queue
    over (vertex, lane) items: only y_0 of a finite light and the live, non-delta light
    vertices project onto the film."""
    N = lig.A.shape[1]
    J = len(idx)
    dt = lig.A.dtype
    water = scene.water
    log_n = log_n_light_tracing(cfg, N, dt)
    Cp = mis_form(cfg).pinhole(cfg, log_n, dt, etas)  # z_0 alone
    i_of = jnp.asarray(idx, jnp.int32)
    sg = jax.lax.stop_gradient

    lig_at = vertex_table(lig)

    def item(k, n):
        i = i_of[k]
        y, yp = lig_at(i, n), lig_at(jnp.maximum(i - 1, 0), n)
        co = Vec3(*(c[n] for c in cam_o))
        first = i == 0
        # ---- visibility camera -> y (the pinhole as a medium-like point: no offset) ----
        vis, w, d, wseg = _visible_one(scene, cfg, co, y.n, jnp.ones((), bool), y.p, y.n,
                                       y.medium)
        pix, imp, inside = camera_importance(scene, w)
        Tr = _tr_one(scene, wseg, d)
        to_cam = -w
        # y_0: what it emits towards the camera (Le |cos|; a point light's I); y_i>0: the
        # scattering factor
        f0 = lights.emitted_toward(scene, e.light[n], to_cam, y.n)
        fi = subpath.eval_f(scene, y.kind, y.mat, y.wo, to_cam, y.n)
        fterm = jnp.where(first, f0, fi)
        contrib = y.beta * fterm * Tr * (imp / jnp.maximum(d * d, 1e-30)) / (N * cfg.tuning.chunks)
        # ---- pdfs at the join: B(y_i) by the camera, B(y_{i-1}) through y_i ----
        A_s, A_s1, B_s1, B_s2 = light_tracing_join_pdfs(scene, y, yp, w, d, wseg,
                                                        (i == 1) & e.infinite[n])
        wgt = sg(mis_form(cfg).join_weight(cfg, i + 1, jnp.asarray(1, jnp.int32), parts[0], Cp,
                                           A_s, A_s1, sg(B_s1), sg(B_s2), e.delta[n],
                                           e.infinite[n], sg(log_n), lanes=((n,), (0,))))
        return pix, jnp.where(vis & inside, contrib * wgt, 0.0)

    def worth(k, n):  # False: the item contributes 0 whatever the rest computes
        i = i_of[k]
        y = lig_at(i, n)  # (from the packed table, as in next-event estimation)
        p, ny, med = y.p, y.n, y.medium
        co = Vec3(*(c[n] for c in cam_o))
        w, _, oa, wd, tmax = _segment(co, ny, jnp.ones((), bool), p, ny, med)
        inside = camera_importance(scene, w)[2]
        if water.enabled:
            inside = inside & ~geometry.crosses_water(water, oa, wd, 0.0, tmax,
                                                      cfg.march_steps)
        return inside

    ys = rows(lig, idx)
    first = (idx == 0)[:, None]
    ok = jnp.where(first, ~e.infinite[None], ys.alive & ~ys.delta)
    kk = jnp.broadcast_to(jnp.arange(J, dtype=jnp.int32)[:, None], (J, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (J, N))
    # first the cheap part: a light vertex outside the camera's frustum, or seen through
    # the water surface (`crosses_water`, a delta interface), contributes nothing; in a
    # pool that leaves few of the live light vertices for the shadow ray and the join
    ok = ok & masked_map(worth, ok, (kk, nn), False, J)
    return masked_map(item, ok, (kk, nn), (0, 0.0), J)
