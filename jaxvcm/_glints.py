"""Glints: the lights seen in the water surface from the pinhole, by one manifold
connection per camera path.

The paths pinhole c -> s -> y with s on the water surface (a mirror reflection; a
refraction when the camera is under the water) and y on a light are made by one technique
of the core alone: the emitter hit (s = 0, t = 3), a camera ray that reflects at the
surface and happens to land on the light. No connection joins s (a delta vertex) and no
merge has a non-delta vertex to merge at. With a small light each such sample is 0 or the
light's whole radiance: the glints in the waves are the noisiest part of a pool's image.

The glint technique (`glints`) samples points y on a light (`_lights.sample_emission`,
several per camera path, stratified over the light: `light_uniforms`) and for each finds
the points s whose direction from the pinhole falls in that path's
own pixel j: Newton (`_manifold.solve_near`) from seeds fixed per pixel (rays through the
pixel on the water's mean level): its centre's, and where that root lands in or beside the
pixel, the other points of a 3 x 3 grid over it, as two roots of one light point can share
a pixel (the pairs that merge at a fold of the glint). Call the result F_j(y): the distinct
roots of the law in the pixel that these seeds reach (the centre's and the first `EXTRA`
others, `roots`), often none.

The cull (`_may_hold`). Most (pixel, light point) pairs hold no root, and a bound says so
before any Newton step. The surface points seen in pixel j lie in the frustum of its rays
between the heights level +- sum |A|, narrowed to h(r1) +- L rho_h (L = sum |A| |k| bounds
the slope, rho_h the frustum's horizontal reach from r1, the centre ray at the mean
level). A root s needs the surface's slope grad h(s) to equal the slope the law asks for,
g*(s) = -(H_x, H_z) / H_y with H = eta_a w_a + eta_b w_b. Over the frustum, measured from
r (the centre ray at h(r1)): w_a turns by at most the pixel's angular radius alpha and w_b
by at most asin(rho / |y - r|) (rho: the frustum's 3-D reach), so |H(s) - H(r)| <= e =
eta_a alpha + eta_b asin(rho / |y - r|) and |g*(s) - g*(r)| <= e (|H_y| + |H_xz|) /
(|H_y| (|H_y| - e)); the surface's slope moves by at most K rho_h (K = sum |A| k^2 bounds
the heightfield's Hessian). Where |g*(r) - grad h(r)| exceeds their sum (and a margin for
rounding; the pixel widened by `EDGE`) no root can lie in the pixel: F_j(y) is empty
without a solve. The bound is conservative, so F_j is the same function with or without
it (tests: every root of a full search keeps its pixel); it leaves 2.6 % of the pairs to
the solves at 256 x 256 on the default pool, 18 % at 96 x 96, 40 % at 64 x 64.
The contribution of a root, per sample of pixel j (the camera's pixel importance W(w) =
`camera_importance`: 1 / (A_pix cos^3)):

    area light:   W(w) F(s) eta^2 T_r L_e(y -> s) |d w / d A_y| / p_A(y)
    point light:  W(w) F(s) T_r I |d omega_y / d A_perp(c)| / p_sel
    sun:          W(w) F(s) T_r E |d A_perp(beam) / d A_perp(c)| / p_sel

(F: Fresnel reflectance, or transmittance for a refraction; eta^2: the radiance's n^2 law,
(n_camera / n_light)^2, area lights only, as the point and sun forms are irradiances; T_r:
the water's transmittance of c -> s for a camera under the water; the Jacobians are
`_manifold.generalized_geometry`'s, through the implicit function of the root). Both
segments are shadow-tested.

MIS (power or balance heuristic, beta). In the area measure of y, per sample of pixel j:
    p_g  = p_A(y)                                   the light's pdf (selection included),
    p_eh = W(w) P_sel(s) |d w / d A_y| P_pass(c, s)  the camera ray through the surface
(P_sel: the camera path's Fresnel choice of the lobe at s; P_pass: its water's
distance-sampling factor, 1 above the water). With n light points per camera path
(`SAMPLES`, each point's value divided by n; stratified: point k lies in its own part of
the light of probability 1/n, so the mean of the n values f / p_g is still unbiased for
the integral of w_g f, whatever weights that sum to one on each path) the glint technique takes
w_g = (n p_g)^beta / ((n p_g)^beta + p_eh^beta) of the paths F_j returns, the emitter hit
w_eh = 1 - w_g of those (`emitter_share`, evaluated at every emitter hit of that shape
with the same F_j) and w_eh = 1 (its weight without glints, as no other technique makes
these paths) of every other path. So on every path w_g + w_eh = 1 whatever the solver
misses (a root outside every seed's basin): the estimator is unbiased by construction,
and only its variance depends on how often F_j finds the root (a missed root's emitter
hit is a sample of the light's whole radiance at weight 1). Point lights and the sun
cannot be hit (p_eh = 0): w_g = 1, light no other technique finds. (The roulette's
survival at s is left out of p_eh: no path this short meets the roulette in a shipped
configuration, and any positive pdfs keep the weights' sum 1.)
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import _geometry as geometry
from . import _lights as lights
from . import _manifold as manifold
from . import _media as media
from . import _subpath as subpath
from . import _vec as vec
from ._camera import camera_importance, generate_ray
from ._config import RenderConfig
from ._materials import fresnel_dielectric
from ._queue import masked_map
from ._scene import LIGHT_POINT, LIGHT_RECT, LIGHT_SPHERE, LIGHT_SUN, MAT_DIELECTRIC, Scene
from ._vec import Vec3

ITERS = 8  # Newton iterations from a pixel's seed (the root lies within a pixel's footprint)
# Newton solves per light point at most (`roots`): the pixel centre's, and where its root
# lands in or beside the pixel, those of the other points of a 3 x 3 grid over the pixel.
# Two roots of one light point can share a pixel (the pairs that merge at a fold of the
# glint) and one seed reaches only one of them. On the default pool at 64 x 64, of the
# 6,280 roots in view of 200 light points (72 sharing a pixel) the centre alone returns
# 99.39 %, with the grid 99.97 % (all 72); the grid runs for 5.7 % of the light points of
# random pixels (0.5 % at 256 x 256, where 1,498 of 1,498 roots of 48 points are found)
SEEDS = 9
# the roots beyond the centre's that F_j keeps per light point and pixel: the first
# distinct ones in seed order (the queues then hold 1 + EXTRA items per light point, not
# SEEDS). Roots per (pixel, light point) with any, default pool, 400 light points: at
# 24 x 24, 9,095 one, 1,381 two, 225 three, none more; at 64 x 64, 12,380 one, 76 two; at
# 256 x 256 (100 points), 3,122 one, 2 two. A root F_j does not return is rendered by the
# emitter hits at their full weight, as any the seeds miss (module doc)
EXTRA = 2
# light points per camera path, stratified over the light (`light_uniforms`): the
# technique's variance is that of the light points alone (the pixel's seeds are fixed),
# and their search is cheap next to their contributions, so several points per path cut
# it at little cost; their count n multiplies the technique's pdf in the MIS weights (the
# balance / power heuristic with n samples, Veach 1997 9.2)
SAMPLES = 8
STREAM = 0x67_6C_69_6E  # fold_in tag of the glint samples' key ("glin")


def applies(scene: Scene) -> bool:
    """The scene has water and a light a glint can show (area, point, sun)."""
    return scene.water.enabled and any(
        k in (LIGHT_RECT, LIGHT_SPHERE, LIGHT_POINT, LIGHT_SUN) for k in scene.lights.kind)


def law(scene: Scene, c: Vec3):
    """The law of the glints seen from the pinhole c (a traced bool: refraction iff the
    camera is under the water) and whether glints exist for it (a dispersive water's
    refraction is a hero-only path: no glints, the emitter hits keep those paths)."""
    refract = manifold.below(scene.water, c)
    if scene.materials.dispersive:
        return refract, ~refract
    return refract, jnp.ones((), bool)


def _seed(scene: Scene, pixel, su, sv):
    """(x, z, ok): the seed of a Newton solve for pixel `pixel`: the ray through the point
    (su, sv) of the pixel on the water's mean level, inside the footprint."""
    cam = scene.camera
    dt = cam.origin.dtype
    c, d = generate_ray(cam, pixel, jnp.asarray(su, dt), jnp.asarray(sv, dt))
    w = scene.water
    dy = jnp.where(jnp.abs(d.y) > 1e-12, d.y, 1e-12)
    t = (w.level - c.y) / dy
    x, z = c.x + t * d.x, c.z + t * d.z
    fp = w.footprint
    ok = (t > 0) & (x > fp[0]) & (x < fp[1]) & (z > fp[2]) & (z < fp[3])
    return jnp.clip(x, fp[0], fp[1]), jnp.clip(z, fp[2], fp[3]), ok


