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
from ._scene import DELTA_LIGHTS, LIGHT_BACKGROUND, LIGHT_SKY, MAT_DIELECTRIC, Scene
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


# the families of the vertex-connection queue (`vertex_connection`)
NEE, LT, CONN = 0, 1, 2


def _sel(kind, nee=None, lt=None, conn=None):
    """The value of an item's family. `kind` a Python int: the queue has that family alone,
    and only its value is given (nothing of the others is traced); traced: the value of
    the families given (pytrees of one structure), selected per item."""
    vals = [(k, v) for k, v in ((NEE, nee), (LT, lt), (CONN, conn)) if v is not None]
    if isinstance(kind, int):
        return dict(vals)[kind]
    out = vals[-1][1]
    for k, v in reversed(vals[:-1]):
        out = jax.tree.map(lambda a, b, k=k: a if a is b else jnp.where(kind == k, a, b),
                           v, out)
    return out


def join_pdfs(scene: Scene, kind, z=None, zp=None, y=None, yp=None, ls=None, w=None, d=None,
              wseg=None, yp_infinite=None, imp=None, families=(NEE, LT, CONN)):
    """(A0, JoinPdfs) of a technique of the vertex-connection queue, the one implementation
    of the three families' join pdfs (`nee_join_pdfs`, `light_tracing_join_pdfs`,
    `connection_join_pdfs` are it with a static `kind`). `kind`: NEE, LT or CONN, a Python
    int, or traced among `families` (their arguments given; each pdf is then evaluated
    once with its arguments selected per item, the same arithmetic as the family alone).
    A0: the light's pdf of y_0 (next-event estimation; 1 for the others)."""
    water = scene.water
    fams = (kind,) if isinstance(kind, int) else families

    def has(k):
        return k in fams

    cam_side = has(NEE) or has(CONN)  # z_j, z_{j-1} are read
    light_side = has(LT) or has(CONN)  # y_i, y_{i-1} are read
    one = None
    if has(NEE):
        inf = ~jnp.isfinite(ls.dist)
        dist = jnp.where(inf, 0.0, ls.dist)
        A0 = lights.light_point_pdf(scene, ls.light, ls.wi)
        pe = lights.emission_pdf_dir(scene, ls.light, ls.n, -ls.wi, z.p)  # the line through z_j
        cos_z = jnp.where(z.medium, 1.0, jnp.abs(vec.dot(z.n, ls.wi)))
        g = jnp.where(inf, cos_z, cos_z / jnp.maximum(dist * dist, 1e-30))
        As_nee = pe * g * subpath.dist_pdf(water, wseg, z.medium, ls.dist)  # A(z_j)
        one = jnp.ones_like(As_nee)
    if cam_side:  # z_j's direction towards the light end: the light sample, or y
        wz = _sel(kind, nee=None if not has(NEE) else ls.wi, conn=w if has(CONN) else None)
        # z_{j-1} from z_j, coming from the light end (its own arrival segment's water)
        A_s1, _ = reverse_pdf(scene, z.kind, z.mat, z.n, z.p, wz, z.wo, zp.p, zp.medium, zp.n,
                              z.seg_water)
        pz = subpath.bsdf_pdf(scene, z.kind, z.mat, None, z.wo, wz, z.n)  # y from z_j
    if light_side:  # y_{i-1} from y_i, coming from the camera end
        b, p_inf = reverse_pdf(scene, y.kind, y.mat, y.n, y.p, -w, y.wo, yp.p, yp.medium,
                               yp.n, y.seg_water)
        B_s2 = jnp.where(yp_infinite, p_inf, b)
        to_y = subpath.to_area(1.0, y.medium, y.n, w, d, wseg, water)
        one = jnp.ones_like(B_s2)
    out = {}
    if has(NEE):
        cos_y = jnp.abs(vec.dot(ls.n, ls.wi))
        B0 = jnp.where(inf, pz, pz * cos_y / jnp.maximum(dist * dist, 1e-30)
                       * subpath.dist_pdf(water, wseg, False, ls.dist))
        out[NEE] = (A0, JoinPdfs(As_nee, A_s1, B0, one))
    if has(LT):
        imp = camera_importance(scene, w)[1] if imp is None else imp
        out[LT] = (one, JoinPdfs(one, one, imp * to_y, B_s2))
    if has(CONN):
        py = subpath.bsdf_pdf(scene, y.kind, y.mat, None, y.wo, -w, y.n)
        out[CONN] = (one, JoinPdfs(py * subpath.to_area(1.0, z.medium, z.n, w, d, wseg, water),
                                   A_s1, pz * to_y, B_s2))
    return _sel(kind, nee=out.get(NEE), lt=out.get(LT), conn=out.get(CONN))


