"""Vertex merging on the bidirectional core: progressive photon mapping (`ppm`) and merging
with MIS (`bpm`, `vcm`: `vertex_merging` below).

Photons are the stored light-subpath vertices y_i, i >= 1, that are alive and not delta
(surface or medium). Each camera subpath follows its delta prefix to its first non-delta
vertex z_j and gathers there, like with like (surface photons on the same side of a
surface, with the disk kernel 1 / (pi r^2); medium photons with the sphere kernel
1 / (4/3 pi r^3)), over the sorted hash grid (`_hashgrid`), with the 1/N light-path
normalisation:
    L += beta_z * sum_photons f_z(wo_z, wo_y) beta_y / (kernel N),  segments i + j <= D,
with f_z the BSDF without its cosine on surfaces and the phase function over sigma_s in the
medium (both throughputs carry sigma_s of their own scattering event; the merged path has
one, see `_one_scattering_event`).
Emission met along the delta prefix (and at z_j itself) is added with weight 1: pure
photon mapping has no other technique for it.

Radii: surfaces and the medium have their own progressive schedules (`pass_radius`); the
grid is built for the larger one and each pair is accepted with its own kind's radius.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _hashgrid as hashgrid
from . import _queue as queue
from . import _subpath as subpath
from . import _vec as vec
from ._config import RenderConfig
from ._mis import mis_form
from ._path import both_dispersed, log_n_light_tracing, reverse_pdf
from ._scene import Scene
from ._subpath import PathEnds
from ._vec import Vec3


class Radii(NamedTuple):
    """Merging radii of one pass: disk kernel on surfaces, sphere kernel in the medium."""

    surface: Array
    medium: Array


def pass_radius(cfg: RenderConfig, scene: Scene, pass_index) -> Radii:
    """Progressive radii of pass i = pass_index + 1 (Knaus & Zwicker 2011):
        surfaces  r_i = r_1 i^((alpha - 1) / 2)   (2-D density estimate),
        medium    r_i = r_1 i^((alpha - 1) / 3)   (3-D: the variance of a sphere kernel
                  grows as r^-3, so the radius shrinks more slowly for the same alpha),
    r_1 = `cfg.radius` times the scene's view radius (`Scene.view_radius`: the size of what
    the camera sees, `_io._view`), neither below the smallest radius
    the hash grid resolves in the scene's float dtype at the scene's extent
    (`resolvable_radius`): a schedule that reaches it stays there (the render goes on, its
    merging bias no longer shrinks; the host driver says so once, `radius_floor_note`). The
    pass index alone drives the schedule, so resumed and sharded renders agree."""
    rv = scene.view_radius
    i = jnp.asarray(pass_index, rv.dtype) + 1.0
    r1 = cfg.radius * rv
    floor = FLOOR_MARGIN * resolvable_radius(scene)
    return Radii(jax.lax.stop_gradient(jnp.maximum(r1 * i ** ((cfg.alpha - 1.0) / 2.0), floor)),
                 jax.lax.stop_gradient(jnp.maximum(r1 * i ** ((cfg.alpha - 1.0) / 3.0), floor)))


FLOOR_MARGIN = 1.01  # the floor a little above the grid's limit (its float rounding)


def resolvable_radius(scene: Scene) -> Array:
    """The smallest merging radius (metres, traced) that the hash grid resolves in the
    scene's float dtype for every point of the scene's box: `_hashgrid.build`'s `precise`
    condition, |coordinate| + span within CELL_MARGIN / (32 u) cells of 2 r (1 +
    CELL_MARGIN), with the box's largest |coordinate| + span (`precise_radius` on the host
    in float64)."""
    lo, hi = scene.bounds[0], scene.bounds[1]
    span = jnp.max(jnp.maximum(jnp.abs(lo), jnp.abs(hi)) + (hi - lo))
    u = float(np.finfo(np.dtype(scene.bounds.dtype)).eps) / 2
    cells = hashgrid.CELL_MARGIN / (32.0 * u) - 2.0
    return jax.lax.stop_gradient(span / (cells * 2.0 * (1.0 + hashgrid.CELL_MARGIN)))


def precise_radius(scene: Scene) -> tuple[float, float]:
    """(smallest merging radius in metres the hash grid resolves in the scene's float dtype
    at the scene's extent, that extent |coordinate| + span in metres): the host's float64
    `resolvable_radius`."""
    lo, hi = (np.asarray(b, np.float64) for b in np.asarray(scene.bounds))
    span = float(np.max(np.maximum(np.abs(lo), np.abs(hi)) + (hi - lo)))
    u = float(np.finfo(np.dtype(scene.bounds.dtype)).eps) / 2
    cells = hashgrid.CELL_MARGIN / (32.0 * u) - 2.0
    return span / (cells * 2.0 * (1.0 + hashgrid.CELL_MARGIN)), span


def radius_floor_note(scene: Scene, cfg: RenderConfig, passes: int) -> str | None:
    """Host side: the one-line warning of a render of `passes` passes whose radius schedule
    reached the hash grid's limit in the scene's float dtype (`pass_radius` keeps it there),
    or None (also without merging). A float64 scene
    (`load_scene(..., dtype=jnp.float64)`) resolves ~10^8 times smaller radii."""
    if cfg.techniques.merging is None or passes < 1:
        return None
    r_min, span = precise_radius(scene)
    r1 = cfg.radius * float(scene.view_radius)
    r = r1 * float(passes) ** ((cfg.alpha - 1.0) / 2.0)  # the last pass's surface radius
    if r > FLOOR_MARGIN * r_min:
        return None
    first = r1 <= FLOOR_MARGIN * r_min
    when = ("from the first pass" if first else
            f"from pass {int(math.ceil((FLOOR_MARGIN * r_min / r1) ** (2.0 / (cfg.alpha - 1.0))))}")
    return (f"config.radius: the merging radius stayed at {FLOOR_MARGIN * r_min:.3g} m, what "
            f"the hash grid resolves in {np.dtype(scene.bounds.dtype).name} at this scene's "
            f"extent ({span:.3g} m), {when}: the merging bias stopped shrinking there; a "
            f"float64 scene resolves smaller radii")


def log_etas(radius, n_paths, dtype):
    """log of the merging multiplicity times kernel size, eta_VCM (Georgiev et al. 2012):
    (surface pi r_s^2 N, medium 4/3 pi r_m^3 N); `radius` is a `_merge.Radii` (surface,
    medium) or one radius for both; zeros when there is no merging."""
    if radius is None:
        z = jnp.zeros((), dtype)
        return z, z
    ln = jnp.log(jnp.asarray(n_paths, dtype))
    rs, rm = (radius.surface, radius.medium) if hasattr(radius, "medium") else (radius, radius)
    rs = jnp.asarray(rs, dtype)
    rm = jnp.asarray(rm, dtype)
    return ln + jnp.log(jnp.pi * rs * rs), ln + jnp.log(4.0 / 3.0 * jnp.pi * rm * rm * rm)


def kernel_size(medium, radius: Radii):
    """pi r^2 (surface disk) or 4/3 pi r^3 (medium sphere), per vertex."""
    return jnp.where(medium, 4.0 / 3.0 * jnp.pi * radius.medium**3, jnp.pi * radius.surface**2)


def _within(medium, d2, radius: Radii):
    r = jnp.where(medium, radius.medium, radius.surface)
    return d2 <= r * r


def _search_radius(radius: Radii):
    return jnp.maximum(radius.surface, radius.medium)


def _one_scattering_event(scene: Scene, medium):
    """[B, C] factor 1/sigma_s at medium merges, 1 on surfaces. Both subpath throughputs
    carry the scattering coefficient of their own free-flight event (sigma_s T / p), but
    the merged path has one scattering event at x_s, so sigma_s must count once (Jensen's
    volume radiance estimate L = 1/sigma_s sum p dPhi / (4/3 pi r^3)). A channel with
    sigma_s = 0 does not scatter at all: its merged contribution is 0."""
    sig = scene.water.sigma_s
    inv = jnp.where(sig > 0, 1.0 / jnp.where(sig > 0, sig, 1.0), 0.0)
    return jnp.where(medium[:, None], inv[None, :], 1.0)


PHOTON_FRACTION = 0.5  # default photon room: this share of the light-vertex slots,
PHOTON_MIN_ROOM = 4096  # ... and at least this many (smaller passes keep every slot)


def photon_room(cfg: RenderConfig, slots: int) -> int:
    """Static number of photons the hash grid holds for `slots` light-vertex slots
    ([max(D - 1, 1), paths] flattened): `cfg.tuning.photon_capacity` if set, else
    PHOTON_FRACTION of the slots rounded up to a multiple of 1024 and at least
    PHOTON_MIN_ROOM; never more than the slots (then nothing is compacted). Half the slots
    holds the valid photons of every shipped scene at depth 8: a small share of the slots
    in the open pools, a larger one in the closed, lit Cornell boxes, which a smaller
    default room would send through a re-run (and a recompile) of their first pass.
    Shallow depths have larger shares; those overflow once, and the host re-run
    (`more_room`) gives them room."""
    if cfg.tuning.photon_capacity:
        room = int(cfg.tuning.photon_capacity)
    else:
        room = max(PHOTON_MIN_ROOM, -(-int(math.ceil(slots * PHOTON_FRACTION)) // 1024) * 1024)
    return min(room, slots)


def more_room(cfg: RenderConfig, need=None, photon_overflow=None, photons=None) -> RenderConfig:
    """Host side: the config of the re-run after a merging overflow (jax-md's
    re-allocation pattern; never truncate). Candidates: the power of two that holds the
    longest candidate list `need`, at least twice the old capacity (with `need` None: twice
    the old one, always). Photons (flagged by `photon_overflow`; None: inferred, the
    candidates had room): at least twice the old room and a power of two with a quarter
    more than the valid `photons` (the next passes' counts scatter around it); with no
    count, every light-vertex slot. The photon room is a power of two so that the re-run
    programs stay few; one re-run is enough for the pass that overflowed."""
    cand = need is None or need > cfg.tuning.merge_capacity
    if photon_overflow is None:
        photon_overflow = not cand
    if cand:
        cap = 2 * cfg.tuning.merge_capacity
        if need is not None:
            cap = max(cap, 1 << max(need - 1, 1).bit_length())
        cfg = cfg.tuned(merge_capacity=cap)
    if photon_overflow:
        if photons is None:
            room = 2**30  # more than any pass has slots: no compaction
        else:
            want = photons + photons // 4
            room = max(2 * cfg.tuning.photon_capacity, 1 << max(want - 1, 1).bit_length())
        cfg = cfg.tuned(photon_capacity=room)
    return cfg


class Photons(NamedTuple):
    """The hash grid over the valid photons, compacted into `photon_room` slots.

    grid:     `hashgrid.HashGrid` over the compacted photons.
    slot:     [room] int32 compacted photon -> its light-vertex slot (clamped in range;
              None: no compaction, the grid holds every slot).
    count:    valid photons (the room that would have been enough).
    overflow: more valid photons than room (some are missing: the host re-runs the pass).
    """

    grid: hashgrid.HashGrid
    slot: Array | None
    count: Array
    overflow: Array


def photon_grid(cfg: RenderConfig, p: Vec3, valid, radius: Radii, dtype) -> Photons:
    """Hash grid of the photons `p` ([M] light-vertex slots) where `valid` holds. Only the
    valid ones are built: they are gathered in slot order into a static room
    (`photon_room`, `_queue.compact`), so the sort, hashes and bucket counts run over the
    room instead of every slot. The table size and the in-bucket order (slot order) are
    those of the uncompacted grid, so every query meets the same candidates in the same
    order (the same sums, bit for bit) as long as nothing overflows."""
    M = p.x.shape[0]
    table = 1 << max(4, int(math.ceil(math.log2(max(M, 16)))))
    room = photon_room(cfg, M)
    r = _search_radius(radius)
    if room >= M:
        grid = hashgrid.build(p.x, p.y, p.z, valid, r, table_size=table, dtype=dtype)
        return Photons(grid, None, jnp.sum(valid, dtype=jnp.int32), jnp.zeros((), bool))
    idx, count, overflow = queue.compact(valid, room)
    slot = jnp.minimum(idx, M - 1)
    grid = hashgrid.build(p.x[slot], p.y[slot], p.z[slot],
                          jnp.arange(room, dtype=jnp.int32) < count, r, table_size=table,
                          dtype=dtype)
    return Photons(grid, slot, count, overflow)


def _photon_slots(ph: Photons, fn):
    """`fn(qi, pj, d2)` of light-vertex slots pj, as a kernel over the grid's photons."""
    if ph.slot is None:
        return fn
    return lambda qi, pj, d2: fn(qi, ph.slot[pj], d2)


class Merged(NamedTuple):
    """What a merging stage reports besides its estimate (all sticky scalars)."""

    overflow: Array  # something is missing (candidates or photons): re-run with room
    need: Array  # longest candidate list of a gather point
    photons: Array  # valid photons (the photon room that would have been enough)
    photon_overflow: Array  # more valid photons than photon room
    imprecise: Array  # the hash grid cannot resolve the radius at the photons' coordinates
    # in the scene's float dtype (`_hashgrid.build`'s `precise`): neighbours may be missed


def photon_gather(scene: Scene, cfg: RenderConfig, cam: PathEnds, cverts: subpath.Vertex,
                  lig: PathEnds, radius):
    """PPM estimate per camera lane [N, C] and the gather's `Merged` report (overflow
    flags, the longest candidate list of any gather point, the valid photons)."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    C = scene.channels
    # ---- photons: y_1 .. y_{D-1} flattened ----
    idx = np.arange(1, lig.A.shape[0])
    flat = lambda a: a[idx].reshape((-1,) + a.shape[2:])  # noqa: E731
    pp = Vec3(*(flat(c) for c in lig.p))
    pn = Vec3(*(flat(c) for c in lig.n))
    pwo = Vec3(*(flat(c) for c in lig.wo))
    pbeta = flat(lig.beta)
    pmed = flat(lig.medium)
    pdisp = flat(lig.disp)
    pdepth = jnp.repeat(jnp.asarray(idx, jnp.int32), N)
    pvalid = flat(lig.alive) & ~flat(lig.delta)
    ph = photon_grid(cfg, pp, pvalid, radius, dt)

    # ---- gather vertex: the first non-delta camera vertex ----
    nd = cam.alive[1:] & ~cam.delta[1:]  # [D, N] for z_1..z_D
    has = jnp.any(nd, axis=0)
    j = jnp.argmax(nd, axis=0).astype(jnp.int32) + 1  # index into cam (z_j)
    lane = jnp.arange(N)
    g = lambda a: a[j, lane]  # noqa: E731
    zp = Vec3(*(g(c) for c in cam.p))
    zn = Vec3(*(g(c) for c in cam.n))
    zwo = Vec3(*(g(c) for c in cam.wo))
    zbeta, zmed, zkind, zmat = g(cam.beta), g(cam.medium), g(cam.kind), g(cam.mat)
    zdisp = g(cam.disp)

    def kernel(qi, pj, d2):
        same = zmed[qi] == pmed[pj]
        facing = zmed[qi] | (vec.dot(Vec3(zn.x[qi], zn.y[qi], zn.z[qi]),
                                   Vec3(pn.x[pj], pn.y[pj], pn.z[pj])) > 0)
        wo_p = Vec3(pwo.x[pj], pwo.y[pj], pwo.z[pj])
        wo_z = Vec3(zwo.x[qi], zwo.y[qi], zwo.z[qi])
        nz = Vec3(zn.x[qi], zn.y[qi], zn.z[qi])
        f = jax.vmap(lambda k_, m_, a, b, n_: subpath.eval_f(scene, k_, m_, a, b, n_))(
            zkind[qi], zmat[qi], wo_z, wo_p, nz)
        cosp = jnp.where(zmed[qi], 1.0, jnp.abs(vec.dot(nz, wo_p)))
        f = f / jnp.maximum(cosp, 1e-8)[:, None]  # f without the cosine (density does it)
        depth_ok = pdepth[pj] + j[qi] <= D
        ok = same & facing & depth_ok & _within(zmed[qi], d2, radius)
        f = f * _one_scattering_event(scene, zmed[qi])
        f = f * both_dispersed(C, zdisp[qi], pdisp[pj]).astype(f.dtype)
        return jnp.where(ok[:, None], f * pbeta[pj], 0.0)

    total, overflow, need = hashgrid.query_reduce(ph.grid, zp.x, zp.y, zp.z,
                                                  _photon_slots(ph, kernel),
                                                  _search_radius(radius),
                                                  max_candidates=cfg.tuning.merge_capacity,
                                                  return_need=True, valid=has)
    rep = Merged(overflow | ph.overflow, need, ph.count, ph.overflow, ~ph.grid.precise)
    est = zbeta * total / (kernel_size(zmed, radius) * N)[:, None]
    est = jnp.where(has[:, None], est, 0.0)
    # ---- emission along the delta prefix and at the gather vertex (weight 1) ----
    jj = jnp.arange(1, D + 1, dtype=jnp.int32)[:, None]
    prefix = jj <= jnp.where(has, j, D)[None]
    Le = jnp.sum(jnp.where((prefix & cverts.alive)[..., None], cam.beta[1:] * cverts.Le, 0.0),
                 axis=0)
    return est + Le, rep


# ---------------------------------------------------------------- bpm / vcm: merging with MIS
def vertex_merging(scene: Scene, cfg: RenderConfig, cam: PathEnds, lig: PathEnds, e, radius,
                   parts, by_photon: bool = False):
    """Merging at every non-delta camera vertex z_j (j = 1..D-1) with every photon y_i
    (i >= 1) within `radius`, like with like, weighted by MIS over all connection and
    merging techniques of the algorithm (the weights of `_mis.mis_weight(merge=True)`,
    evaluated at the join by the form `_mis.mis_form(cfg)`):
        L += w_VM beta_z f_z(wo_z, wo_y) beta_y / (kernel N),   i + j <= D.
    `parts`: the subpaths' (light, camera) per-subpath MIS state (`_mis.AbstractMIS.subpaths`):
    each candidate gathers O(1) entries of it.
    Returns ([D-1, N, C]: per gather vertex z_j and camera lane, the `Merged` report);
    `by_photon` (static, for per-technique images): [D-1, N, I, C], split by the
    photon's index i = 1..I as well (the gather's sums D-1 times as wide)."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    log_n = log_n_light_tracing(cfg, N, dt)
    # ---- photons y_1..y_{D-1}, gather points z_1..z_{D-1}, flattened (index = row * N + lane)
    li = np.arange(1, lig.A.shape[0])
    ci = np.arange(1, D)
    flat = lambda a, idx: a[idx].reshape((-1,) + a.shape[2:])  # noqa: E731
    pvalid = flat(lig.alive, li) & ~flat(lig.delta, li)
    py = Vec3(*(flat(c, li) for c in lig.p))
    ph = photon_grid(cfg, py, pvalid, radius, dt)
    zq = Vec3(*(flat(c, ci) for c in cam.p))
    zvalid = flat(cam.alive, ci) & ~flat(cam.delta, ci)  # dead / delta: no look-up

    cam_at, lig_at = subpath.vertex_table(cam), subpath.vertex_table(lig)

    def kernel(qi, pj, d2):
        jq = (qi // N + 1).astype(jnp.int32)
        lc = qi % N
        ip = (pj // N + 1).astype(jnp.int32)
        ll = pj % N
        z, zp = cam_at(jq, lc), cam_at(jq - 1, lc)
        y, yp = lig_at(ip, ll), lig_at(ip - 1, ll)
        same = (z.medium == y.medium) & (z.medium | (vec.dot(z.n, y.n) > 0))
        ok = (same & (ip + jq <= D) & z.alive & ~z.delta & y.alive & ~y.delta
              & _within(z.medium, d2, radius))
        fz = jax.vmap(lambda k_, m_, a, b, n_: subpath.eval_f(scene, k_, m_, a, b, n_))(
            z.kind, z.mat, z.wo, y.wo, z.n)
        cz = jnp.where(z.medium, 1.0, jnp.abs(vec.dot(z.n, y.wo)))
        fz = fz / jnp.maximum(cz, 1e-8)[:, None] * _one_scattering_event(scene, z.medium)
        fz = fz * both_dispersed(scene.channels, z.disp, y.disp).astype(fz.dtype)
        # ---- the pdfs that change at the merge (x_s = z, photon y_s = y) ----
        rev = jax.vmap(lambda *args: reverse_pdf(scene, *args))
        # z_{j-1} through z, coming from y_{i-1}; y_{i-1} through z, coming from z_{j-1}
        A_s1, _ = rev(z.kind, z.mat, z.n, z.p, y.wo, z.wo, zp.p, zp.medium, zp.n, z.seg_water)
        b1, pb1 = rev(z.kind, z.mat, z.n, z.p, z.wo, y.wo, yp.p, yp.medium, yp.n, y.seg_water)
        B_s1 = jnp.where((ip == 1) & e.infinite[ll], pb1, b1)
        B_s2 = lig.B[jnp.maximum(ip - 2, 0), ll]
        sg = jax.lax.stop_gradient
        w = mis_form(cfg).join_weight(cfg, ip, jq + 1, parts[0], parts[1], sg(y.A), sg(A_s1),
                                      sg(B_s1), sg(B_s2), e.delta[ll], e.infinite[ll],
                                      sg(log_n), merge=True, lanes=((ll,), (lc,)))
        val = jnp.where(ok[:, None], (fz * y.beta) * w[:, None], 0.0)
        if by_photon:  # [B, D-1, C]: the value in the row of its photon y_i
            rows = jnp.asarray(li, jnp.int32)
            val = jnp.where((ip[:, None] == rows[None, :])[:, :, None], val[:, None, :], 0.0)
        return val

    total, overflow, need = hashgrid.query_reduce(ph.grid, zq.x, zq.y, zq.z,
                                                  _photon_slots(ph, kernel),
                                                  _search_radius(radius),
                                                  max_candidates=cfg.tuning.merge_capacity,
                                                  return_need=True, valid=zvalid)
    rep = Merged(overflow | ph.overflow, need, ph.count, ph.overflow, ~ph.grid.precise)
    zmed = flat(cam.medium, ci)
    if by_photon:  # the same arithmetic per photon row
        est = (flat(cam.beta, ci)[:, None, :] * total
               / (kernel_size(zmed, radius) * N)[:, None, None])
        est = jnp.where(zvalid[:, None, None], est, 0.0)
        return est.reshape((len(ci), N) + total.shape[1:]), rep
    est = flat(cam.beta, ci) * total / (kernel_size(zmed, radius) * N)[:, None]
    est = jnp.where(zvalid[:, None], est, 0.0).reshape(len(ci), N, -1)
    return est, rep