# the pixel widened by this fraction on every side in `_may_hold` (a root's pixel is
# assigned from its rounded direction)
EDGE = 1.0 / 64.0


def _may_hold(scene: Scene, pixel, c: Vec3, b, refract, b_dir: bool):
    """False only where no root of c -> s -> b can have its direction from c in `pixel`
    (module doc: the cull), so that `roots` solves only where a root may lie. The surface
    points seen in the pixel lie in the frustum of its rays between two heights; over it
    the slope the law asks for moves by at most dg and the surface's slope by at most
    K rho_h; a root needs them to meet. Conservative: where the frustum is unbounded (a
    ray near the horizon, the camera within the waves' heights) or the bound degenerates
    (b close to the surface, |H_y| small), True."""
    w = jax.lax.stop_gradient(scene.water)
    cam = scene.camera
    dt = c.x.dtype
    c = Vec3(*(jax.lax.stop_gradient(a) for a in c))
    b = Vec3(*(jax.lax.stop_gradient(a) for a in b))
    A, L, _ = manifold._waves(w)
    K = jnp.sum(jnp.abs(w.amp) * (w.kx * w.kx + w.kz * w.kz)) if w.n_waves else jnp.zeros((), dt)
    half = jnp.asarray(0.5, dt)
    _, d0 = generate_ray(cam, pixel, half, half)
    lo_e, hi_e = jnp.asarray(-EDGE, dt), jnp.asarray(1.0 + EDGE, dt)
    ds = [generate_ray(cam, pixel, u, v)[1] for u in (lo_e, hi_e) for v in (lo_e, hi_e)]
    # the pixel's angular radius (from the chords: arccos of a cosine near 1 loses it)
    chord = jnp.max(jnp.stack([vec.length(d - d0) for d in ds]))
    alpha = 2.0 * jnp.arcsin(jnp.minimum(0.5 * chord, 1.0))
    # the frustum is bounded where every ray crosses both heights ahead of c
    side = jnp.sign(w.level - c.y)
    sure = jnp.all(jnp.stack([d.y * side for d in ds + [d0]]) > 1e-6)
    sure = sure & (jnp.abs(c.y - w.level) > A)

    def on(d, y):  # the point of ray d at height y
        t = (y - c.y) / jnp.where(jnp.abs(d.y) > 1e-6, d.y, 1e-6)
        return c + d * t

    def reach(r, lo, hi):  # (horizontal, 3-D) distance from r to the frustum's corners
        ps = [on(d, y) for d in ds for y in (lo, hi)]
        h = jnp.stack([jnp.sqrt((p.x - r.x) ** 2 + (p.z - r.z) ** 2) for p in ps])
        f = jnp.stack([vec.length(p - r) for p in ps])
        return jnp.max(h), jnp.max(f)

    lo, hi = w.level - A, w.level + A
    r1 = on(d0, w.level)
    rh1, _ = reach(r1, lo, hi)
    h1, _, _ = geometry.water_height(w, r1.x, r1.z, unroll=geometry.SOLVER_WAVES_UNROLLED)
    # the surface's height over the frustum's horizontal reach: h(r1) +- L rho_h
    lo, hi = jnp.maximum(lo, h1 - L * rh1), jnp.minimum(hi, h1 + L * rh1)
    r = on(d0, h1)
    rh, rho = reach(r, lo, hi)
    _, gx, gz = geometry.water_height(w, r.x, r.z, unroll=geometry.SOLVER_WAVES_UNROLLED)
    E = manifold._ends(w, c, b, refract, b_dir)
    wa = vec.normalize(c - r)
    if b_dir:
        wb, delta_b = vec.normalize(-b), jnp.zeros((), dt)
        far = jnp.asarray(True)
    else:
        rb = vec.length(b - r)
        wb = (b - r) / jnp.maximum(rb, 1e-30)
        far = rho < 0.5 * rb
        delta_b = jnp.arcsin(jnp.clip(rho / jnp.maximum(rb, 1e-30), 0.0, 1.0))
    H = wa * E.eta_a + wb * E.eta_b
    e = E.eta_a * alpha + E.eta_b * delta_b  # bounds |H(s) - H(r)| over the frustum
    Hy = jnp.abs(H.y)
    Hxz = jnp.sqrt(H.x * H.x + H.z * H.z)
    steady = Hy > 2.0 * e
    sHy = jnp.where(steady, H.y, 1.0)
    gsx, gsz = -H.x / sHy, -H.z / sHy  # the slope the law asks for at r
    dg = e * (Hy + Hxz) / jnp.maximum(Hy * (Hy - e), 1e-30)
    dist = jnp.sqrt((gsx - gx) ** 2 + (gsz - gz) ** 2)
    slack = 1e-3 * (1.0 + jnp.sqrt(gsx * gsx + gsz * gsz))
    meet = dist <= K * rh + dg + slack
    return E.ok & ~(sure & far & steady & ~meet)