def nee_join_pdfs(scene: Scene, z, zp, ls: lights.LightSample, wseg):
    """s = 1, next-event estimation from z = z_j (zp = z_{j-1}) to the light sample `ls`
    (`lights.sample_light` at z.p: y_0 = z.p + ls.wi ls.dist, normal ls.n); wseg: the
    shadow segment runs through the water. Returns (A0, JoinPdfs): A0 = A(y_0), the
    light's pdf of the point (selection included; delta lights: the selection);
    A_s = A(z_j): y_0 emits towards z_j -> area at z_j; A_s1 = A(z_{j-1}): z_j scatters
    the light's direction -ls.wi towards z_{j-1} -> area at z_{j-1} (its own arrival
    segment's water); B_s1 = B(y_0): z_j samples ls.wi (its wo: z.wo) -> area at y_0 (a
    surface: P_pass in the water; sun / sky: the solid-angle pdf); B_s2 = 1 (no y_{-1})."""
    return join_pdfs(scene, NEE, z=z, zp=zp, ls=ls, wseg=wseg)


def light_tracing_join_pdfs(scene: Scene, y, yp, w: Vec3, d, wseg, yp_infinite) -> JoinPdfs:
    """t = 1, light vertex y = y_i (yp = y_{i-1}) joined to the pinhole: w the unit
    direction pinhole -> y, d the distance, wseg: the segment runs through the water;
    yp_infinite: y_{i-1} is a light vertex at infinity (then B(y_{i-1}) stays a solid-angle
    pdf). B_s1 = B(y_i): the pinhole samples w (`camera_importance`'s pdf, 0 off the film)
    -> area at y_i; B_s2 = B(y_{i-1}): y_i scatters the camera's direction -w towards
    y_{i-1} -> area at y_{i-1}. The pinhole has no light-side pdf: A_s = A_s1 = 1."""
    return join_pdfs(scene, LT, y=y, yp=yp, w=w, d=d, wseg=wseg, yp_infinite=yp_infinite)[1]


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
    return join_pdfs(scene, CONN, z=z, zp=zp, y=y, yp=yp, w=w, d=d, wseg=wseg,
                     yp_infinite=yp_infinite)[1]


# ---------------------------------------------------------------- the techniques
def emitter_hits(scene: Scene, cfg: RenderConfig, cam: PathEnds, verts: subpath.Vertex,
                 etas, parts, glint_roots=None, mnee=False):
    """s = 0: z_j on an emitter or at infinity (sky), j = 1..D: {(0, j + 1): [N, C]}.
    `glint_roots` (ok [R, N], s [R, N]: F_pixel of each path's z_2, `_glints.Found.share`):
    the glint technique runs, and the emitter hits of its paths take their share of them
    (`_glints.emitter_share`). `mnee`: manifold next-event estimation runs; an emitter hit
    through the water surface counts it in its sums (`_mnee.emitter_hit_factor`)."""
    val = _emitter_hits_queued(scene, cfg, cam, verts, parts, etas, glint_roots, mnee)
    return {(0, j + 1): val[j - 1] for j in range(1, cfg.max_depth + 1)}


