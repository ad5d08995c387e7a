"""Vertex connection: every (s, t) technique of bidirectional path tracing, weighted by
explicit-sum MIS (`_mis.py`).

Techniques (s light vertices, t camera vertices, path x_0 .. x_k with k = s + t - 1):
    s = 0          the camera subpath hits an emitter / escapes to the sky,
    s = 1          next-event estimation (a fresh light sample per camera vertex),
    t = 1          light tracing: light vertex -> pinhole, splatted into the film,
    s, t >= 2      camera vertex z_{t-1} joined to light vertex y_{s-1} of the light
                   subpath with the same index (one light subpath per pixel sample).
Each technique's weight is computed from the full path's light- and camera-side pdfs:
the stored subpath pdfs plus the four that change at the join (pbrt's `MISWeight`):
    A(z_{t-1}), A(z_{t-2})  light-side pdfs of the two camera vertices nearest the join,
    B(y_{s-1}), B(y_{s-2})  camera-side pdfs of the two light vertices nearest the join.
Each family is vectorised over its techniques J and the N paths: arrays are [J, N]; the
full-path assembly gathers with traced (s, t), so one compiled kernel serves every
technique of a family whatever the maximum depth.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _geometry as G
from . import _lights as Lt
from . import _media as Md
from . import _mis
from . import _mis_recursive
from . import _subpath as SP
from . import _vec as V
from ._config import RenderConfig
from ._scene import LIGHT_SKY, LIGHT_SUN, Scene
from ._vec import Vec3


def vv(f):
    """vmap over the two leading axes [J, N] of every argument."""
    return jax.vmap(jax.vmap(f))


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


def _pdfs(e: PathEnds) -> Pdfs:
    return Pdfs(e.A, e.B, e.q, e.delta, e.medium)


def _stack0(v0, rest):
    return jnp.concatenate([v0[None], rest], axis=0)


def _ends(p0: Vec3, n0: Vec3, wo0: Vec3, beta0, A0, B0, verts: SP.Vertex, rest_A, rest_B) -> PathEnds:
    N = A0.shape[0]
    f = jnp.zeros((N,), bool)
    st = _stack0
    return PathEnds(
        Vec3(*(st(a, b) for a, b in zip(p0, verts.p))),
        Vec3(*(st(a, b) for a, b in zip(n0, verts.n))),
        Vec3(*(st(a, b) for a, b in zip(wo0, verts.wo))),
        st(beta0, verts.beta), st(A0, rest_A), st(B0, rest_B),
        st(jnp.ones((N,), A0.dtype), verts.q), st(f, verts.delta),
        st(f, verts.kind == SP.KIND_MEDIUM), st(jnp.full((N,), -1, jnp.int32), verts.kind),
        st(jnp.zeros((N,), jnp.int32), verts.mat), st(f, verts.seg_water),
        st(jnp.ones((N,), bool), verts.alive), st(f, verts.dispersed))


def camera_ends(scene: Scene, cam_o: Vec3, verts: SP.Vertex, n_paths: int) -> PathEnds:
    """z_0 (the pinhole: B = 1, never a delta vertex) followed by the camera records."""
    dt = cam_o.x.dtype
    N = n_paths
    cf = V.from_array(jnp.broadcast_to(scene.camera.forward, (N, 3)))
    one = jnp.ones((N,), dt)
    return _ends(cam_o, cf, cf, jnp.ones((N, scene.channels), dt), one, one, verts,
                 verts.pdf_rev, verts.pdf_fwd)


def light_ends(scene: Scene, e: Lt.Emission, rev0, verts: SP.Vertex, n_paths: int) -> PathEnds:
    """y_0 (on the light, or at infinity) followed by the light records."""
    return _ends(e.p, e.n, -e.d, e.beta0, e.pdf_pos, rev0, verts, verts.pdf_fwd, verts.pdf_rev)


def _at(ends: PathEnds, idx) -> PathEnds:
    """Rows idx ([J], static) of every field: [J, N, ...]."""
    idx = np.asarray(idx)
    return jax.tree.map(lambda a: a[idx], ends)


# ---------------------------------------------------------------- MIS assembly
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
    a = A * jnp.where(i >= 1, SP.rr(i - 1, q_prev, cfg), 1.0)
    b = B * jnp.where(i < k, SP.rr(k - i - 1, q_next, cfg), 1.0)
    return a, b, delta & (i <= k), medium


def log_n_light_tracing(cfg: RenderConfig, n_paths, dtype):
    """log of light tracing's sample count relative to the camera techniques, per pixel:
    each of the N = pixels * spp light paths splats once (n = N per pixel, Veach 1997
    10.3.4) while a pixel has spp camera paths, so n_LT / n_camera = N / spp = pixels."""
    return jnp.log(jnp.asarray(n_paths // cfg.spp, dtype))


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


# ---------------------------------------------------------------- geometry helpers
def _conv(target_medium, target_n: Vec3, w: Vec3, d, seg_water, scene: Scene, infinite=False):
    """Solid angle at a source -> area/volume pdf factor at the target (see SP.to_area)."""
    return SP.to_area(1.0, target_medium, target_n, w, d, seg_water, scene.water, infinite)


def _visible(scene: Scene, cfg: RenderConfig, pa: Vec3, na: Vec3, ma, pb: Vec3, nb: Vec3, mb):
    """Mutual visibility of two vertices (offset on the correct sides), the unit direction
    a -> b, the distance, and whether the segment runs through the water. [J, N]"""
    dv = pb - pa
    d = V.length(dv)
    w = dv / jnp.maximum(d, 1e-30)
    oa = SP.spawn(pa, na, ma, w)
    ob = SP.spawn(pb, nb, mb, -w)
    dd = ob - oa
    ddl = V.length(dd)
    wd = dd / jnp.maximum(ddl, 1e-30)
    vis = vv(lambda o, w_, t: G.unoccluded(scene, o, w_, t, cfg.march_steps))(
        oa, wd, ddl * (1.0 - 1e-5))
    if scene.water.enabled:
        # a medium vertex lies inside the water body, so membership of the spawn point
        # decides for every kind of end (the camera included)
        water_seg = vv(lambda o: G.inside_water(scene.water, o))(oa)
    else:
        water_seg = jnp.zeros_like(vis)
    return vis & (d > 1e-7), w, d, water_seg


def _tr(scene, water_seg, d):
    if not scene.water.enabled:
        return jnp.ones(d.shape + (1,), d.dtype)
    return jnp.where(water_seg[..., None], Md.transmittance(scene.water, d[..., None]), 1.0)


def _f(scene):
    return vv(lambda k_, m_, a, b, n_: SP.eval_f(scene, k_, m_, a, b, n_))


def _pdf(scene):
    return vv(lambda k_, m_, a, b, n_: SP.bsdf_pdf(scene, k_, m_, None, a, b, n_))


def _sky_id(scene: Scene) -> int:
    for k, kind in enumerate(scene.lights.kind):
        if kind == LIGHT_SKY:
            return k
    return 0


# ---------------------------------------------------------------- s = 0
def emitter_hits(scene: Scene, cfg: RenderConfig, cam: PathEnds, verts: SP.Vertex,
                 etas=(0.0, 0.0)):
    """z_j on an emitter or at infinity (sky), j = 1..D: technique (0, j + 1)."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    js = np.arange(1, D + 1)
    z, zp = _at(cam, js), _at(cam, js - 1)  # z_j and z_{j-1}
    Le = verts.Le  # [D, N, C] for z_1..z_D
    esc = verts.escaped
    lid = jnp.where(esc, _sky_id(scene), jnp.maximum(verts.light, 0))
    A_s = vv(lambda l, w: Lt.light_point_pdf(scene, l, w))(lid, z.p)  # z.p: sky direction if esc
    pe = vv(lambda l, n_, w: Lt.emission_pdf_dir(scene, l, n_, w))(lid, z.n, z.wo)
    dv = zp.p - z.p
    d = V.length(dv)
    a_area = pe * _conv(zp.medium, zp.n, dv / jnp.maximum(d, 1e-30), d, z.seg_water, scene)
    c_inf = jnp.where(zp.medium, 1.0, jnp.abs(V.dot(zp.n, z.p)))
    A_s1 = jnp.where(esc, pe * c_inf, a_area)
    one = jnp.ones((D, N), dt)
    w = family_weights(cfg, np.zeros(D), js + 1, _pdfs(cam), (None, 1), _pdfs(cam), (None, 1),
                       A_s, A_s1, one, one, jnp.zeros((), bool), esc,
                       log_n_light_tracing(cfg, N, dt), etas)
    ok = z.alive & jnp.any(Le > 0, axis=-1)
    contrib = jnp.where(ok[..., None], z.beta * Le * w[..., None], 0.0)
    return {(0, int(j) + 1): contrib[i] for i, j in enumerate(js)}