def _same(c: Vec3, s: Vec3, p: Vec3):
    """s and p are one surface point (float32 rounding of a root seen from c)."""
    return vec.length(s - p) <= 1e-4 * (1.0 + vec.length(s - c))


def _solve(scene: Scene, pixel, c: Vec3, b, refract, b_dir: bool, su, sv):
    """Newton from the seed at (su, sv) of the pixel: (a root in the pixel, the stopped
    point, the pixel its direction falls in, inside the image)."""
    x0, z0, seed_ok = _seed(scene, pixel, su, sv)
    r = manifold.solve_near(scene.water, c, b, x0, z0, refract=refract, b_is_direction=b_dir,
                            iters=ITERS)
    pix, _, inside = camera_importance(scene, vec.normalize(r.s - c))
    good = seed_ok & r.valid & inside
    return good & (pix == pixel), Vec3(*(jax.lax.stop_gradient(a) for a in r.s)), pix, good


def _centre(scene: Scene, pixel, c: Vec3, b, refract, b_dir: bool):
    """The pixel centre's solve: (root in the pixel, point, more: its root lies in the
    pixel or one of its 8 neighbours, so the pixel may hold a second root)."""
    ok, s, pix, good = _solve(scene, pixel, c, b, refract, b_dir, 0.5, 0.5)
    W = scene.camera.width
    near = (jnp.abs(pix // W - pixel // W) <= 1) & (jnp.abs(pix % W - pixel % W) <= 1)
    return ok, s, good & near


def _more(scene: Scene, pixel, c: Vec3, b, refract, b_dir: bool, ok0, s0: Vec3):
    """The solves from the other 8 points of a 3 x 3 grid over the pixel (its centre is
    `_centre`'s): (ok [EXTRA], points [EXTRA]): the first EXTRA roots, in seed order, that
    are neither the centre's (`ok0`, `s0`) nor an earlier seed's."""
    t = jnp.asarray([1.0 / 6.0, 0.5, 5.0 / 6.0], scene.camera.origin.dtype)
    su, sv = jnp.repeat(t, 3), jnp.tile(t, 3)
    keep = jnp.asarray([0, 1, 2, 3, 5, 6, 7, 8])  # all but the centre (index 4)
    okm, sm = jax.vmap(lambda a, q: _solve(scene, pixel, c, b, refract, b_dir, a, q)[:2])(
        su[keep], sv[keep])
    ok = jnp.concatenate([ok0[None], okm])
    s = jax.tree.map(lambda a, q: jnp.concatenate([a[None], q]), s0, sm)
    same = jax.vmap(lambda a: jax.vmap(lambda q: _same(c, a, q))(s))(s)  # [9, 9]
    earlier = jnp.tril(jnp.ones((SEEDS, SEEDS), bool), -1)
    left = (ok & ~jnp.any(same & earlier & ok[None, :], axis=1))[1:]
    oks, pts = [], []
    for _ in range(EXTRA):  # the first EXTRA new roots, in seed order
        i = jnp.argmax(left)
        oks.append(left[i])
        pts.append(jax.tree.map(lambda a: a[i], sm))
        left = left.at[i].set(False)
    return jnp.stack(oks), jax.tree.map(lambda *a: jnp.stack(a), *pts)


def roots(scene: Scene, pixel, c: Vec3, b, refract, exists, b_dir: bool = False):
    """F_pixel(b): the roots of c -> s -> b whose direction from c falls in `pixel`:
    (ok [1 + EXTRA], s [1 + EXTRA] stopped points), each distinct root marked once; none
    where the pixel cannot hold a root (`_may_hold`). Newton from the
    pixel centre's seed; where its root lies in the pixel or a neighbour (the pixel may hold
    a second root: the pairs that merge at a fold of the glint), Newton from the other
    points of a 3 x 3 grid over the pixel as well. A deterministic function of (pixel, b):
    the glint technique counts the roots it returns, the emitter hit takes its share of
    exactly those paths (`emitter_share`)."""
    may = _may_hold(scene, pixel, c, b, refract, b_dir)
    ok0, s0, more = _centre(scene, pixel, c, b, refract, b_dir)
    ok0, more = ok0 & may, more & may
    okm, sm = _more(scene, pixel, c, b, refract, b_dir, ok0, s0)
    ok = jnp.concatenate([ok0[None], okm & more])
    s = jax.tree.map(lambda a, q: jnp.concatenate([a[None], q]), s0, sm)
    return ok & exists, s


def _fresnel(scene: Scene, c: Vec3, s: Vec3, refract: bool):
    """(F [C], P_sel): the factor the interface gives the glint (R, or 1 - R) per channel,
    and the camera path's probability of choosing that lobe at s (`_materials`' hero)."""
    water = scene.water
    _, hx, hz = geometry.water_height(water, s.x, s.z, unroll=geometry.SOLVER_WAVES_UNROLLED)
    n = vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))
    cos_o = vec.dot(n, vec.normalize(c - s))
    ior = scene.materials.ior[water.mat]
    eta = jnp.where(cos_o >= 0, ior, 1.0 / ior)
    R, _ = fresnel_dielectric(cos_o, eta)
    R_h = R[0] if jnp.ndim(R) else R
    C = scene.channels
    return (jnp.where(refract, 1.0 - R, R) * jnp.ones((C,), c.x.dtype),
            jnp.where(refract, 1.0 - R_h, R_h))


