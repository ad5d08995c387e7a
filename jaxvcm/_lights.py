"""Light sampling (next-event estimation) and emission evaluation, one point at a time.

Light selection: probability proportional to each light's emitted power estimate
(`Lights.power_weight`, computed at scene load from the mean over channels of the
radiance times pi times the emitting area; the sun and sky use the area of the scene's
bounding disk). The selection probability is part of every light pdf. It is treated
as a sampling decision and is detached from gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _sampling as S
from . import _vec as V
from ._scene import LIGHT_RECT, LIGHT_SKY, LIGHT_SPHERE, LIGHT_SUN, Scene
from ._vec import Vec3


class LightSample(NamedTuple):
    wi: Vec3  # unit direction from the shading point towards the light
    dist: Array  # distance to the sampled point, inf for sun and sky
    Le: Array  # [C] radiance (area, sky) or irradiance (sun) arriving along -wi
    pdf_w: Array  # solid-angle pdf including selection probability; 1 for the sun
    delta: Array  # sun: a delta distribution (MIS weight 1, no BSDF-sampling counterpart)
    valid: Array  # False: back side of a one-sided light, or sky below the horizon


def selection_pdf(scene: Scene) -> Array:
    w = jax.lax.stop_gradient(scene.lights.power_weight)
    return w / jnp.sum(w)


def rect_area(scene: Scene, i):
    e1 = V.from_array(scene.rects.e1[i])
    e2 = V.from_array(scene.rects.e2[i])
    return V.length(V.cross(e1, e2))


def sample_light(scene: Scene, p: Vec3, u_sel, u1, u2) -> LightSample:
    """Pick one light by power and sample a direction towards it from p."""
    lights = scene.lights
    sel = selection_pdf(scene)
    li, _ = S.sample_discrete(sel, u_sel)
    psel = sel[li]
    dt = p.x.dtype
    C = lights.radiance.shape[-1]
    out = LightSample(
        Vec3(jnp.zeros((), dt), jnp.ones((), dt), jnp.zeros((), dt)),
        jnp.asarray(jnp.inf, dt), jnp.zeros((C,), dt), jnp.ones((), dt),
        jnp.zeros((), bool), jnp.zeros((), bool))
    # Static unrolled loop over the (few) lights: compute each, keep the selected one.
    for k, kind in enumerate(lights.kind):
        Le = lights.radiance[k]
        if kind == LIGHT_RECT:
            r = lights.shape[k]
            p0 = V.from_array(scene.rects.p0[r])
            e1 = V.from_array(scene.rects.e1[r])
            e2 = V.from_array(scene.rects.e2[r])
            nl = V.cross(e1, e2)
            area = V.length(nl)
            nl = nl / area
            q = p0 + e1 * u1 + e2 * u2
            dv = q - p
            d2 = V.dot(dv, dv)
            dist = jnp.sqrt(d2)
            wi = dv / jnp.maximum(dist, 1e-30)
            cos_l = -V.dot(wi, nl)
            valid = (cos_l > 0) & (d2 > 0)
            pdf = d2 / jnp.maximum(cos_l * area, 1e-30)
            s = LightSample(wi, dist, Le, pdf, jnp.zeros((), bool), valid)
        elif kind == LIGHT_SPHERE:
            r = lights.shape[k]
            c = V.from_array(scene.spheres.center[r])
            rad = scene.spheres.radius[r]
            dirn = S.uniform_sphere(u1, u2)
            q = c + dirn * rad
            dv = q - p
            d2 = V.dot(dv, dv)
            dist = jnp.sqrt(d2)
            wi = dv / jnp.maximum(dist, 1e-30)
            cos_l = jnp.abs(V.dot(wi, dirn))  # two-sided emitter
            valid = (cos_l > 0) & (d2 > 0)
            pdf = d2 / jnp.maximum(cos_l * 4.0 * jnp.pi * rad * rad, 1e-30)
            s = LightSample(wi, dist, Le, pdf, jnp.zeros((), bool), valid)
        elif kind == LIGHT_SUN:
            dl = V.from_array(lights.direction[k])
            s = LightSample(-dl, jnp.asarray(jnp.inf, dt), Le, jnp.ones((), dt),
                            jnp.ones((), bool), jnp.ones((), bool))
        elif kind == LIGHT_SKY:
            loc = S.cosine_hemisphere(u1, u2)
            wi = Vec3(loc.x, loc.z, loc.y)  # z-up local -> y-up world
            pdf = S.cosine_hemisphere_pdf(wi.y)
            s = LightSample(wi, jnp.asarray(jnp.inf, dt), Le, pdf, jnp.zeros((), bool), wi.y > 0)
        else:  # pragma: no cover
            raise ValueError(kind)
        pick = li == k
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
    cos = V.dot(wo, n)
    for k, kind in enumerate(lights.kind):
        if kind == LIGHT_RECT:
            area = rect_area(scene, lights.shape[k])
            front = cos > 0
            Lk = jnp.where(front, lights.radiance[k], 0.0)
            pk = dist * dist / jnp.maximum(jnp.abs(cos) * area, 1e-30)
        elif kind == LIGHT_SPHERE:
            rad = scene.spheres.radius[lights.shape[k]]
            Lk = lights.radiance[k]
            pk = dist * dist / jnp.maximum(jnp.abs(cos) * 4.0 * jnp.pi * rad * rad, 1e-30)
        else:
            continue
        pick = is_light & (lid == k)
        Le = jnp.where(pick, Lk, Le)
        pdf = jnp.where(pick, pk * sel[k], pdf)
    return Le, jax.lax.stop_gradient(pdf)


def emitted_escape(scene: Scene, d: Vec3) -> tuple[Array, Array]:
    """Radiance of the sky along escaping direction d, and its NEE pdf (selection included)."""
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
            pdf = pdf + jnp.where(up, S.cosine_hemisphere_pdf(d.y) * sel[k], 0.0)
    return Le, jax.lax.stop_gradient(pdf)