# ---------------------------------------------------------------- s = 1
def next_event(scene: Scene, cfg: RenderConfig, cam: PathEnds, u_nee, etas=(0.0, 0.0)):
    """NEE from z_j, j = 1..D-1: technique (1, j + 1)."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    js = np.arange(1, D)
    z, zp = _at(cam, js), _at(cam, js - 1)
    ls = vv(lambda p_, u: Lt.sample_light(scene, p_, u[0], u[1], u[2]))(z.p, u_nee)
    is_delta_l = jnp.asarray([k == LIGHT_SUN for k in scene.lights.kind])[ls.light]
    inf = ~jnp.isfinite(ls.dist)
    dist = jnp.where(inf, 0.0, ls.dist)
    y = z.p + ls.wi * dist
    f = _f(scene)(z.kind, z.mat, z.wo, ls.wi, z.n)
    oz = SP.spawn(z.p, z.n, z.medium, ls.wi)
    tmax = jnp.where(inf, jnp.inf, V.length(y - oz) * (1.0 - 1e-4))
    vis = vv(lambda o, w_, tm: G.unoccluded(scene, o, w_, tm, cfg.march_steps))(oz, ls.wi, tmax)
    if scene.water.enabled:
        wseg = vv(lambda o: G.inside_water(scene.water, o))(oz)
    else:
        wseg = jnp.zeros(inf.shape, bool)
    Tr = _tr(scene, wseg, jnp.where(inf, jnp.inf, ls.dist))
    contrib = z.beta * f * ls.Le * Tr / ls.pdf_w[..., None]
    # ---- pdfs at the join ----
    A0 = vv(lambda l, w: Lt.light_point_pdf(scene, l, w))(ls.light, ls.wi)
    pe = vv(lambda l, n_, w: Lt.emission_pdf_dir(scene, l, n_, w))(ls.light, ls.n, -ls.wi)
    cos_z = jnp.where(z.medium, 1.0, jnp.abs(V.dot(z.n, ls.wi)))
    g = jnp.where(inf, cos_z, cos_z / jnp.maximum(dist * dist, 1e-30))
    A_s = pe * g * SP.dist_pdf(scene.water, wseg, z.medium, ls.dist)  # A(z_j)
    pr = _pdf(scene)(z.kind, z.mat, ls.wi, z.wo, z.n)  # z_{j-1} from z_j, coming from y
    dv = zp.p - z.p
    d1 = V.length(dv)
    A_s1 = pr * _conv(zp.medium, zp.n, dv / jnp.maximum(d1, 1e-30), d1, z.seg_water, scene)
    pb = _pdf(scene)(z.kind, z.mat, z.wo, ls.wi, z.n)  # y from z_j
    cos_y = jnp.abs(V.dot(ls.n, ls.wi))
    B0 = jnp.where(inf, pb, pb * cos_y / jnp.maximum(dist * dist, 1e-30)
                   * SP.dist_pdf(scene.water, wseg, False, ls.dist))
    # the fresh light sample as a one-vertex light subpath
    J = len(js)
    f1 = jnp.zeros((J, N, 1), bool)
    lig = Pdfs(A0[..., None], B0[..., None], jnp.ones((J, N, 1), dt), f1, f1)
    one = jnp.ones((J, N), dt)
    w = family_weights(cfg, np.ones(J), js + 1, lig, (0, 0), _pdfs(cam), (None, 1),
                       A_s, A_s1, B0, one, is_delta_l, inf, log_n_light_tracing(cfg, N, dt), etas)
    ok = z.alive & ~z.delta & ls.valid & vis
    contrib = jnp.where(ok[..., None], contrib * w[..., None], 0.0)
    return {(1, int(j) + 1): contrib[i] for i, j in enumerate(js)}


# ---------------------------------------------------------------- t = 1
def camera_importance(scene: Scene, w: Vec3):
    """(pixel index, 1 / (A_pix cos^3), inside) for a unit direction w leaving the pinhole;
    the film is the image plane at distance 1 with pixels of area A_pix, so a camera
    subpath samples w with this solid-angle pdf, and W_e G = 1 / (A_pix cos^3 d^2)."""
    cam = scene.camera
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


def light_tracing(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: Lt.Emission, cam_o: Vec3,
                  etas=(0.0, 0.0)):
    """y_i -> pinhole, i = 0..D-1: technique (i + 1, 1), splatted: {(s, 1): (pixel, value)}."""
    N = lig.A.shape[1]
    D = cfg.max_depth
    dt = lig.A.dtype
    idx = np.arange(0, D)
    y, yp = _at(lig, idx), _at(lig, np.maximum(idx - 1, 0))
    J = len(idx)
    co = Vec3(*(jnp.broadcast_to(c, (J, N)) for c in cam_o))
    vis, w, d, wseg = _visible(scene, cfg, co, y.n, jnp.ones((J, N), bool), y.p, y.n, y.medium)
    pix, imp, inside = vv(lambda w_: camera_importance(scene, w_))(w)
    Tr = _tr(scene, wseg, d)
    to_cam = -w
    # y_0: emitted radiance towards the camera; y_i>0: the scattering factor
    Le0 = vv(lambda l, n_, w_: Lt.emitted_surface(scene, l, w_, n_, jnp.ones((), dt))[0])(
        jnp.broadcast_to(e.light, (J, N)), y.n, to_cam)
    f0 = Le0 * jnp.abs(V.dot(y.n, to_cam))[..., None]
    fi = _f(scene)(y.kind, y.mat, y.wo, to_cam, y.n)
    first = (idx == 0)[:, None]
    fterm = jnp.where(first[..., None], f0, fi)
    ok = jnp.where(first, ~e.infinite[None], y.alive & ~y.delta)
    contrib = y.beta * fterm * Tr * (imp / jnp.maximum(d * d, 1e-30))[..., None] / N
    # ---- pdfs at the join: B(y_i) by the camera, B(y_{i-1}) through y_i ----
    B_s1 = imp * _conv(y.medium, y.n, w, d, wseg, scene)
    pr = _pdf(scene)(y.kind, y.mat, to_cam, y.wo, y.n)
    dv = yp.p - y.p
    d1 = V.length(dv)
    b2 = pr * _conv(yp.medium, yp.n, dv / jnp.maximum(d1, 1e-30), d1, y.seg_water, scene)
    B_s2 = jnp.where(((idx - 1) == 0)[:, None] & e.infinite[None], pr, b2)
    one = jnp.ones((J, N), dt)
    N0 = jnp.ones((1, N), dt)
    camp = Pdfs(N0, N0, N0, jnp.zeros((1, N), bool), jnp.zeros((1, N), bool))  # z_0 alone
    wgt = family_weights(cfg, idx + 1, np.ones(J), _pdfs(lig), (None, 1), camp, (None, 1),
                         one, one, B_s1, B_s2, e.delta[None], e.infinite[None],
                         log_n_light_tracing(cfg, N, dt), etas)
    good = ok & vis & inside
    val = jnp.where(good[..., None], contrib * wgt[..., None], 0.0)
    return {(int(i) + 1, 1): (pix[j], val[j]) for j, i in enumerate(idx)}


# ---------------------------------------------------------------- s, t >= 2
def connections(scene: Scene, cfg: RenderConfig, lig: PathEnds, cam: PathEnds, e: Lt.Emission,
                etas=(0.0, 0.0)):
    """z_{t-1} joined to y_{s-1} for s, t >= 2, s + t - 1 <= D."""
    N = cam.A.shape[1]
    D = cfg.max_depth
    dt = cam.A.dtype
    pairs = [(s, t) for s in range(2, D + 1) for t in range(2, D + 2 - s)]
    if not pairs:
        return {}
    ss = np.array([p[0] for p in pairs])
    ts = np.array([p[1] for p in pairs])
    y, yp = _at(lig, ss - 1), _at(lig, ss - 2)
    z, zp = _at(cam, ts - 1), _at(cam, ts - 2)
    vis, w, d, wseg = _visible(scene, cfg, z.p, z.n, z.medium, y.p, y.n, y.medium)  # w: z -> y
    fy = _f(scene)(y.kind, y.mat, y.wo, -w, y.n)
    fz = _f(scene)(z.kind, z.mat, z.wo, w, z.n)
    Tr = _tr(scene, wseg, d)
    contrib = y.beta * fy * fz * z.beta * Tr / jnp.maximum(d * d, 1e-30)[..., None]
    contrib = contrib * both_dispersed(scene.channels, y.disp, z.disp).astype(dt)
    P = _pdf(scene)
    A_s = P(y.kind, y.mat, y.wo, -w, y.n) * _conv(z.medium, z.n, w, d, wseg, scene)
    B_s1 = P(z.kind, z.mat, z.wo, w, z.n) * _conv(y.medium, y.n, w, d, wseg, scene)
    dz = zp.p - z.p
    lz = V.length(dz)
    A_s1 = P(z.kind, z.mat, w, z.wo, z.n) * _conv(zp.medium, zp.n, dz / jnp.maximum(lz, 1e-30),
                                                  lz, z.seg_water, scene)
    dy = yp.p - y.p
    ly = V.length(dy)
    p4 = P(y.kind, y.mat, -w, y.wo, y.n)
    b = p4 * _conv(yp.medium, yp.n, dy / jnp.maximum(ly, 1e-30), ly, y.seg_water, scene)
    B_s2 = jnp.where(((ss - 2) == 0)[:, None] & e.infinite[None], p4, b)
    J = len(pairs)
    wgt = family_weights(cfg, ss, ts, _pdfs(lig), (None, 1), _pdfs(cam), (None, 1), A_s, A_s1,
                         B_s1, B_s2, e.delta[None], e.infinite[None], log_n_light_tracing(cfg, N, dt),
                         etas)
    ok = y.alive & ~y.delta & z.alive & ~z.delta & vis
    val = jnp.where(ok[..., None], contrib * wgt[..., None], 0.0)
    return {pr: val[i] for i, pr in enumerate(pairs)}