def _cam_medium(scene: Scene, c: Vec3, s: Vec3, refract: bool):
    """(T_r [C], P_pass) of c -> s: the water's transmittance and the camera path's
    distance-sampling factor (a camera under the water: a refraction glint)."""
    C = scene.channels
    dt = c.x.dtype
    d = vec.length(s - c)
    return (jnp.where(refract, media.transmittance(scene.water, d), 1.0) * jnp.ones((C,), dt),
            jnp.where(refract, subpath.dist_pdf(scene.water, jnp.ones((), bool), False, d), 1.0))


def emitter_pdf(scene: Scene, c: Vec3, s: Vec3, y: Vec3, n_y: Vec3, refract: bool):
    """p_eh: the emitter-hit technique's pdf of y (area measure, per sample of the pixel)
    through the root s (module doc)."""
    G = manifold.generalized_geometry(scene.water, c, s, y, refract=refract, n_b=n_y)
    return _emitter_pdf(scene, c, s, refract, G)


def _emitter_pdf(scene: Scene, c: Vec3, s: Vec3, refract, G):
    """`emitter_pdf` from the chain's |d w / d A_y| = G."""
    imp = camera_importance(scene, vec.normalize(s - c))[1]
    _, P_sel = _fresnel(scene, c, s, refract)
    _, P_pass = _cam_medium(scene, c, s, refract)
    return jax.lax.stop_gradient(imp * P_sel * G * P_pass)


