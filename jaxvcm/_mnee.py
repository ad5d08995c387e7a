"""Manifold next-event estimation: light that reaches a vertex under the water through one
refraction at the surface, found by Newton and weighted inside the explicit MIS sums.

The path ... z_{j-1}, a = z_j, s, y_0: a non-delta camera vertex a under the water (floor,
wall, medium vertex), s on the water surface (a delta vertex: refraction), y_0 on a light
above the water (area or point light), or the sun (a direction: below). Without this
technique only three kinds of technique make such paths: the camera's emitter hit
through s (s = 0), a light subpath y_0 -> s -> a joined further on (connections with
s >= 3 light vertices, light tracing) and merging at a (bpm, vcm). Next-event estimation
from a cannot: its shadow ray crosses the surface (Hanika, Droske & Fascione 2015;
Zeltner, Georgiev & Jakob 2020).

The technique (`manifold_nee`): at every live non-delta camera vertex a under the water, a
point y_0 on a light (`_lights.sample_emission`, area pdf a_0 = p_sel / A; a point light's
selection) and the surface point s that refracts y_0's light to a: Newton from the
flat-water solution (`_manifold.flat_seed`, `solve_near`). Call the result F(a, y_0): a
deterministic function, one root or none. The contribution of a root, both segments
shadow-tested:

    beta(a) f(a) I(y_0 -> s) T(s) T_r(a, s) G_perp / a_0

(f: the scattering factor with its cosine, or the phase function; I: Le |cos| of an area
light, a point light's intensity; T: Fresnel transmittance; T_r: the water's
transmittance of a -> s; G_perp = d omega_{y0} / d A_perp(a), the solid angle at the light
per unit area across the ray at a through the chain, `_manifold.generalized_geometry`).

MIS: the technique is the connection technique 2 of the path (light vertices y_0, s; the
camera's from a on), which the delta convention of the sums excludes because x_1 = s is a
delta vertex. In the sums' convention (a Dirac stored as 1, area conversions kept, the
pdfs a_i light side, b_i camera side) its pdf is a_0 a_1^eff b_2 b_3 ..., where

    a_1^eff = cos_s / (d(y_0, s)^2 d(s, a)^2 P_T(s) G_perp)

makes its ratio to every other technique the ratio of the true densities: against the
light subpath through s (technique 3), a_1^eff b_2 / (a_1 a_2) = p_C(a) / (p_omega(y_0)
P_T G_perp cos-or-1 P_pass), the camera's pdf of a over the light's density of a through
the chain; against the emitter hit the same by the chain's reciprocity (P_T: the
subpath's Fresnel choice of refraction at s). So the technique is one more term of the
sums with the log factor lm = log(a_1^eff / a_1): `_mis._explicit` adds it to the term of
technique 2 wherever that term is summed (the light subpaths' partials at y_2,
`light_factors`; an emitter hit through s, `emitter_hit_factor`; the technique's own
weight, `lm_own`).

Unbiased whatever the solver misses: every site that adds the manifold term for a path
first asks F(a, y_0) (the same function from the same vertices) and adds it only where F
returns that path's s. So the weights of all techniques that make a path sum to 1 on
every path: a root F misses (a fold's second root, a root outside the seed's basin) keeps
the weights it had without this technique. Refused for a dispersive water (a hero-only
refraction); the sky is not a light end of it.

The sun (`b_dir`: its light end is the direction d its light travels): the root is the
entry point of the refracted beam through a, the contribution beta f E T T_r G_perp /
p_sel with G_perp = d A_perp(beam) / d A_perp(a), and the light subpath's y_0 is its point
on the emission disk: a_1 = p_disk cos_s (a line from infinity) and a_1^eff = cos_s /
(d(s, a)^2 P_T G_perp).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _geometry as geometry
from . import _lights as lights
from . import _manifold as manifold
from . import _media as media
from . import _subpath as subpath
from . import _vec as vec
from ._config import RenderConfig
from ._materials import fresnel_dielectric
from ._mis import mis_form
from ._mis._explicit import Entries, log_pos
from ._path import log_n_light_tracing, reverse_pdf
from ._queue import masked_map
from ._scene import (DELTA_LIGHTS, LIGHT_POINT, LIGHT_RECT, LIGHT_SPHERE, LIGHT_SUN,
                     MAT_DIELECTRIC, Scene)
from ._subpath import PathEnds, rows, vertex_table
from ._vec import Vec3

ITERS = 10  # Newton iterations from the flat-water seed
STREAM = 0x6D_6E_65_65  # fold_in tag of the technique's light samples ("mnee")
_POINT_KINDS = (LIGHT_RECT, LIGHT_SPHERE, LIGHT_POINT)


def applies(scene: Scene) -> bool:
    """The scene has a non-dispersive water and a light the technique reaches (area,
    point, sun)."""
    return scene.water.enabled and not scene.materials.dispersive and bool(_ends(scene))


def _ends(scene: Scene) -> list[bool]:
    """The kinds of light end in this scene (static; `b_dir`): a point (area and point
    lights: False), a direction (the sun: True)."""
    kinds = scene.lights.kind
    return ([False] if any(k in _POINT_KINDS for k in kinds) else []) + (
        [True] if LIGHT_SUN in kinds else [])


def _of_end(scene: Scene, light, b_dir: bool):
    """Traced: light `light` has the end kind `b_dir`."""
    want = (LIGHT_SUN,) if b_dir else _POINT_KINDS
    table = jnp.asarray([kind in want for kind in scene.lights.kind])
    return table[jnp.maximum(light, 0)] & (light >= 0)


def _normal(water, s: Vec3) -> Vec3:
    _, hx, hz = geometry.water_height(water, s.x, s.z, unroll=geometry.SOLVER_WAVES_UNROLLED)
    return vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))


def chain(scene: Scene, a: Vec3, s: Vec3, y: Vec3, G=None, b_dir: bool = False):
    """(log a_1^eff, G_perp) of the chain a -> s -> y (module doc): a under the water, y a
    light point above it (`b_dir`: the direction the sun's light travels), s the root.
    `G`: G_perp if already evaluated (the sun: d A_perp(beam) / d A_perp(a)). The log
    factor is a stopped value (a weight's)."""
    water = scene.water
    if G is None:
        G = manifold.generalized_geometry(water, a, s, y, refract=True, b_is_direction=b_dir)
    sg = jax.lax.stop_gradient
    a, s, y, Gs = sg(a), sg(s), sg(y), sg(G)
    n_s = _normal(sg(water), s)
    tiny = 1e-30
    if b_dir:  # towards the sun; no distance: a_1 of a line from infinity is cos_s p_disk
        w_y, log_d2 = vec.normalize(-y), 0.0
    else:
        d_sy = vec.length(y - s)
        w_y, log_d2 = (y - s) / jnp.maximum(d_sy, 1e-30), 2.0 * jnp.log(jnp.maximum(d_sy, tiny))
    d_sa = vec.length(a - s)
    cos_s = jnp.abs(vec.dot(n_s, w_y))
    R, _ = fresnel_dielectric(cos_s, sg(water.ior))  # the light arrives from the air
    p_t = 1.0 - R
    log_eff = (jnp.log(jnp.maximum(cos_s, tiny)) - log_d2
               - 2.0 * jnp.log(jnp.maximum(d_sa, tiny)) - jnp.log(jnp.maximum(p_t, tiny))
               - jnp.log(jnp.maximum(Gs, tiny)))
    ok = (cos_s > 0) & (p_t > 0) & (Gs > 0) & jnp.isfinite(Gs)
    return jnp.where(ok, log_eff, -jnp.inf), G


def solve(scene: Scene, a: Vec3, y: Vec3, b_dir: bool = False, iters: int = ITERS
          ) -> manifold.Near:
    """F(a, y): Newton from the flat-water seed (the technique's one solve)."""
    water = scene.water
    x0, z0 = manifold.flat_seed(water, a, y, b_is_direction=b_dir)
    return manifold.solve_near(water, a, y, x0, z0, refract=True, b_is_direction=b_dir,
                               iters=iters)


def returns(scene: Scene, a: Vec3, y: Vec3, s: Vec3, b_dir: bool = False):
    """F(a, y) returns the surface vertex s of a path (the check every site makes before
    it counts the technique's pdf)."""
    sg = jax.lax.stop_gradient
    a, y, s = sg(a), sg(y), sg(s)
    r = solve(scene, a, y, b_dir)
    return r.valid & (vec.length(sg(r.s) - s) <= 1e-4 * (1.0 + vec.length(s - a)))


def _surface_vertex(scene: Scene, v) -> jax.Array:
    """The vertex (a `PathEnds` row) is on the water surface (a delta refraction)."""
    return v.delta & (v.kind == MAT_DIELECTRIC) & (v.mat == scene.water.mat)


def _shape(scene: Scene, a, s, y_p: Vec3, light, light_ok, b_dir: bool = False):
    """The path a -> s -> y_0 is one the technique makes: a live non-delta vertex under
    the water, s on the surface, y_0 a light end of kind `b_dir` (a point: above the
    water; the sun: shining down)."""
    water = scene.water
    above = (y_p.y < 0) if b_dir else ~manifold.below(water, y_p)
    return (light_ok & _of_end(scene, light, b_dir) & a.alive & ~a.delta
            & _surface_vertex(scene, s) & manifold.below(water, a.p) & above)


def light_factors(scene: Scene, cfg: RenderConfig, lig: PathEnds, e: lights.Emission):
    """(ok [N], lm [N]): the light subpaths y_0 -> s = y_1 -> y_2 whose y_2 the technique
    reaches through their own s (F(y_2, y_0) = y_1), and the log factor of its term at
    y_2, log(a_1^eff / a_1) with a_1 the subpath's own pdf of y_1. A work queue over the
    lanes of that shape (most light subpaths of a pool)."""
    N = lig.A.shape[1]
    dt = lig.A.dtype
    if lig.A.shape[0] < 3:
        f = jnp.zeros((N,), bool)
        return f, jnp.zeros((N,), dt)
    y1, y2 = rows(lig, [1]), rows(lig, [2])
    one = lambda r: jax.tree.map(lambda a: a[0], r)  # noqa: E731
    y1, y2 = one(y1), one(y2)
    at = vertex_table(lig)
    lanes = jnp.arange(N, dtype=jnp.int32)
    ok_all, lm_all = jnp.zeros((N,), bool), jnp.zeros((N,), dt)
    for b_dir in _ends(scene):  # one queue per kind of light end
        end = (e.infinite & e.delta) if b_dir else ~e.infinite
        shape = _shape(scene, y2, y1, e.d if b_dir else e.p, e.light, end, b_dir)

        def item(n, b_dir=b_dir):
            s, a = at(1, n), at(2, n)
            y = Vec3(*(c[n] for c in (e.d if b_dir else e.p)))
            ok = returns(scene, a.p, y, s.p, b_dir)
            lm, _ = chain(scene, a.p, s.p, y, b_dir=b_dir)
            lm = lm - jnp.log(jnp.maximum(jax.lax.stop_gradient(s.A), 1e-30))
            ok = ok & jnp.isfinite(lm) & (s.A > 0)
            return ok, jnp.where(ok, lm, 0.0)

        ok, lm = masked_map(item, shape, (lanes,), (False, 0.0), 2)
        ok_all, lm_all = ok_all | ok, jnp.where(ok, lm, lm_all)
    return ok_all, lm_all


def emitter_hit_factor(scene: Scene, za, zs, z, light, escaped, j, A_s1):
    """(ok, lm) of an emitter hit at z = z_j through z_{j-1} = zs on the water surface from
    za = z_{j-2} (`_mis._explicit.join`'s `c2`): the technique makes that path iff F(za, z)
    returns zs; A_s1: the join's light-side pdf of zs, a_1."""
    if not any(not b for b in _ends(scene)):  # no light a camera path can hit
        return jnp.zeros((), bool), jnp.zeros((), A_s1.dtype)
    shape = (j >= 3) & ~escaped & _shape(scene, za, zs, z.p, light, jnp.ones((), bool))
    ok = shape & returns(scene, za.p, z.p, zs.p)
    lm, _ = chain(scene, za.p, zs.p, z.p)
    lm = lm - jnp.log(jnp.maximum(A_s1, 1e-30))
    ok = ok & jnp.isfinite(lm) & (A_s1 > 0)
    return ok, jnp.where(ok, lm, 0.0)


def two_vertex_light(cfg: RenderConfig, a0, a1, delta_light, leta0, q1=subpath.Q_SPECULAR):
    """The light side's entries of the technique: y_0 (pdf a_0) and the surface vertex s
    (the delta convention's a_1) as a two-vertex light subpath, in closed form (what
    `_explicit.entries(light(...), 2, t)` reads; `start_entries`' pattern): s starts no
    technique (a delta vertex: no next-event estimation from it, no merging at it); y_0
    starts the emitter hit unless the light is a delta light; no table. q1: the roulette
    survival a light subpath has at s (a delta vertex's)."""
    dt = a0.dtype
    f = jnp.zeros(a0.shape, bool)
    leta = jnp.broadcast_to(jnp.asarray(leta0, dt), a0.shape)
    return Entries(ok1=~f, lp1=log_pos(a1, 0.0), vc1=f, vm1=f,
                   q1=jnp.broadcast_to(jnp.asarray(q1, dt), a0.shape), delta1=~f, leta1=leta,
                   ok2=~f, lp2=log_pos(a0, 0.0),
                   vc2=jnp.asarray(cfg.techniques.emitter_hits) & ~delta_light, vm2=f,
                   delta2=f, leta2=leta, table=jnp.full(a0.shape, -jnp.inf, dt),
                   zero=~(a0 > 0) | ~(a1 > 0))


def manifold_nee(scene: Scene, cfg: RenderConfig, cam: PathEnds, parts, etas, key):
    """The technique from every camera vertex z_j, j = 1..D-2 (paths of j + 2 segments):
    {(2, j + 1): [N, C]}. Two work queues: every live non-delta vertex under the water
    samples its light point and runs its Newton solve; only those whose solve found a
    root trace the two shadow rays and evaluate the chain's Jacobian, the contribution
    and the weight."""
    D = cfg.max_depth
    js = np.arange(1, D - 1)
    if len(js) == 0:
        return {}
    N = cam.A.shape[1]
    J = len(js)
    dt = cam.A.dtype
    water = scene.water
    C = scene.channels
    log_n = log_n_light_tracing(cfg, N, dt)
    is_delta = jnp.asarray([k in DELTA_LIGHTS for k in scene.lights.kind])
    j_of = jnp.asarray(js, jnp.int32)
    cam_at = vertex_table(cam)
    u = jax.random.uniform(key, (J, N, 5), dt)
    sg = jax.lax.stop_gradient
    zs = rows(cam, js)
    want = zs.alive & ~zs.delta & manifold.below(water, zs.p)

    def emission(i, n):
        return lights.sample_emission(scene, u[i, n])

    ii = jnp.broadcast_to(jnp.arange(J, dtype=jnp.int32)[:, None], (J, N))
    nn = jnp.broadcast_to(jnp.arange(N, dtype=jnp.int32)[None, :], (J, N))
    out = jnp.zeros((J, N, C), dt)
    for b_dir in _ends(scene):  # two queues per kind of light end (a point, the sun)

        def end(e, b_dir=b_dir):  # the light end: a point, or the sun's travel direction
            if b_dir:
                return e.d, (e.infinite & e.delta) & (e.d.y < 0)
            return e.p, ~e.infinite & ~manifold.below(water, e.p)

        def search(i, n, b_dir=b_dir, end=end):  # the cheap part: the light end, one solve
            a = cam_at(j_of[i], n)
            e = emission(i, n)
            y, ok = end(e)
            r = solve(scene, a.p, y, b_dir)
            return ok & _of_end(scene, e.light, b_dir) & r.valid, sg(r.s.x), sg(r.s.z)

        found, xs, zs_ = masked_map(search, want, (ii, nn), (False, 0.0, 0.0), 2 * J)

        def item(i, n, b_dir=b_dir, end=end, found=found, xs=xs, zs_=zs_):
            j = j_of[i]
            ok = found[i, n]
            # a round's padding items (not found) run on a safe stand-in (a vertex under
            # the water, the light straight above it), so that no NaN of a garbage vertex
            # enters the gradients through the masked-out branch
            z = _safe_vertex(scene, ok, cam_at(j, n))
            zp = cam_at(j - 1, n)
            e = emission(i, n)
            one, zero = jnp.ones((), dt), jnp.zeros((), dt)
            y_safe = Vec3(zero, -one, zero) if b_dir else Vec3(z.p.x, water.level + 1.0, z.p.z)
            y = vec.where(ok, end(e)[0], y_safe)
            x0, z0 = jnp.where(ok, xs[i, n], z.p.x), jnp.where(ok, zs_[i, n], z.p.z)
            # the root again from itself: the polish step and its implicit-function
            # derivatives
            s = manifold.polished(water, z.p, y, x0, z0, refract=True, b_is_direction=b_dir)
            # ---- visibility: a -> s (under the water), s -> the light (above it) ----
            w_a, d_as, oa, wd, tmax = _segment(z.p, z.n, z.medium, s)
            vis = geometry.unoccluded(scene, oa, wd, tmax, cfg.march_steps)
            n_s = _normal(water, s)
            if b_dir:
                w_y, d_sy = vec.normalize(-y), jnp.asarray(jnp.inf, dt)
            else:
                d_sy = vec.length(y - s)
                w_y = (y - s) / jnp.maximum(d_sy, 1e-30)
            o2 = subpath.offset(s, n_s, w_y)
            t2 = d_sy if b_dir else vec.length(y - o2) * (1.0 - 1e-4)
            vis = vis & geometry.unoccluded(scene, o2, w_y, t2, cfg.march_steps)
            # ---- contribution (the sun: its irradiance through the beam's Jacobian) ----
            lm_eff, G = chain(scene, z.p, s, y, b_dir=b_dir)
            T = manifold.fresnel_factor(water, z.p, s, y, refract=True, b_is_direction=b_dir)
            Tr = media.transmittance(water, d_as) * jnp.ones((C,), dt)
            if b_dir:
                I = scene.lights.radiance[e.light]
            else:
                I = lights.emitted_toward(scene, e.light, -w_y, e.n)
            f = subpath.eval_f(scene, z.kind, z.mat, z.wo, w_a, z.n)
            contrib = z.beta * f * I * T * Tr * G / e.pdf_pos
            # ---- the pdfs at the join (technique (2, j + 1): light y_0, s; camera z_j ..) --
            # a_1: y_0 emits towards s (from the sun: the line through s, per perpendicular
            # area) -> area at s
            pe = lights.emission_pdf_dir(scene, e.light, e.n, -w_y, s)
            a1 = pe * subpath.to_area(1.0, False, n_s, w_y, jnp.where(b_dir, 1.0, d_sy), False,
                                      water, b_dir)
            A_s = subpath.to_area(1.0, z.medium, z.n, w_a, d_as, True, water)  # Dirac at s: 1
            A_s1, _ = reverse_pdf(scene, z.kind, z.mat, z.n, z.p, w_a, z.wo, zp.p, zp.medium,
                                  zp.n, z.seg_water)
            B_s1 = (subpath.bsdf_pdf(scene, z.kind, z.mat, None, z.wo, w_a, z.n)
                    * subpath.to_area(1.0, False, n_s, w_a, d_as, True, water))
            # b_0 through the Dirac at s (read only by the emitter hit's term: none for the
            # sun, a delta light)
            B_s2 = one if b_dir else subpath.to_area(1.0, False, e.n, w_y, d_sy, False, water)
            mj = mis_form(cfg)
            dl = is_delta[e.light]
            Le_ = two_vertex_light(cfg, sg(e.pdf_pos), sg(a1), dl, sg(etas[0]))
            t = j + 1
            Ce_ = mj.entries(cfg, parts[1], t, jnp.asarray(2, jnp.int32), (n,))
            lm = lm_eff - jnp.log(jnp.maximum(sg(a1), 1e-30))
            w = sg(mj.join(cfg, jnp.asarray(2, jnp.int32), t, Le_, Ce_, sg(A_s), sg(A_s1),
                           sg(B_s1), sg(B_s2), dl, jnp.asarray(b_dir), sg(log_n), lm_own=lm))
            good = ok & vis & jnp.isfinite(lm)
            return jnp.where(good, contrib * w, 0.0)

        out = out + masked_map(item, found, (ii, nn), 0.0, 2 * J)
    return {(2, int(j) + 1): out[i] for i, j in enumerate(js)}


def _safe_vertex(scene: Scene, ok, z):
    """z where ok, else a stand-in camera vertex half a metre under the middle of the
    water's footprint (a diffuse floor-like vertex facing up): finite everywhere."""
    water = scene.water
    fp = water.footprint
    dt = z.p.x.dtype
    c = Vec3(0.5 * (fp[0] + fp[1]), water.level - 0.5, 0.5 * (fp[2] + fp[3]))
    up = Vec3(jnp.zeros((), dt), jnp.ones((), dt), jnp.zeros((), dt))
    sub = z._replace(p=c, n=up, wo=up, medium=jnp.zeros((), bool), beta=jnp.zeros_like(z.beta))
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), z, sub)


def _segment(p: Vec3, n: Vec3, medium, s: Vec3):
    """a -> s: unit direction, distance, and its shadow ray (offset off a, direction, tmax
    short of s: nothing may lie between a and the root, the surface included)."""
    dv = s - p
    d = vec.length(dv)
    w = dv / jnp.maximum(d, 1e-30)
    o = subpath.spawn(p, n, medium, w)
    dd = s - o
    dl = vec.length(dd)
    return w, d, o, dd / jnp.maximum(dl, 1e-30), dl * (1.0 - 1e-4)