def next_event(scene: Scene, cfg: RenderConfig, cam: PathEnds, u_nee, etas, parts):
    """s = 1: next-event estimation from z_j, j = 1..D-1: {(1, j + 1): [N, C]} (the
    vertex-connection queue with this family alone)."""
    return vertex_connection(scene, cfg, None, cam, None, u_nee, None, etas, parts, (NEE,))


def light_tracing(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: lights.Emission,
                  cam_o: Vec3, etas, parts):
    """t = 1: y_i -> pinhole, i = 0..D-1, splatted: {(i + 1, 1): (pixel [N], value [N, C])}
    (the vertex-connection queue with this family alone)."""
    return vertex_connection(scene, cfg, lig, None, e, None, cam_o, etas, parts, (LT,))


def connections(scene: Scene, cfg: RenderConfig, lig: PathEnds, cam: PathEnds,
                e: lights.Emission, parts, summed: bool):
    """s, t >= 2: z_{t-1} joined to y_{s-1}, s + t - 1 <= D: {(s, t): [N, C]} (the
    vertex-connection queue with this family alone); `summed`: the family's sum per path
    [N, C] and its count of non-finite values instead."""
    out = vertex_connection(scene, cfg, lig, cam, e, None, None, (0.0, 0.0), parts, (CONN,),
                            summed=summed)
    if summed:
        return {} if out is None else (out[0], out[2])
    return out


def families(cfg: RenderConfig) -> tuple[int, ...]:
    """The families of the vertex-connection queue that `cfg`'s algorithm runs: next-event
    estimation (s = 1, max_depth >= 2), light tracing (t = 1) and the connections
    (s, t >= 2, max_depth >= 3)."""
    tech = cfg.techniques
    D = cfg.max_depth
    out = []
    if tech.camera_paths and tech.nee and D >= 2:
        out.append(NEE)
    if tech.light_paths and tech.light_tracing:
        out.append(LT)
    if tech.light_paths and tech.connections and D >= 3:
        out.append(CONN)
    return tuple(out)


def queue_rows(cfg: RenderConfig) -> int:
    """Techniques (rows of N items) of `cfg`'s vertex-connection queue."""
    return len(_rows(cfg, families(cfg))["kind"])


def _rows(cfg: RenderConfig, fams) -> dict:
    """The queue's rows (one technique each, every lane an item) as static arrays: family,
    s, t, the camera vertex z_j (jz), the light vertex y_i (iy), the row of the light
    samples' uniforms (next-event estimation), and the technique labels in row order."""
    D = cfg.max_depth
    rows = []
    if NEE in fams:  # (1, j + 1) from z_j
        rows += [(NEE, 1, j + 1, j, 0, j - 1) for j in range(1, D)]
    if LT in fams:  # (i + 1, 1) from y_i
        rows += [(LT, i + 1, 1, 0, i, 0) for i in range(D)]
    if CONN in fams:  # (s, t): z_{t-1} joined to y_{s-1}
        rows += [(CONN, s, t, t - 1, s - 1, 0) for s in range(2, D + 1)
                 for t in range(2, D + 2 - s)]
    a = np.array(rows, np.int32).reshape(-1, 6)
    return dict(kind=a[:, 0], s=a[:, 1], t=a[:, 2], jz=a[:, 3], iy=a[:, 4], u=a[:, 5],
                labels=[(int(r[1]), int(r[2])) for r in a])


def _tr_one(scene: Scene, wseg, d):
    """`_tr` for one item: [C] transmittance of a segment of length d ([1] without water)."""
    if not scene.water.enabled:
        return jnp.ones((1,), d.dtype)
    return jnp.where(wseg, media.transmittance(scene.water, d), 1.0)