def glint_weight(cfg: RenderConfig, p_g, p_eh, samples: int = SAMPLES):
    """w_g = (n p_g)^beta / ((n p_g)^beta + p_eh^beta) with n = `samples` light points per
    path (module doc); the emitter hit's share is the same function with the pdfs
    swapped (`emitter_share`, with the same n)."""
    return _share(cfg, samples * p_g, p_eh)


def _share(cfg: RenderConfig, p_own, p_other):
    beta = 2.0 if cfg.mis == "power" else 1.0
    r = jnp.where(p_own > 0, p_other / jnp.where(p_own > 0, p_own, 1.0), jnp.inf)
    return jnp.where(p_own > 0, 1.0 / (1.0 + r ** beta), 0.0)


def _ends(scene: Scene) -> list[bool]:
    """The kinds of light end a glint has in this scene (static): a point (area and point
    lights), a direction (the sun)."""
    kinds = scene.lights.kind
    ends = []
    if any(k in (LIGHT_RECT, LIGHT_SPHERE, LIGHT_POINT) for k in kinds):
        ends.append(False)
    if LIGHT_SUN in kinds:
        ends.append(True)
    return ends


def _contribution(scene: Scene, cfg: RenderConfig, e: lights.Emission, x, z, refract,
                  b_dir: bool, samples: int = SAMPLES):
    """The weighted contribution [C] of a root the search found at (x, z) (the costly
    part: the differentiable root, both shadow rays, the chain's Jacobians, MIS)."""
    water = scene.water
    dt = scene.camera.origin.dtype
    kinds = scene.lights.kind
    c = vec.from_array(scene.camera.origin)
    b = e.d if b_dir else e.p
    # the root again, from itself (no iteration: the polish step and its implicit-function
    # derivatives, so gradients flow through it)
    s = manifold.polished(water, c, b, x, z, refract=refract, b_is_direction=b_dir)
    w = vec.normalize(s - c)
    _, imp, _ = camera_importance(scene, w)
    # ---- visibility: c -> s (nothing before the root), s -> y ----
    d1 = vec.length(s - c)
    vis = geometry.unoccluded(scene, c, w, d1 * (1.0 - 1e-4), cfg.march_steps)
    _, hx, hz = geometry.water_height(water, s.x, s.z, unroll=geometry.SOLVER_WAVES_UNROLLED)
    n_s = vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))
    w2 = -b if b_dir else vec.normalize(b - s)
    o2 = subpath.offset(s, n_s, w2)
    t2 = jnp.asarray(jnp.inf, dt) if b_dir else vec.length(b - o2) * (1.0 - 1e-4)
    vis = vis & geometry.unoccluded(scene, o2, w2, t2, cfg.march_steps)
    # ---- contribution ----
    F, _ = _fresnel(scene, c, s, refract)
    Tr, _ = _cam_medium(scene, c, s, refract)
    base = imp * F * Tr / e.pdf_pos  # 1 / (p_sel p_A); 1 / p_sel: point, sun
    if b_dir:
        G = manifold.generalized_geometry(water, c, s, b, refract=refract, b_is_direction=True)
        val = base * scene.lights.radiance[e.light] * G
        wgt = jnp.ones((), dt)
    else:
        # area lights: radiance towards s, the n^2 law, MIS against the emitter hit
        G_a = manifold.generalized_geometry(water, c, s, b, refract=refract, n_b=e.n)
        Le, _ = lights.emitted_surface(scene, e.light, vec.normalize(s - b), e.n,
                                       jnp.ones((), dt))
        scale = manifold.radiance_scale(water, c, b, refract=refract)
        area = base * Le * scale * G_a
        p_eh = _emitter_pdf(scene, c, s, refract, G_a)
        w_area = glint_weight(cfg, jax.lax.stop_gradient(e.pdf_pos), p_eh, samples)
        if any(k == LIGHT_POINT for k in kinds):
            is_point = jnp.zeros((), bool)
            for k, kind in enumerate(kinds):
                if kind == LIGHT_POINT:
                    is_point = is_point | (e.light == k)
            G_p = manifold.generalized_geometry(water, c, s, b, refract=refract)
            point = base * lights.emitted_toward(scene, e.light, w2, e.n) * G_p
            val = jnp.where(is_point, point, area)
            wgt = jnp.where(is_point, 1.0, w_area)
        else:
            val, wgt = area, w_area
    return jnp.where(vis, val * wgt, 0.0)


