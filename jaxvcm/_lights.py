"""Light sampling (next-event estimation) and emission evaluation, one point at a time.

Light selection: probability proportional to each light's emitted power estimate
(`Lights.power_weight`, computed at scene load from the mean over channels of the
radiance times pi times the emitting area; the sun, sky and background use the area of
the scene's bounding disk).

Lights at infinity: the sun (delta direction), the sky (constant radiance over the upper
hemisphere, cosine-distributed about +y when sampled) and the background (constant
radiance over every direction, uniform on the sphere when sampled: SmallVCM's
"background" light). A scene has at most one of sky and background (the emitter hit of an
escaped camera vertex belongs to it, `_connect._sky_id`).

Point lights (SmallVCM's point light): intensity I (W/sr) from a point, isotropic; a
delta position like the sun's delta direction: next-event estimation's "pdf" is the
selection probability (the irradiance I / d^2 arrives along -wi), emission starts at the
point with a direction uniform on the sphere (pdf 1 / (4 pi)), and no path can hit it.
The selection probability is part of every light pdf. It is treated as a sampling
decision and is detached from gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _sampling as sampling
from . import _vec as vec
from ._scene import (LIGHT_BACKGROUND, LIGHT_POINT, LIGHT_RECT, LIGHT_SKY, LIGHT_SPHERE, LIGHT_SUN,
                     Scene, bounding_sphere)
from ._vec import Vec3


class LightSample(NamedTuple):
    wi: Vec3  # unit direction from the shading point towards the light
    dist: Array  # distance to the sampled point, inf for sun and sky
    Le: Array  # [C] radiance (area, sky) or irradiance (sun; point: I / d^2) along -wi
    pdf_w: Array  # solid-angle pdf including selection probability; p_sel for sun, point
    delta: Array  # sun, point: a delta distribution (no BSDF-sampling counterpart)
    valid: Array  # False: back side of a one-sided light, or sky below the horizon
    light: Array  # index of the chosen light
    n: Vec3  # normal at the sampled light point (area lights)


def selection_pdf(scene: Scene) -> Array:
    w = jax.lax.stop_gradient(scene.lights.power_weight)
    total = jnp.sum(w)
    # sun / sky weights use the bounding disk, zero in a scene without geometry: uniform then
    return jnp.where(total > 0, w / jnp.where(total > 0, total, 1.0), 1.0 / w.shape[0])


class Group(NamedTuple):
    """Lights that share one code path (static): one kind and one aim fraction."""

    kind: int
    aim: float
    members: tuple[int, ...]


def groups(scene: Scene) -> tuple[Group, ...]:
    """The scene's lights grouped by (kind, aim fraction), in order of first appearance.
    Every per-light evaluation below runs once per group, on the parameters of the group's
    member at hand (`member`): the compiled program grows with the number of light kinds
    (at most six), never with the number of lights."""
    out: dict[tuple[int, float], list[int]] = {}
    for k, kind in enumerate(scene.lights.kind):
        out.setdefault((kind, aim_fraction(scene, k)), []).append(k)
    return tuple(Group(kind, aim, tuple(m)) for (kind, aim), m in out.items())


def member(scene: Scene, g: Group, light):
    """(index, picked): the light to read group g's parameters at, and whether the traced
    light index `light` belongs to g. A one-member group reads its member (a static index:
    no gather); otherwise `light` itself, or the group's first member when `light` is not
    in it (a genuine light of the kind, so the unpicked lanes compute finite values)."""
    if len(g.members) == 1:
        return g.members[0], light == g.members[0]
    table = jnp.asarray([k in g.members for k in range(scene.lights.count)])
    picked = table[jnp.maximum(light, 0)] & (light >= 0)  # -1 (no light) is in no group
    return jnp.where(picked, light, g.members[0]), picked


def shape_of(scene: Scene, k):
    """The rect / sphere index of light k (static k: a Python int)."""
    shapes = scene.lights.shape
    return shapes[k] if isinstance(k, int) else jnp.asarray(shapes, jnp.int32)[k]


def rect_area(scene: Scene, i):
    return rect_frame(scene, i)[4]


def rect_frame(scene: Scene, i):
    """(p0, e1, e2, unit normal, area) of rectangle i (the emitting side for lights)."""
    p0 = vec.from_array(scene.rects.p0[i])
    e1 = vec.from_array(scene.rects.e1[i])
    e2 = vec.from_array(scene.rects.e2[i])
    nl = vec.cross(e1, e2)
    area = vec.length(nl)
    return p0, e1, e2, nl / area, area


def sample_light(scene: Scene, p: Vec3, u_sel, u1, u2) -> LightSample:
    """Pick one light by power and sample a direction towards it from p."""
    lights = scene.lights
    sel = selection_pdf(scene)
    li, _ = sampling.sample_discrete(sel, u_sel)
    psel = sel[li]
    dt = p.x.dtype
    C = lights.radiance.shape[-1]
    up = Vec3(jnp.zeros((), dt), jnp.ones((), dt), jnp.zeros((), dt))
    out = LightSample(up, jnp.asarray(jnp.inf, dt), jnp.zeros((C,), dt), jnp.ones((), dt),
                      jnp.zeros((), bool), jnp.zeros((), bool), li, up)
    # One copy per group of lights (`groups`): compute it for the selected light's group
    # member, keep the selected one.
    for g in groups(scene):
        kind = g.kind
        k, pick = member(scene, g, li)
        Le = lights.radiance[k]
        if kind == LIGHT_RECT:
            p0, e1, e2, nl, area = rect_frame(scene, shape_of(scene, k))
            q = p0 + e1 * u1 + e2 * u2
            dv = q - p
            d2 = vec.dot(dv, dv)
            dist = jnp.sqrt(d2)
            wi = dv / jnp.maximum(dist, 1e-30)
            cos_l = -vec.dot(wi, nl)
            valid = (cos_l > 0) & (d2 > 0)
            pdf = d2 / jnp.maximum(cos_l * area, 1e-30)
            s = LightSample(wi, dist, Le, pdf, jnp.zeros((), bool), valid, li, nl)
        elif kind == LIGHT_SPHERE:
            r = shape_of(scene, k)
            c = vec.from_array(scene.spheres.center[r])
            rad = scene.spheres.radius[r]
            dirn = sampling.uniform_sphere(u1, u2)
            q = c + dirn * rad
            dv = q - p
            d2 = vec.dot(dv, dv)
            dist = jnp.sqrt(d2)
            wi = dv / jnp.maximum(dist, 1e-30)
            cos_l = jnp.abs(vec.dot(wi, dirn))  # two-sided emitter
            valid = (cos_l > 0) & (d2 > 0)
            pdf = d2 / jnp.maximum(cos_l * 4.0 * jnp.pi * rad * rad, 1e-30)
            s = LightSample(wi, dist, Le, pdf, jnp.zeros((), bool), valid, li, dirn)
        elif kind == LIGHT_SUN:
            dl = vec.from_array(lights.direction[k])
            s = LightSample(-dl, jnp.asarray(jnp.inf, dt), Le, jnp.ones((), dt),
                            jnp.ones((), bool), jnp.ones((), bool), li, dl)
        elif kind == LIGHT_SKY:
            loc = sampling.cosine_hemisphere(u1, u2)
            wi = Vec3(loc.x, loc.z, loc.y)  # z-up local -> y-up world
            pdf = sampling.cosine_hemisphere_pdf(wi.y)
            s = LightSample(wi, jnp.asarray(jnp.inf, dt), Le, pdf, jnp.zeros((), bool), wi.y > 0,
                            li, -wi)
        elif kind == LIGHT_POINT:
            dv = vec.from_array(lights.position[k]) - p
            d2 = vec.dot(dv, dv)
            dist = jnp.sqrt(d2)
            wi = dv / jnp.maximum(dist, 1e-30)
            s = LightSample(wi, dist, Le / jnp.maximum(d2, 1e-30), jnp.ones((), dt),
                            jnp.ones((), bool), d2 > 0, li, -wi)
        elif kind == LIGHT_BACKGROUND:
            wi = sampling.uniform_sphere(u1, u2)
            s = LightSample(wi, jnp.asarray(jnp.inf, dt), Le, jnp.asarray(0.25 / jnp.pi, dt),
                            jnp.zeros((), bool), jnp.ones((), bool), li, -wi)
        else:  # pragma: no cover
            raise ValueError(kind)
        out = jax.tree.map(lambda a, b: jnp.where(pick, a, b), s, out)
    pdf_w = out.pdf_w * jnp.where(out.delta, 1.0, psel)
    # A delta light's "pdf" is the selection probability alone (the estimator divides by it).
    pdf_w = jnp.where(out.delta, psel, pdf_w)
    return out._replace(pdf_w=jax.lax.stop_gradient(pdf_w))


def emitted_surface(scene: Scene, light_id, wo: Vec3, n: Vec3, dist) -> tuple[Array, Array]:
    """Radiance leaving an emitter towards wo (pointing away from the surface) and the
    NEE solid-angle pdf (selection included) of sampling that point from `dist` away."""
    lights = scene.lights
    C = lights.radiance.shape[-1]
    dt = n.x.dtype
    is_light = light_id >= 0
    lid = jnp.where(is_light, light_id, 0)
    sel = selection_pdf(scene)
    Le = jnp.zeros((C,), dt)
    pdf = jnp.zeros((), dt)
    cos = vec.dot(wo, n)
    for g in groups(scene):
        kind = g.kind
        if kind not in (LIGHT_RECT, LIGHT_SPHERE):
            continue
        k, pick = member(scene, g, lid)
        if kind == LIGHT_RECT:
            area = rect_area(scene, shape_of(scene, k))
            front = cos > 0
            Lk = jnp.where(front, lights.radiance[k], 0.0)
            pk = dist * dist / jnp.maximum(jnp.abs(cos) * area, 1e-30)
        else:
            rad = scene.spheres.radius[shape_of(scene, k)]
            Lk = lights.radiance[k]
            pk = dist * dist / jnp.maximum(jnp.abs(cos) * 4.0 * jnp.pi * rad * rad, 1e-30)
        pick = is_light & pick
        Le = jnp.where(pick, Lk, Le)
        pdf = jnp.where(pick, pk * sel[k], pdf)
    return Le, jax.lax.stop_gradient(pdf)


def emitted_escape(scene: Scene, d: Vec3) -> tuple[Array, Array]:
    """Radiance of the sky or background along escaping direction d, and its NEE pdf
    (selection included)."""
    lights = scene.lights
    C = lights.radiance.shape[-1]
    dt = d.x.dtype
    sel = selection_pdf(scene)
    Le = jnp.zeros((C,), dt)
    pdf = jnp.zeros((), dt)
    for k, kind in enumerate(lights.kind):
        if kind == LIGHT_SKY:
            up = d.y > 0
            Le = Le + jnp.where(up, lights.radiance[k], 0.0)
            pdf = pdf + jnp.where(up, sampling.cosine_hemisphere_pdf(d.y) * sel[k], 0.0)
        elif kind == LIGHT_BACKGROUND:
            Le = Le + lights.radiance[k]
            pdf = pdf + (0.25 / jnp.pi) * sel[k]
    return Le, jax.lax.stop_gradient(pdf)


# ---------------------------------------------------------------- emission (light subpaths)
class Emission(NamedTuple):
    """Start of a light subpath: the light vertex y_0 and the first ray.

    Area lights: y_0 is a point on the light (area pdf p_sel / A), the direction is
    cosine-distributed about the emitting normal (pdf cos / pi; spheres emit on both sides,
    cos / (2 pi)). Sun, sky and background: y_0 is a direction (the sun's is fixed, the
    sky's cosine-distributed about +y, the background's uniform on the sphere, pdf
    1 / (4 pi)); the ray starts on a disk of the scene's bounding radius
    perpendicular to it, outside the bounding sphere (perpendicular-area pdf 1 / (pi R^2)).
    """

    p: Vec3  # y_0 on an area light (the disk point for sun / sky)
    n: Vec3  # emitting normal of y_0 (area lights)
    o: Vec3  # origin of the first ray (offset off the light)
    d: Vec3  # direction light travels on the first segment
    beta0: Array  # [C] 1 / (p_sel p_A): throughput of y_0 before emission (light tracing, s = 1)
    beta1: Array  # [C] throughput carried by the first ray
    pdf_pos: Array  # light-side pdf of y_0 (area measure; solid angle for sky and
    #                 background; p_sel for the sun)
    pdf_dir: Array  # pdf of the first segment: solid angle (area lights), 1/(pi R^2) at infinity
    light: Array  # light index
    infinite: Array  # y_0 is at infinity (sun, sky, background)
    delta: Array  # delta light (sun, point)


def aim_fraction(scene: Scene, k: int) -> float:
    """Static fraction of light k's photons aimed at the water's footprint (0: none)."""
    aim = scene.lights.aim
    return float(aim[k]) if k < len(aim) else 0.0


def aimed_pdf(scene: Scene, d: Vec3, p: Vec3):
    """Perpendicular-area pdf of the aimed part of an infinite light's emission:
    the line of direction d (the way light travels) through p crosses the water's plane
    y = level at c; the aimed photons cross it in the footprint [x0, x1] x [z0, z1], in cell
    (i, j) of the [G, G] `aim_map` over the rectangle `aim_rect` (the footprint by default)
    with probability w_ij / sum w, uniformly inside the cell: density G^2 w_ij / (sum w A_F)
    per unit area of the plane (A_F the rectangle's area), and per unit area perpendicular
    to d divided by |d_y| (the plane's projected area element). 0 where c lies outside the
    rectangle or d is parallel to the plane."""
    wat = scene.water
    dt = d.x.dtype
    w = jax.lax.stop_gradient(scene.lights.aim_map).astype(dt)
    G = w.shape[0]
    rect = jax.lax.stop_gradient(scene.lights.aim_rect)
    x0, x1, z0, z1 = (rect[i].astype(dt) for i in range(4))
    ok_y = jnp.abs(d.y) > 1e-7
    dy = jnp.where(ok_y, d.y, -1.0)
    s = (wat.level.astype(dt) - p.y) / dy
    u = (p.x + d.x * s - x0) / (x1 - x0)
    v = (p.z + d.z * s - z0) / (z1 - z0)
    inside = ok_y & (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
    j = jnp.clip(jnp.floor(u * G), 0, G - 1).astype(jnp.int32)
    i = jnp.clip(jnp.floor(v * G), 0, G - 1).astype(jnp.int32)
    area = (x1 - x0) * (z1 - z0)
    dens = w[i, j] * (G * G) / (jnp.sum(w) * area * jnp.abs(dy))
    return jnp.where(inside, dens, 0.0)


def _aimed_origin(scene: Scene, d: Vec3, u1, u2):
    """A point c on the water's plane in the footprint, drawn from `aim_map` (cell by u1,
    remapped, then uniform in the cell by the rest of u1 and u2): `aimed_pdf`'s density."""
    wat = scene.water
    dt = u1.dtype
    w = jax.lax.stop_gradient(scene.lights.aim_map).astype(dt).reshape(-1)
    G = scene.lights.aim_map.shape[0]
    cdf = jnp.cumsum(w)
    total = cdf[-1]
    idx = jnp.minimum(jnp.sum(cdf <= u1 * total).astype(jnp.int32), G * G - 1)
    lo = jnp.where(idx > 0, cdf[jnp.maximum(idx - 1, 0)], 0.0)
    ur = jnp.clip((u1 * total - lo) / jnp.maximum(w[idx], 1e-30), 0.0, 1.0 - 1e-6)
    i, j = idx // G, idx % G
    rect = jax.lax.stop_gradient(scene.lights.aim_rect)
    x0, x1, z0, z1 = (rect[k].astype(dt) for k in range(4))
    x = x0 + (x1 - x0) * (j.astype(dt) + ur) / G
    z = z0 + (z1 - z0) * (i.astype(dt) + u2) / G
    return Vec3(x, wat.level.astype(dt) * jnp.ones((), dt), z)


def emission_pdf_dir(scene: Scene, light, n: Vec3, w: Vec3, p: Vec3 | None = None):
    """Pdf of the emission direction w (leaving y_0, the way light travels) for light
    `light` with normal n: solid angle for area lights and point lights (1 / (4 pi)); at
    infinity the perpendicular-area pdf of the line of direction w through the point p:
    1/(pi R^2) on the bounding disk, mixed with `aimed_pdf` for an aimed light (p needed
    then; the mixture is the density the emission samples, so every technique's MIS sees
    the same pdf)."""
    _, rb = bounding_sphere(scene)
    dt = n.x.dtype
    pdf = jnp.zeros((), dt)
    cos = vec.dot(n, w)
    for g in groups(scene):
        kind = g.kind
        if kind == LIGHT_RECT:
            pk = jnp.maximum(cos, 0.0) * sampling.INV_PI
        elif kind == LIGHT_SPHERE:
            pk = jnp.abs(cos) * (0.5 * sampling.INV_PI)
        elif kind == LIGHT_POINT:
            pk = jnp.asarray(0.25 / jnp.pi, dt)
        else:
            pk = jnp.ones((), dt) / (jnp.pi * rb * rb)
            P = g.aim
            if P > 0:
                if p is None:
                    raise ValueError("emission_pdf_dir: an aimed light needs the point p")
                pk = (1.0 - P) * pk + P * aimed_pdf(scene, w, p)
        pdf = jnp.where(member(scene, g, light)[1], pk, pdf)
    return jax.lax.stop_gradient(pdf)


def light_point_pdf(scene: Scene, light, w_inf: Vec3):
    """Light-side pdf of y_0 (selection included): p_sel / area for area lights; for the
    sky and background p_sel times the direction pdf of w_inf (pointing to the sky); p_sel
    for the sun and point lights (delta: remapped to 1 times the selection)."""
    sel = selection_pdf(scene)
    dt = w_inf.x.dtype
    pdf = jnp.zeros((), dt)
    for g in groups(scene):
        kind = g.kind
        k, pick = member(scene, g, light)
        if kind == LIGHT_RECT:
            pk = 1.0 / rect_area(scene, shape_of(scene, k))
        elif kind == LIGHT_SPHERE:
            r = scene.spheres.radius[shape_of(scene, k)]
            pk = 1.0 / (4.0 * jnp.pi * r * r)
        elif kind == LIGHT_SKY:
            pk = sampling.cosine_hemisphere_pdf(w_inf.y)
        elif kind == LIGHT_BACKGROUND:
            pk = jnp.asarray(0.25 / jnp.pi, dt)
        else:
            pk = jnp.ones((), dt)
        pdf = jnp.where(pick, pk * sel[k], pdf)
    return jax.lax.stop_gradient(pdf)


def emitted_toward(scene: Scene, light, w: Vec3, n: Vec3):
    """What y_0 sends towards direction w in light tracing's s = 1 technique, per unit
    projected area and solid angle as the estimator divides it: Le |cos(n, w)| for area
    lights (Le on the emitting side), I for point lights. [C]"""
    lights = scene.lights
    C = lights.radiance.shape[-1]
    dt = n.x.dtype
    Le, _ = emitted_surface(scene, light, w, n, jnp.ones((), dt))
    out = Le * jnp.abs(vec.dot(n, w))
    for g in groups(scene):
        if g.kind == LIGHT_POINT:
            k, pick = member(scene, g, light)
            out = jnp.where(pick, lights.radiance[k], out)
    return out * jnp.ones((C,), dt)


def sample_emission(scene: Scene, u) -> Emission:
    """Sample y_0 and the first direction of a light subpath. u: 5 uniforms."""
    lights = scene.lights
    sel = selection_pdf(scene)
    li, _ = sampling.sample_discrete(sel, u[0])
    psel = sel[li]
    dt = u.dtype
    C = lights.radiance.shape[-1]
    cb, rb = bounding_sphere(scene)
    cb = vec.from_array(cb)
    z = jnp.zeros((), dt)
    zero3 = Vec3(z, z, z)
    out = Emission(zero3, zero3, zero3, Vec3(z, -jnp.ones((), dt), z), jnp.zeros((C,), dt),
                   jnp.zeros((C,), dt), jnp.ones((), dt), jnp.ones((), dt),
                   jnp.asarray(0, jnp.int32), jnp.zeros((), bool), jnp.zeros((), bool))
    dx, dy = sampling.concentric_disk(u[3], u[4])
    for g in groups(scene):
        kind = g.kind
        k, pick = member(scene, g, li)
        Le = lights.radiance[k]
        if kind == LIGHT_POINT:  # y_0 the point, the direction uniform on the sphere
            p = vec.from_array(lights.position[k])
            d = sampling.uniform_sphere(u[1], u[2])
            pdf_dir = jnp.asarray(0.25 / jnp.pi, dt)
            e = Emission(p, d, p, d, jnp.ones((C,), dt) / psel, Le / (psel * pdf_dir), psel,
                         pdf_dir, jnp.asarray(k, jnp.int32), jnp.zeros((), bool),
                         jnp.ones((), bool))
        elif kind in (LIGHT_RECT, LIGHT_SPHERE):
            if kind == LIGHT_RECT:
                p0, e1, e2, n, area = rect_frame(scene, shape_of(scene, k))
                p = p0 + e1 * u[1] + e2 * u[2]
                loc = sampling.cosine_hemisphere(u[3], u[4])
                d = vec.to_world(loc, n)
                pdf_dir = sampling.cosine_hemisphere_pdf(loc.z)
            else:
                r = shape_of(scene, k)
                c = vec.from_array(scene.spheres.center[r])
                rad = scene.spheres.radius[r]
                area = 4.0 * jnp.pi * rad * rad
                # u[1] picks the side (both sides emit), reused for the point
                out_side = u[1] < 0.5
                u1 = jnp.where(out_side, 2.0 * u[1], 2.0 * u[1] - 1.0)
                n = sampling.uniform_sphere(u1, u[2])
                p = c + n * rad
                loc = sampling.cosine_hemisphere(u[3], u[4])
                nn = vec.where(out_side, n, -n)
                d = vec.to_world(loc, nn)
                pdf_dir = 0.5 * sampling.cosine_hemisphere_pdf(loc.z)
            cos = jnp.abs(vec.dot(d, n))
            pdf_pos = psel / area
            scale = 1e-4 * (1.0 + jnp.maximum(jnp.maximum(jnp.abs(p.x), jnp.abs(p.y)), jnp.abs(p.z)))
            o = p + n * jnp.where(vec.dot(d, n) >= 0, scale, -scale)
            e = Emission(p, n, o, d, jnp.ones((C,), dt) / pdf_pos, Le * cos / (pdf_pos * pdf_dir), pdf_pos,
                         pdf_dir, jnp.asarray(k, jnp.int32), jnp.zeros((), bool),
                         jnp.zeros((), bool))
        else:
            if kind == LIGHT_SUN:
                d = vec.from_array(lights.direction[k])
                pdf_pos = psel
                delta = jnp.ones((), bool)
            elif kind == LIGHT_SKY:
                loc = sampling.cosine_hemisphere(u[1], u[2])
                w_sky = Vec3(loc.x, loc.z, loc.y)
                d = -w_sky
                pdf_pos = psel * sampling.cosine_hemisphere_pdf(w_sky.y)
                delta = jnp.zeros((), bool)
            else:  # background: y_0 a direction uniform on the sphere
                d = -sampling.uniform_sphere(u[1], u[2])
                pdf_pos = psel * (0.25 / jnp.pi)
                delta = jnp.zeros((), bool)
            t1, t2 = vec.onb(d)
            o = cb - d * (rb * 1.01) + (t1 * dx + t2 * dy) * rb
            pdf_disk = 1.0 / (jnp.pi * rb * rb) * jnp.ones((), dt)
            P = g.aim
            if P > 0:
                # ---- aimed: with probability P (u[3] < P, remapped) the line crosses the
                # water's plane at a point drawn from the footprint's map; it starts
                # outside the bounding sphere (1.01 R behind its centre along d) ----
                aimed = u[3] < P
                ua = jnp.clip(u[3] / P, 0.0, 1.0 - 1e-6)
                ub = jnp.clip((u[3] - P) / (1.0 - P), 0.0, 1.0 - 1e-6)
                dx2, dy2 = sampling.concentric_disk(ub, u[4])
                o_disk = cb - d * (rb * 1.01) + (t1 * dx2 + t2 * dy2) * rb
                c = _aimed_origin(scene, d, ua, u[4])
                o_aim = c - d * (vec.dot(c - cb, d) + rb * 1.01)
                o = vec.where(aimed, o_aim, o_disk)
                pdf_disk = (1.0 - P) * pdf_disk + P * aimed_pdf(scene, d, o)
            e = Emission(o, -d, o, d, jnp.zeros((C,), dt), Le / (pdf_pos * pdf_disk), pdf_pos,
                         pdf_disk, jnp.asarray(k, jnp.int32),
                         jnp.ones((), bool), delta)
        out = jax.tree.map(lambda a, b: jnp.where(pick, a, b), e, out)
    return out._replace(pdf_pos=jax.lax.stop_gradient(out.pdf_pos),
                        pdf_dir=jax.lax.stop_gradient(out.pdf_dir))