def _emitter_hits_queued(scene: Scene, cfg: RenderConfig, cam: PathEnds,
                         verts: subpath.Vertex, parts, etas, glint_roots=None, mnee=False):
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

    def item(i, n, glint=True):  # z_j, j = i + 1: technique (0, j + 1)
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
        if glint_roots is not None and glint:  # the glints' paths: the hit's share of them
            z0, z1 = cam_at(0, n), cam_at(1, n)
            w = w * glint_share(scene, cfg, z0.p, z1, z, lid, esc, i + 1, None,
                                jax.tree.map(lambda a: a[:, n], glint_roots))
        return z.beta * r.Le * w

    ok = verts.alive & jnp.any(verts.Le > 0, axis=-1)
    ii = jnp.broadcast_to(jnp.arange(D, dtype=jnp.int32)[:, None], (D, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (D, N))
    # narrow rounds (N / 8 items): a round costs its width whatever it holds, and the hits
    # are few (in a pool; with a sky, up to one per path)
    if glint_roots is None:
        return masked_map(item, ok, (ii, nn), 0.0, 8 * D)
    # the glint share (its chain's Jacobian) only where the path can be a glint's, z_2
    # seen in the water surface at z_1: a queue of its own, far narrower (a few such hits
    # a pass)
    water = scene.water
    glint = (ii == 1) & ((cam.kind[1] == MAT_DIELECTRIC) & (cam.mat[1] == water.mat))[None, :]
    return (masked_map(lambda i, n: item(i, n, glint=False), ok & ~glint, (ii, nn), 0.0, 8 * D)
            + masked_map(item, ok & glint, (ii, nn), 0.0, 64 * D))


def _entries(cfg: RenderConfig, kind, nee=None, lt=None, conn=None):
    """`_sel` of the families' MIS entries, a field that one of them lacks (the manifold
    factors of a light side with manifold next-event estimation) neutral in the others
    (log factor 0, no manifold connection)."""
    vals = [v for v in (nee, lt, conn) if v is not None]
    if len(vals) > 1 and hasattr(vals[0], "_fields"):
        def full(e):
            fill = {}
            for f in e._fields:
                if getattr(e, f) is None:
                    ref = next((getattr(o, f) for o in vals if getattr(o, f) is not None), None)
                    if ref is not None:
                        fill[f] = jnp.zeros_like(ref)
            return e._replace(**fill)
        nee, lt, conn = (None if v is None else full(v) for v in (nee, lt, conn))
    return _sel(kind, nee=nee, lt=lt, conn=conn)


def vertex_connection(scene: Scene, cfg: RenderConfig, lig: PathEnds | None,
                      cam: PathEnds | None, e: lights.Emission | None, u_nee,
                      cam_o: Vec3 | None, etas, parts, fams, summed=False):
    """Vertex connection: next-event estimation (s = 1: a fresh light sample y_0 per camera
    vertex z_j, j = 1..D-1), light tracing (t = 1: light vertex y_i, i = 0..D-1, through
    the pinhole, splatted) and the connections (s, t >= 2: z_{t-1} joined to y_{s-1} of the
    light subpath with the same index), whichever of the families `fams` are given, as
    one work queue over (technique, lane) items (`_queue.masked_map`): one kernel for
    every item, with one copy of what the three have in common (the shadow ray, the
    scattering factors at both ends, the join pdfs (`join_pdfs`) and the MIS join),
    each family's own part (the light sample, the pinhole) selected per item.

    First the cheap part, where it drops items: a light sample whose shadow ray, or a
    light vertex whose segment to the pinhole, has its ends on opposite sides of the water
    surface (a delta interface: blocked; `crosses_water`, two height evaluations) or a
    light vertex outside the camera's frustum contributes nothing; in a pool that leaves
    few of the live items. The connections' pairs are all queued (a first pass over them
    costs more than it saves: few light vertices survive their first bounce).

    Returns {(s, t): value}: [N, C] per camera path, (pixel [N], value [N, C]) for a
    light-tracing technique. `summed` (the pass wants only its image): the items added
    into one [N, C] array per camera path and one [P, C] array per pixel (light tracing's
    splats) instead, with the count of non-finite values zeroed in them: (camera [N, C],
    pixels [P, C], count); None without items."""
    if not fams:
        return None
    R = _rows(cfg, fams)
    if len(R["kind"]) == 0:
        return None
    ends = cam if cam is not None else lig
    N = ends.A.shape[1]
    J = len(R["kind"])
    dt = ends.A.dtype
    C = scene.channels
    P = scene.camera.height * scene.camera.width
    water = scene.water
    cam_side = NEE in fams or CONN in fams
    light_side = LT in fams or CONN in fams
    log_n = log_n_light_tracing(cfg, N, dt)
    mj = mis_form(cfg)
    sg = jax.lax.stop_gradient
    is_delta = jnp.asarray([k in DELTA_LIGHTS for k in scene.lights.kind])
    kind_of, s_of, t_of = (jnp.asarray(R[k]) for k in ("kind", "s", "t"))
    jz_of, iy_of, u_of = (jnp.asarray(R[k]) for k in ("jz", "iy", "u"))
    static_kind = fams[0] if len(fams) == 1 else None
    cam_at = vertex_table(cam) if cam_side else None
    lig_at = vertex_table(lig) if light_side else None
    if NEE in fams and isinstance(u_nee, Uniforms) and not u_nee.lazy:
        u_nee = u_nee.dense()  # (no per-item hash: the table)
    Cp = mj.pinhole(cfg, log_n, dt, etas) if LT in fams else None  # z_0 alone

    def light_sample(r, n, z):  # next-event estimation: the light sample at z, its shadow ray
        # the light sample's uniforms hashed for this item alone (`_uniforms`), not the
        # dense table of every (depth, lane) slot, dead or alive
        i = u_of[r]
        u = u_nee.at(i, n) if isinstance(u_nee, Uniforms) else u_nee[i, n]
        ls = lights.sample_light(scene, z.p, u[0], u[1], u[2])
        inf = ~jnp.isfinite(ls.dist)
        dist = jnp.where(inf, 0.0, ls.dist)
        y = z.p + ls.wi * dist
        oz = subpath.spawn(z.p, z.n, z.medium, ls.wi)
        tmax = jnp.where(inf, jnp.inf, vec.length(y - oz) * (1.0 - 1e-4))
        return ls, inf, oz, tmax

    def segment(kind, n, z, y):  # light tracing, connections: the segment to y and its ray
        co = None if LT not in fams else Vec3(*(c[n] for c in cam_o))
        one = jnp.ones((), bool)
        pa = _sel(kind, lt=co, conn=None if z is None else z.p)
        na = _sel(kind, lt=y.n, conn=None if z is None else z.n)
        ma = _sel(kind, lt=one, conn=None if z is None else z.medium)
        return _segment(pa, na, ma, y.p, y.n, y.medium)

    def kind_at(r):
        return static_kind if static_kind is not None else kind_of[r]

    def ends_at(r, n):
        z = zp = y = yp = None
        if cam_side:
            z, zp = cam_at(jz_of[r], n), cam_at(jz_of[r] - 1, n)
        if light_side:
            y, yp = lig_at(iy_of[r], n), lig_at(jnp.maximum(iy_of[r] - 1, 0), n)
        return z, zp, y, yp

    # ---- the cheap part: items that cannot contribute, dropped before the queue
    def worth(r, n):  # False: the item contributes 0 whatever the rest computes
        kind = kind_at(r) if len(wfams) > 1 else wfams[0]
        z, _, y, _ = ends_at(r, n)
        nee = lt = None
        if NEE in wfams:
            ls, _, oz, tmax_n = light_sample(r, n, z)
            nee = (oz, ls.wi, tmax_n)
        if LT in wfams:
            w, _, oa, wd, tmax_s = segment(LT, n, None, y)
            lt = (oa, wd, tmax_s)
        o, dv, tmax = _sel(kind, nee=nee, lt=lt)
        cross = (geometry.crosses_water(water, o, dv, 0.0, tmax, cfg.march_steps)
                 if water.enabled else jnp.zeros((), bool))
        return _sel(kind, nee=None if nee is None else ls.valid & ~cross,
                    lt=None if lt is None else camera_importance(scene, w)[2] & ~cross)

    # ---- one item: the shadow ray, both ends' factors, the join pdfs, the MIS join
    def item(r, n):
        kind = kind_at(r)
        s, t = s_of[r], t_of[r]
        z, zp, y, yp = ends_at(r, n)
        if NEE in fams:
            ls, inf, oz, tmax_n = light_sample(r, n, z)
            is_delta_l = is_delta[ls.light]
        if light_side:
            w, d, oa, wd, tmax_s = segment(kind, n, z, y)
        nee = None if NEE not in fams else (oz, ls.wi, tmax_n)
        seg = None if not light_side else (oa, wd, tmax_s)
        o, dv, tmax = _sel(kind, nee=nee, lt=seg if LT in fams else None,
                           conn=seg if CONN in fams else None)
        vis = geometry.unoccluded(scene, o, dv, tmax, cfg.march_steps)
        wseg = geometry.inside_water(water, o) if water.enabled else jnp.zeros((), bool)
        d_nee = None if NEE not in fams else jnp.where(inf, jnp.inf, ls.dist)
        Tr = _tr_one(scene, wseg, _sel(kind, nee=d_nee, lt=d if LT in fams else None,
                                       conn=d if CONN in fams else None))
        # ---- the scattering factors: at z towards the light end, at y towards the camera end
        if cam_side:
            wz = _sel(kind, nee=None if NEE not in fams else ls.wi,
                      conn=w if CONN in fams else None)
            fz = subpath.eval_f(scene, z.kind, z.mat, z.wo, wz, z.n)
        if light_side:
            fy = subpath.eval_f(scene, y.kind, y.mat, y.wo, -w, y.n)
        imp = pix = inside = None
        if LT in fams:
            pix, imp, inside = camera_importance(scene, w)
        # ---- the four pdfs the join changes ----
        yp_inf = None if not light_side else (iy_of[r] == 1) & e.infinite[n]
        A0, (A_s, A_s1, B_s1, B_s2) = join_pdfs(
            scene, kind, z=z, zp=zp, y=y, yp=yp, ls=None if NEE not in fams else ls,
            w=w if light_side else None, d=d if light_side else None, wseg=wseg,
            yp_infinite=yp_inf, imp=imp, families=fams)
        # ---- the MIS join: the fresh light sample's entries in closed form
        # (`start_entries`), the pinhole's (light tracing), or the subpaths' partials
        # (a subpath's partials are read once, shared by the families that read them)
        lig_e = mj.entries(cfg, parts[0], s, t, (n,)) if light_side else None
        cam_e = mj.entries(cfg, parts[1], t, s, (n,)) if cam_side else None
        Le_ = _entries(cfg, kind,
                       nee=None if NEE not in fams else mj.start_entries(
                           cfg, sg(A0), is_delta_l, sg(etas[0])),
                       lt=lig_e if LT in fams else None, conn=lig_e if CONN in fams else None)
        Ce_ = _entries(cfg, kind, nee=cam_e if NEE in fams else None,
                       lt=None if LT not in fams else mj.entries(cfg, Cp, t, s, (0,)),
                       conn=cam_e if CONN in fams else None)
        if light_side:
            ed, ei = e.delta[n], e.infinite[n]
        dl = _sel(kind, nee=None if NEE not in fams else is_delta_l,
                  lt=ed if LT in fams else None, conn=ed if CONN in fams else None)
        il = _sel(kind, nee=None if NEE not in fams else inf,
                  lt=ei if LT in fams else None, conn=ei if CONN in fams else None)
        wgt = sg(mj.join(cfg, s, t, Le_, Ce_, sg(A_s), sg(A_s1), sg(B_s1), sg(B_s2), dl, il,
                         sg(log_n)))
        # ---- each family's contribution (its own arithmetic) ----
        val = {}
        if NEE in fams:  # (the pdf of another family's item's stand-in sample: 1, so that
            # nothing infinite enters the gradient through the branch not taken)
            pdf_w = ls.pdf_w if static_kind is not None else jnp.where(kind == NEE, ls.pdf_w, 1.0)
            c = z.beta * fz * ls.Le * Tr / pdf_w
            val[NEE] = jnp.where(ls.valid & vis, c * wgt, 0.0)
        if LT in fams:  # y_0: what it emits towards the camera (Le |cos|; a point light's
            # I); y_i>0: the scattering factor
            f0 = lights.emitted_toward(scene, e.light[n], -w, y.n)
            c = (y.beta * jnp.where(iy_of[r] == 0, f0, fy) * Tr
                 * (imp / jnp.maximum(d * d, 1e-30)) / (N * cfg.tuning.chunks))
            val[LT] = jnp.where(vis & (d > 1e-7) & inside, c * wgt, 0.0)
        if CONN in fams:
            c = y.beta * fy * fz * z.beta * Tr / jnp.maximum(d * d, 1e-30)
            c = c * both_dispersed(C, y.disp, z.disp).astype(dt)
            val[CONN] = jnp.where(vis & (d > 1e-7), c * wgt, 0.0)
        v = _sel(kind, nee=val.get(NEE), lt=val.get(LT), conn=val.get(CONN))
        if summed:  # its row: the camera path's, or (light tracing) N + its pixel
            if LT not in fams:  # (every item in its path's row)
                return v
            splat = N + jnp.clip(pix, 0, P - 1)
            return (splat if static_kind is not None else jnp.where(kind == LT, splat, n)), v
        return (jnp.zeros((), jnp.int32) if pix is None else pix), v

    # ---- which items run
    if cam_side:
        zs = rows(cam, R["jz"])
        cam_ok = zs.alive & ~zs.delta
    if light_side:
        ys = rows(lig, R["iy"])
        light_ok = ys.alive & ~ys.delta
    kinds = R["kind"][:, None]
    ok = jnp.zeros((J, N), bool)
    if NEE in fams:
        ok = ok | ((kinds == NEE) & cam_ok)
    if LT in fams:  # y_0 of a finite light, and the live non-delta light vertices
        first = (R["iy"] == 0)[:, None]
        ok = ok | ((kinds == LT) & jnp.where(first, ~e.infinite[None], light_ok))
    if CONN in fams:
        ok = ok | ((kinds == CONN) & light_ok & cam_ok)
    rr = jnp.broadcast_to(jnp.arange(J, dtype=jnp.int32)[:, None], (J, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (J, N))
    wfams = tuple(f for f in fams if f == LT or (f == NEE and water.enabled))
    if wfams:
        wrows = np.isin(R["kind"], wfams)[:, None]
        keep = masked_map(worth, ok & wrows, (rr, nn), False, J)  # rounds of N items
        ok = ok & (~wrows | keep)
    # rounds of N items (a few live items per path in the shipped scenes)
    if summed:
        out, bad = masked_map(item, ok, (rr, nn), 0.0, J, summed=True,
                              summed_rows=N + P if LT in fams else None)
        return out[:N], (out[N:] if LT in fams else None), bad
    pix, val = masked_map(item, ok, (rr, nn), (0, 0.0), J)
    return {lab: ((pix[r], val[r]) if R["kind"][r] == LT else val[r])
            for r, lab in enumerate(R["labels"])}