def strata(samples: int) -> tuple[int, int]:
    """(gx, gy): the grid of a path's light points over the light's position, gx gy =
    `samples`, gx the largest divisor not above the square root (8 points: 2 x 4)."""
    gx = max(d for d in range(1, int(samples**0.5) + 1) if samples % d == 0)
    return gx, samples // gx


def light_uniforms(key, N: int, samples: int, dt):
    """[N samples, 5] uniforms of the glints' light points (`_lights.sample_emission`'s):
    the `samples` points of a path stratified over the two that place the point on the
    light (u[1], u[2]: a jittered gx x gy grid, `strata`), so a pixel that sees part of the
    light gets nearly the same number of points in that part every pass. Point k is
    uniform in its stratum (probability 1/`samples`), so the points together are uniform
    (pdf p_A(y)) and the mean of their values f / p_A is unbiased."""
    u = jax.random.uniform(key, (N, samples, 5), dt)
    gx, gy = strata(samples)
    i = jnp.arange(samples)
    u = u.at[..., 1].set(((i % gx).astype(dt) + u[..., 1]) / gx)
    u = u.at[..., 2].set(((i // gx).astype(dt) + u[..., 2]) / gy)
    return u.reshape(N * samples, 5)


def points(scene: Scene, pixel, key, samples: int = SAMPLES):
    """The technique's light points: (e [K] `_lights.Emission`, their paths' pixels [K]),
    K = N `samples`, point k of path k // samples (`light_uniforms`)."""
    u = light_uniforms(key, pixel.shape[0], samples, scene.camera.origin.dtype)
    return (jax.vmap(lambda uu: lights.sample_emission(scene, uu))(u),
            jnp.repeat(pixel, samples))


def find(scene: Scene, pix, b, use, refract, b_dir: bool):
    """F_pixel(b) (`roots`) of the items (pixel `pix` [M], light end `b` [M]) where `use`
    holds, as work queues: the centre's solve for the items whose pixel may hold a root
    (`_may_hold`: 2.6 % of the glint technique's at 256 x 256 on the default pool), the
    other seeds' for the few whose centre root lands in or beside the pixel. Returns (ok
    [1 + EXTRA, M], s [1 + EXTRA, M] stopped points): item for item what `roots` returns."""
    c = vec.from_array(scene.camera.origin)
    zero = jnp.zeros((), scene.camera.origin.dtype)
    none = Vec3(zero, zero, zero)
    may = jax.vmap(lambda p, bb: _may_hold(scene, p, c, bb, refract, b_dir))(pix, b) & use
    ok0, s0, more = masked_map(lambda p, bb: _centre(scene, p, c, bb, refract, b_dir), may,
                               (pix, b), (False, none, False), 16)
    okm, sm = masked_map(lambda p, bb, o, q: _more(scene, p, c, bb, refract, b_dir, o, q),
                         more, (pix, b, ok0, s0), (False, none), 128)
    ok = jnp.concatenate([ok0[None], okm.T], axis=0)
    s = jax.tree.map(lambda a, q: jnp.concatenate([a[None], q.T], axis=0), s0, sm)
    return ok, s


def share_items(scene: Scene, cam, verts):
    """The camera paths whose emitter hit may take a share of the glints (`emitter_share`:
    z_2 on an area light, seen in the water surface at z_1), and z_2 on the light: (want
    [N], y [N] stopped points)."""
    kinds = scene.lights.kind
    light = verts.light[1]
    is_area = jnp.asarray([k in (LIGHT_RECT, LIGHT_SPHERE) for k in kinds])[
        jnp.maximum(light, 0)] & (light >= 0)
    want = (verts.alive[1] & jnp.any(verts.Le[1] > 0, axis=-1) & ~verts.escaped[1] & is_area
            & (cam.kind[1] == MAT_DIELECTRIC) & (cam.mat[1] == scene.water.mat))
    return want, Vec3(*(jax.lax.stop_gradient(a[2]) for a in cam.p))


class Found(NamedTuple):
    """The roots F_pixel of one pass, found once (`search`): per kind of light end
    (`_ends`), the technique's (ok [1 + EXTRA, K], s [1 + EXTRA, K]); and `share`, the
    emitter hits' (ok [1 + EXTRA, N], s [1 + EXTRA, N]) of their paths' z_2 (None: no area
    light, or not asked for)."""

    technique: tuple
    share: Any = None


def search(scene: Scene, pixel, key, cam=None, verts=None, samples: int = SAMPLES) -> Found:
    """F_pixel for the technique's light points and, given the camera records (`cam`
    `PathEnds`, `verts` records), for the emitter hits that take a share of the glints
    (`share_items`): the point-light ends of both in one set of queues, so the compiled
    pass holds one copy of the solves and both sides meet the same F by construction."""
    e, pix = points(scene, pixel, key, samples)
    K = pix.shape[0]
    c = vec.from_array(scene.camera.origin)
    refract, exists = law(scene, c)
    tech, share = [], None
    for b_dir in _ends(scene):
        use = exists & ((e.infinite & e.delta) if b_dir else ~e.infinite)
        b = e.d if b_dir else e.p
        if b_dir or cam is None:
            tech.append(find(scene, pix, b, use, refract, b_dir))
            continue
        want, y = share_items(scene, cam, verts)
        cat = lambda a, q: jnp.concatenate([a, q])  # noqa: E731
        ok, s = find(scene, cat(pix, pixel), jax.tree.map(cat, b, y), cat(use, want & exists),
                     refract, False)
        tech.append((ok[:, :K], jax.tree.map(lambda a: a[:, :K], s)))
        share = (ok[:, K:], jax.tree.map(lambda a: a[:, K:], s))
    return Found(tuple(tech), share)


def glints(scene: Scene, cfg: RenderConfig, pixel, key, samples: int = SAMPLES,
           found: Found | None = None):
    """The glint technique for every camera path (its pixel [N]): ([N, C] per path, the
    film's mean over its pixel's samples as every camera technique; the number of
    non-finite values, zeroed). Every path samples `samples` light points (`points`) and
    finds their roots in its pixel (`search`, or `found` if the pass already searched
    with the same key); only the roots in the pixel trace the shadow rays and evaluate
    the Jacobians, in a work queue (`_queue.masked_map`); the path's value is the mean over
    its points."""
    N = pixel.shape[0]
    K = N * samples
    dt = scene.camera.origin.dtype
    e, _ = points(scene, pixel, key, samples)
    if found is None:
        found = search(scene, pixel, key, samples=samples)
    refract, _ = law(scene, vec.from_array(scene.camera.origin))
    out = jnp.zeros((K, scene.channels), dt)
    bad = jnp.zeros((), jnp.int32)
    item_of = jnp.arange(K, dtype=jnp.int32)
    for b_dir, (ok, s) in zip(_ends(scene), found.technique):
        # the contributions of every root found, item (seed, k): the centre's roots (a few
        # per cent of the light points hold one), the other seeds' (far fewer), in one
        # queue of rounds of K / 16 items, added per light point
        ks = jnp.broadcast_to(item_of, (1 + EXTRA, K))

        def item(x, z, k, b_dir=b_dir):
            ek = jax.tree.map(lambda a: a[k], e)
            return _contribution(scene, cfg, ek, x, z, refract, b_dir, samples)

        val, n_bad = masked_map(item, ok, (s.x, s.z, ks), 0.0, 16 * (1 + EXTRA), summed=True)
        out, bad = out + val, bad + n_bad
    return out.reshape(N, samples, -1).mean(axis=1), bad


def emitter_share(scene: Scene, cfg: RenderConfig, z0: Vec3, z1, z2, light, escaped, j, pixel,
                  found=None):
    """The emitter hit's share w_eh of its path z0 (pinhole) -> z1 -> z2 (on `light`) at
    camera vertex z_j (module doc): 1 unless j = 2, z1 is on the water surface, the light
    is an area light and F_pixel(z2) returns z1; then p_eh^beta / (p_eh^beta + p_g^beta).
    z1, z2: one vertex each of a `PathEnds` (p, n, kind, mat read). `found`: F_pixel(z2)
    as (ok [1 + EXTRA], s [1 + EXTRA]) from the pass's `search`; None: solved here
    (`roots`)."""
    water = scene.water
    dt = z0.x.dtype
    kinds = scene.lights.kind
    is_area = jnp.asarray([kind in (LIGHT_RECT, LIGHT_SPHERE) for kind in kinds])[
        jnp.maximum(light, 0)] & (light >= 0)
    shape = ((j == 2) & ~escaped & is_area & (z1.kind == MAT_DIELECTRIC)
             & (z1.mat == water.mat))
    refract, exists = law(scene, z0)
    sg = jax.lax.stop_gradient
    y = vec.Vec3(*(sg(a) for a in z2.p))
    ok, s = roots(scene, pixel, z0, y, refract, exists) if found is None else found
    hit = jax.vmap(lambda q: _same(z0, q, Vec3(*(sg(a) for a in z1.p))))(s) & ok
    found = shape & jnp.any(hit)
    s1 = jax.tree.map(lambda a: a[jnp.argmax(hit)], s)
    p_eh = emitter_pdf(scene, z0, s1, y, z2.n, refract)
    p_g = SAMPLES * lights.light_point_pdf(scene, light, y)  # n points per path
    return jnp.where(found, _share(cfg, p_eh, p_g), jnp.ones((), dt))  # 1 - glint_weight
