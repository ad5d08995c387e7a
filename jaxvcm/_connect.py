"""Vertex connection: every (s, t) technique of bidirectional path tracing, weighted by
explicit-sum MIS (`_mis.py`).

Techniques (s light vertices, t camera vertices, path x_0 .. x_k with k = s + t - 1):
    s = 0          the camera subpath hits an emitter / escapes to the sky,
    s = 1          next-event estimation (a fresh light sample per camera vertex),
    t = 1          light tracing: light vertex -> pinhole, splatted into the film,
    s, t >= 2      camera vertex z_{t-1} connected to light vertex y_{s-1} of the light
                   subpath with the same index (one light subpath per pixel sample).
Each technique's weight is computed from the full path's light- and camera-side pdfs:
stored subpath pdfs, plus the four that change at the connection (pbrt's `MISWeight`):
    A(z_{t-1}), A(z_{t-2})  light-side pdfs of the two camera vertices nearest the join,
    B(y_{s-1}), B(y_{s-2})  camera-side pdfs of the two light vertices nearest the join.
(s, t) loops are static Python loops; every technique is vectorised over the N paths.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _geometry as G
from . import _lights as Lt
from . import _media as Md
from . import _mis
from . import _subpath as SP
from . import _vec as V
from ._config import RenderConfig
from ._scene import LIGHT_SUN, Scene
from ._vec import Vec3


class PathEnds(NamedTuple):
    """Per-vertex arrays of one subpath including its start vertex (index 0): [D+1, N]."""

    p: Vec3
    n: Vec3
    wo: Vec3
    beta: Array  # [D+1, N, C]
    A: Array  # light-side pdf (RR-free)
    B: Array  # camera-side pdf (RR-free)
    q: Array
    delta: Array
    medium: Array
    kind: Array
    mat: Array
    seg_water: Array
    alive: Array


def _stack0(v0, rest):
    return jnp.concatenate([v0[None], rest], axis=0)


def camera_ends(scene: Scene, cam_o: Vec3, verts: SP.Vertex, n_paths: int) -> PathEnds:
    dt = cam_o.x.dtype
    N = n_paths
    one = jnp.ones((N,), dt)
    f = jnp.zeros((N,), bool)
    cf = V.from_array(jnp.broadcast_to(scene.camera.forward, (N, 3)))
    C = scene.channels
    st = lambda a, b: _stack0(a, b)  # noqa: E731
    return PathEnds(
        Vec3(*(st(a, b) for a, b in zip(cam_o, verts.p))),
        Vec3(*(st(a, b) for a, b in zip(cf, verts.n))),
        Vec3(*(st(a, b) for a, b in zip(cf, verts.wo))),
        st(jnp.ones((N, C), dt), verts.beta),
        st(one, verts.pdf_rev), st(one, verts.pdf_fwd), st(one, verts.q),
        st(f, verts.delta), st(f, verts.kind == SP.KIND_MEDIUM), st(jnp.full((N,), -1, jnp.int32), verts.kind),
        st(jnp.zeros((N,), jnp.int32), verts.mat), st(f, verts.seg_water), st(~f, verts.alive))


def light_ends(scene: Scene, e: Lt.Emission, rev0, verts: SP.Vertex, n_paths: int) -> PathEnds:
    dt = e.pdf_pos.dtype
    N = n_paths
    f = jnp.zeros((N,), bool)
    C = scene.channels
    st = _stack0
    return PathEnds(
        Vec3(*(st(a, b) for a, b in zip(e.p, verts.p))),
        Vec3(*(st(a, b) for a, b in zip(e.n, verts.n))),
        Vec3(*(st(a, b) for a, b in zip(-e.d, verts.wo))),
        st(e.beta0, verts.beta),
        st(e.pdf_pos, verts.pdf_fwd), st(rev0, verts.pdf_rev), st(jnp.ones((N,), dt), verts.q),
        st(f, verts.delta), st(f, verts.kind == SP.KIND_MEDIUM),
        st(jnp.full((N,), -1, jnp.int32), verts.kind), st(jnp.zeros((N,), jnp.int32), verts.mat),
        st(f, verts.seg_water), st(jnp.ones((N,), bool), verts.alive))


def _at(ends: PathEnds, i: int):
    return jax.tree.map(lambda a: a[i], ends)


def assemble_weight(cfg: RenderConfig, s: int, t: int, lig: PathEnds | None, cam: PathEnds,
                    over: dict, delta_light, infinite_light, log_n_lt):
    """MIS weight [N] of technique (s, t): gather the full path's pdfs from the two subpaths
    (static indices), apply the connection overrides {('A'|'B', i): [N]}, the Russian
    roulette of each direction, and call `_mis.mis_weight` per path."""
    k = s + t - 1
    Lmax = cfg.max_depth + 1
    A, B, q, dl = [], [], [], []
    N = cam.A.shape[1]
    dt = cam.A.dtype
    for i in range(k + 1):
        if i < s and lig is None:  # a fresh light sample (s = 1): pdfs come as overrides
            A.append(jnp.ones((N,), dt))
            B.append(jnp.ones((N,), dt))
            q.append(jnp.ones((N,), dt))
            dl.append(jnp.zeros((N,), bool))
            continue
        src, j = (lig, i) if i < s else (cam, k - i)
        A.append(src.A[j])
        B.append(src.B[j])
        q.append(src.q[j])
        dl.append(src.delta[j])
    for (which, i), v in over.items():
        (A if which == "A" else B)[i] = v
    a, b = [], []
    for i in range(k + 1):
        ri = SP.rr(i - 1, q[i - 1], cfg) if i >= 1 else 1.0
        rc = SP.rr(k - i - 1, q[i + 1], cfg) if i < k else 1.0
        a.append(A[i] * ri)
        b.append(B[i] * rc)
    pad = Lmax - (k + 1)
    a = jnp.stack(a + [jnp.ones((N,), dt)] * pad, axis=-1)
    b = jnp.stack(b + [jnp.ones((N,), dt)] * pad, axis=-1)
    dl = jnp.stack(dl + [jnp.zeros((N,), bool)] * pad, axis=-1)
    beta = 2.0 if cfg.mis == "power" else 1.0
    fn = lambda a_, b_, d_, dlt, inf: _mis.mis_weight(  # noqa: E731
        jax.lax.stop_gradient(a_), jax.lax.stop_gradient(b_), d_, jnp.asarray(k), jnp.asarray(s),
        dlt, inf, log_n_lt, cfg.algorithm, beta)
    w = jax.vmap(fn)(a, b, dl, jnp.broadcast_to(delta_light, (N,)),
                     jnp.broadcast_to(infinite_light, (N,)))
    return jax.lax.stop_gradient(w)


def _pdf_to(scene, pdf_w, tgt: PathEnds, j: int, src_p: Vec3, seg_water, infinite_src=False):
    """Solid-angle pdf at a source point -> area/volume pdf of vertex j of `tgt`."""
    v = tgt.p
    pj = Vec3(v.x[j], v.y[j], v.z[j])
    dv = pj - src_p
    d = V.length(dv)
    w = dv / jnp.maximum(d, 1e-30)
    nj = Vec3(tgt.n.x[j], tgt.n.y[j], tgt.n.z[j])
    return SP.to_area(pdf_w, tgt.medium[j], nj, w, d, seg_water, scene.water, infinite_src)


def _vec(ends: PathEnds, field: str, j: int) -> Vec3:
    v = getattr(ends, field)
    return Vec3(v.x[j], v.y[j], v.z[j])


def _visible(scene: Scene, cfg: RenderConfig, pa: Vec3, na: Vec3, ma, pb: Vec3, nb: Vec3, mb):
    """Mutual visibility of two vertices (offset on the correct sides), the unit direction a->b,
    the distance, and whether the segment runs through the water."""
    dv = pb - pa
    d = V.length(dv)
    w = dv / jnp.maximum(d, 1e-30)
    oa = SP.spawn(pa, na, ma, w)
    ob = SP.spawn(pb, nb, mb, -w)
    dd = ob - oa
    ddl = V.length(dd)
    wd = dd / jnp.maximum(ddl, 1e-30)
    vis = jax.vmap(lambda o, w_, t: G.unoccluded(scene, o, w_, t, cfg.march_steps))(
        oa, wd, ddl * (1.0 - 1e-5))
    if scene.water.enabled:
        # a medium vertex lies inside the water body, so membership of the spawn point
        # decides for every kind of end (the camera included)
        water_seg = jax.vmap(lambda o: G.inside_water(scene.water, o))(oa)
    else:
        water_seg = jnp.zeros_like(vis)
    return vis & (d > 1e-7), w, d, water_seg


def _tr(scene, water_seg, d):
    if not scene.water.enabled:
        return 1.0
    return jnp.where(water_seg[:, None], Md.transmittance(scene.water, d[:, None]), 1.0)


# ---------------------------------------------------------------- s = 0
def emitter_hits(scene: Scene, cfg: RenderConfig, cam: PathEnds, verts: SP.Vertex, out: dict):
    N = cam.A.shape[1]
    D = cfg.max_depth
    for j in range(1, D + 1):  # z_j on an emitter (or at infinity), t = j + 1, k = j
        t = j + 1
        Le = verts.Le[j - 1]
        esc = verts.escaped[j - 1]
        light = verts.light[j - 1]
        # which light: the hit surface's, or the sky for escaped rays
        sky_id = jnp.asarray(_first_sky(scene), jnp.int32)
        lid = jnp.where(esc, sky_id, jnp.maximum(light, 0))
        zj = _vec(cam, "p", j)
        A0 = jax.vmap(lambda l, w: Lt.light_point_pdf(scene, l, w))(lid, zj)
        over = {("A", 0): A0}
        if j >= 2:
            nj = _vec(cam, "n", j)
            wo = _vec(cam, "wo", j)
            pe = jax.vmap(lambda l, n_, w: Lt.emission_pdf_dir(scene, l, n_, w))(lid, nj, wo)
            a1 = _pdf_to(scene, pe, cam, j - 1, zj, cam.seg_water[j])
            # from the sky: perpendicular-area pdf times |cos| at z_{j-1} (no distance)
            nprev = _vec(cam, "n", j - 1)
            cprev = jnp.where(cam.medium[j - 1], 1.0, jnp.abs(V.dot(nprev, zj)))
            over[("A", 1)] = jnp.where(esc, pe * cprev, a1)
        w = assemble_weight(cfg, 0, t, None, cam, over, jnp.zeros((), bool), esc,
                            jnp.log(jnp.asarray(N, cam.A.dtype)))
        contrib = cam.beta[j] * Le * w[:, None]
        ok = verts.alive[j - 1] & jnp.any(Le > 0, axis=-1)
        out[(0, t)] = jnp.where(ok[:, None], contrib, 0.0)


def _first_sky(scene: Scene) -> int:
    from ._scene import LIGHT_SKY

    for k, kind in enumerate(scene.lights.kind):
        if kind == LIGHT_SKY:
            return k
    return 0


# ---------------------------------------------------------------- s = 1
def next_event(scene: Scene, cfg: RenderConfig, cam: PathEnds, u_nee, out: dict):
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    log_n = jnp.log(jnp.asarray(N, dt))
    for j in range(1, D):  # z_j, t = j + 1, k = j + 1
        t = j + 1
        zj, nj, wo = _vec(cam, "p", j), _vec(cam, "n", j), _vec(cam, "wo", j)
        med, kind, mat = cam.medium[j], cam.kind[j], cam.mat[j]
        ls = jax.vmap(lambda p_, u: Lt.sample_light(scene, p_, u[0], u[1], u[2]))(zj, u_nee[j - 1])
        is_delta_l = jnp.asarray([k == LIGHT_SUN for k in scene.lights.kind])[ls.light]
        inf = ~jnp.isfinite(ls.dist)
        y = zj + ls.wi * jnp.where(inf, 0.0, ls.dist)
        f = jax.vmap(lambda k_, m_, a, b, n_: SP.eval_f(scene, k_, m_, a, b, n_))(kind, mat, wo, ls.wi, nj)
        # visibility: to a finite light point, or along wi to infinity
        oz = SP.spawn(zj, nj, med, ls.wi)
        tmax = jnp.where(inf, jnp.inf, V.length(y - oz) * (1.0 - 1e-4))
        vis = jax.vmap(lambda o, w_, tm: G.unoccluded(scene, o, w_, tm, cfg.march_steps))(oz, ls.wi, tmax)
        if scene.water.enabled:
            wseg = jax.vmap(lambda o: G.inside_water(scene.water, o))(oz)
        else:
            wseg = jnp.zeros((N,), bool)
        Tr = _tr(scene, wseg, jnp.where(inf, jnp.inf, ls.dist))
        contrib = cam.beta[j] * f * ls.Le * Tr / ls.pdf_w[:, None]
        # ---- MIS: pdfs at the join ----
        A0 = jax.vmap(lambda l, w: Lt.light_point_pdf(scene, l, w))(ls.light, ls.wi)
        pe = jax.vmap(lambda l, n_, w: Lt.emission_pdf_dir(scene, l, n_, w))(ls.light, ls.n, -ls.wi)
        cos_z = jnp.where(med, 1.0, jnp.abs(V.dot(nj, ls.wi)))
        g = jnp.where(inf, cos_z, cos_z / jnp.maximum(ls.dist**2, 1e-30))
        A1 = pe * g * SP.dist_pdf(scene.water, wseg, med, ls.dist)
        over = {("A", 0): A0, ("A", 1): A1}
        if j >= 2:
            pr = jax.vmap(lambda k_, m_, a, b, n_: SP.bsdf_pdf(scene, k_, m_, None, a, b, n_))(
                kind, mat, ls.wi, wo, nj)
            over[("A", 2)] = _pdf_to(scene, pr, cam, j - 1, zj, cam.seg_water[j])
        pb = jax.vmap(lambda k_, m_, a, b, n_: SP.bsdf_pdf(scene, k_, m_, None, a, b, n_))(
            kind, mat, wo, ls.wi, nj)
        cos_y = jnp.abs(V.dot(ls.n, ls.wi))
        B0 = jnp.where(inf, pb, pb * cos_y / jnp.maximum(ls.dist**2, 1e-30)
                       * SP.dist_pdf(scene.water, wseg, False, ls.dist))
        over[("B", 0)] = B0
        w = assemble_weight(cfg, 1, t, None, cam, over, is_delta_l, inf, log_n)
        ok = cam.alive[j] & ~cam.delta[j] & ls.valid & vis
        out[(1, t)] = jnp.where(ok[:, None], contrib * w[:, None], 0.0)


# ---------------------------------------------------------------- t = 1
def camera_importance(cam_scene, w: Vec3):
    """(pixel index, W_e-type factor 1 / (A_pix cos^3), valid) for a unit direction w from the
    camera; the film is the image plane at distance 1 with pixels of area A_pix."""
    cam = cam_scene.camera
    W, H = cam.width, cam.height
    f = V.from_array(cam.forward)
    r = V.from_array(cam.right)
    u = V.from_array(cam.up)
    cos = V.dot(w, f)
    safe = jnp.where(cos > 0, cos, 1.0)
    sx = V.dot(w, r) / safe
    sy = V.dot(w, u) / safe
    aspect = W / H
    px = (sx / (aspect * cam.tan_half_fov) + 1.0) * 0.5 * W
    py = (1.0 - sy / cam.tan_half_fov) * 0.5 * H
    inside = (cos > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H)
    ix = jnp.clip(px.astype(jnp.int32), 0, W - 1)
    iy = jnp.clip(py.astype(jnp.int32), 0, H - 1)
    a_pix = (2.0 * cam.tan_half_fov * aspect / W) * (2.0 * cam.tan_half_fov / H)
    imp = 1.0 / (a_pix * safe * safe * safe)
    return iy * W + ix, jnp.where(inside, imp, 0.0), inside


def light_tracing(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: Lt.Emission,
                  cam_o: Vec3, out: dict):
    N = lig.A.shape[1]
    D = cfg.max_depth
    dt = lig.A.dtype
    log_n = jnp.log(jnp.asarray(N, dt))
    is_delta_l = e.delta
    for i in range(0, D):  # y_i -> camera: s = i + 1, t = 1, k = s
        s = i + 1
        yi, ni = _vec(lig, "p", i), _vec(lig, "n", i)
        med = lig.medium[i]
        vis, w, d, wseg = _visible(scene, cfg, cam_o, ni, jnp.ones((N,), bool), yi, ni, med)
        pix, imp, inside = jax.vmap(lambda w_: camera_importance(scene, w_))(w)
        Tr = _tr(scene, wseg, d)
        to_cam = -w
        if i == 0:
            Le = jax.vmap(lambda l, n_, w_: Lt.emitted_surface(scene, l, w_, n_, jnp.ones((), dt))[0])(
                e.light, ni, to_cam)
            fterm = Le * jnp.abs(V.dot(ni, to_cam))[:, None]
            ok = ~e.infinite
        else:
            fterm = jax.vmap(lambda k_, m_, a, b, n_: SP.eval_f(scene, k_, m_, a, b, n_))(
                lig.kind[i], lig.mat[i], _vec(lig, "wo", i), to_cam, ni)
            ok = lig.alive[i] & ~lig.delta[i]
        contrib = lig.beta[i] * fterm * Tr * (imp / jnp.maximum(d * d, 1e-30))[:, None] / N
        # ---- MIS ----
        pcam = imp * jnp.where(med, 1.0, jnp.abs(V.dot(ni, w))) / jnp.maximum(d * d, 1e-30)
        over = {("B", s - 1): pcam * SP.dist_pdf(scene.water, wseg, med, d)}
        if i >= 1:
            pr = jax.vmap(lambda k_, m_, a, b, n_: SP.bsdf_pdf(scene, k_, m_, None, a, b, n_))(
                lig.kind[i], lig.mat[i], to_cam, _vec(lig, "wo", i), ni)
            if i - 1 == 0:
                b = _pdf_to(scene, pr, lig, 0, yi, lig.seg_water[i])
                b = jnp.where(e.infinite, pr, b)
            else:
                b = _pdf_to(scene, pr, lig, i - 1, yi, lig.seg_water[i])
            over[("B", s - 2)] = b
        wgt = assemble_weight(cfg, s, 1, lig, _camera_only(lig, cam_o, N), over, is_delta_l,
                              e.infinite, log_n)
        good = ok & vis & inside
        val = jnp.where(good[:, None], contrib * wgt[:, None], 0.0)
        out[(s, 1)] = (pix, val)


def _camera_only(lig: PathEnds, cam_o: Vec3, N: int) -> PathEnds:
    """PathEnds holding just the camera vertex z_0 (for t = 1 assemblies)."""
    dt = lig.A.dtype
    one = jnp.ones((1, N), dt)
    f = jnp.zeros((1, N), bool)
    z = Vec3(cam_o.x[None], cam_o.y[None], cam_o.z[None])
    return PathEnds(z, z, z, jnp.ones((1, N, lig.beta.shape[-1]), dt), one, one, one, f, f,
                    jnp.full((1, N), -1, jnp.int32), jnp.zeros((1, N), jnp.int32), f,
                    jnp.ones((1, N), bool))


# ---------------------------------------------------------------- s, t >= 2
def connections(scene: Scene, cfg: RenderConfig, lig: PathEnds, cam: PathEnds,
                e: Lt.Emission, out: dict):
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    log_n = jnp.log(jnp.asarray(N, dt))
    for s in range(2, D + 1):
        for t in range(2, D + 2 - s):  # k = s + t - 1 <= D
            yi, ny, my = _vec(lig, "p", s - 1), _vec(lig, "n", s - 1), lig.medium[s - 1]
            zj, nz, mz = _vec(cam, "p", t - 1), _vec(cam, "n", t - 1), cam.medium[t - 1]
            wo_y, wo_z = _vec(lig, "wo", s - 1), _vec(cam, "wo", t - 1)
            vis, w, d, wseg = _visible(scene, cfg, zj, nz, mz, yi, ny, my)  # w: z -> y
            fy = jax.vmap(lambda k_, m_, a, b, n_: SP.eval_f(scene, k_, m_, a, b, n_))(
                lig.kind[s - 1], lig.mat[s - 1], wo_y, -w, ny)
            fz = jax.vmap(lambda k_, m_, a, b, n_: SP.eval_f(scene, k_, m_, a, b, n_))(
                cam.kind[t - 1], cam.mat[t - 1], wo_z, w, nz)
            Tr = _tr(scene, wseg, d)
            contrib = lig.beta[s - 1] * fy * fz * cam.beta[t - 1] * Tr / jnp.maximum(d * d, 1e-30)[:, None]
            bp = lambda k_, m_, a, b, n_: SP.bsdf_pdf(scene, k_, m_, None, a, b, n_)  # noqa: E731
            # A(z_{t-1}) from y_{s-1}
            p1 = jax.vmap(bp)(lig.kind[s - 1], lig.mat[s - 1], wo_y, -w, ny)
            cz = jnp.where(mz, 1.0, jnp.abs(V.dot(nz, w)))
            A_s = p1 * cz / jnp.maximum(d * d, 1e-30) * SP.dist_pdf(scene.water, wseg, mz, d)
            # B(y_{s-1}) from z_{t-1}
            p2 = jax.vmap(bp)(cam.kind[t - 1], cam.mat[t - 1], wo_z, w, nz)
            cy = jnp.where(my, 1.0, jnp.abs(V.dot(ny, w)))
            B_s1 = p2 * cy / jnp.maximum(d * d, 1e-30) * SP.dist_pdf(scene.water, wseg, my, d)
            over = {("A", s): A_s, ("B", s - 1): B_s1}
            # A(z_{t-2}) through z_{t-1} coming from y
            if t - 2 >= 1:
                p3 = jax.vmap(bp)(cam.kind[t - 1], cam.mat[t - 1], w, wo_z, nz)
                over[("A", s + 1)] = _pdf_to(scene, p3, cam, t - 2, zj, cam.seg_water[t - 1])
            # B(y_{s-2}) through y_{s-1} coming from z
            p4 = jax.vmap(bp)(lig.kind[s - 1], lig.mat[s - 1], -w, wo_y, ny)
            b = _pdf_to(scene, p4, lig, s - 2, yi, lig.seg_water[s - 1])
            if s - 2 == 0:
                b = jnp.where(e.infinite, p4, b)
            over[("B", s - 2)] = b
            wgt = assemble_weight(cfg, s, t, lig, cam, over, e.delta, e.infinite, log_n)
            ok = (lig.alive[s - 1] & ~lig.delta[s - 1] & cam.alive[t - 1] & ~cam.delta[t - 1]
                  & vis)
            out[(s, t)] = jnp.where(ok[:, None], contrib * wgt[:, None], 0.0)
