"""Surface scattering: Lambertian, ideal mirror, smooth dielectric (exact Fresnel), and
glossy: Lambertian k_d plus a normalised Phong lobe k_s (n + 2) / (2 pi) cos^n(alpha),
alpha the angle between wi and wo's mirror direction (SmallVCM's model; Lafortune &
Willems 1994), sampled by lobe (probabilities from the two reflectances' channel means)
with the lobe's pdf (n + 1) / (2 pi) cos^n(alpha) about the mirror direction, and
evaluated with the mixture pdf of both lobes. Its cos(alpha) = 2 (wo.n)(wi.n) - wo.wi is
symmetric in wo and wi, so f is reciprocal; without the horizon the lobe's directional
albedo is cos(theta_o) (the mean of cos(theta_i) over the lobe is cos(theta_r) (n + 1) /
(n + 2)), so k_d + k_s <= 1 conserves energy.

Conventions (pbrt): wo points away from the surface towards where the path came from,
wi away from the surface towards where it goes next; n is the geometric normal.
`beta` factors are f |cos| / pdf. Transport mode: camera paths carry radiance, so
refraction scales by 1 / eta^2 (eta = IOR of wi's side / IOR of wo's side);
light paths (importance) do not.

Dispersion (hero-wavelength termination; Wilkie, Nawaz, Droske, Weidlich & Hanika 2014,
sec. 4.3): a dielectric with one index per channel (`ior` of shape [C], channel 0 the hero
wavelength) chooses the lobe with the hero's Fresnel R_h and refracts along the hero's
direction. A reflection is the same direction for every wavelength: channel c is weighted
R_c / R_h. A refraction is valid for the hero only: the weight is 1/eta_h^2 (radiance) on
channel 0 and 0 on the others, and `disperse` is set; the path's owner multiplies the
hero by C once per full path (`_subpath.step`, `_connect`, `_merge`), which turns the
C-wavelength average into the single-wavelength estimator of the hero, unbiased because
the hero is uniform on the range.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _sampling as sampling
from . import _vec as vec
from ._scene import MAT_DIELECTRIC, MAT_DIFFUSE, MAT_GLOSSY, MAT_MIRROR
from ._vec import Vec3


def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance for |cos_i| with relative IOR eta = n_t / n_i.
    Returns (R, cos_t); R = 1 under total internal reflection."""
    cos_i = jnp.clip(jnp.abs(cos_i), 0.0, 1.0)
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1.0
    # (under total internal reflection cos_t = 0 without a square root at 0, whose
    # infinite derivative would make a NaN of the gradient through the discarded branch)
    cos_t = jnp.where(tir, 0.0, jnp.sqrt(jnp.where(tir, 1.0, 1.0 - sin2_t)))
    r_par = (eta * cos_i - cos_t) / jnp.maximum(eta * cos_i + cos_t, 1e-30)
    r_perp = (cos_i - eta * cos_t) / jnp.maximum(cos_i + eta * cos_t, 1e-30)
    R = 0.5 * (r_par * r_par + r_perp * r_perp)
    return jnp.where(tir, 1.0, R), cos_t


class BSDFSample(NamedTuple):
    wi: Vec3
    weight: Array  # [C] f |cos| / pdf
    pdf: Array  # solid-angle pdf (1 for delta lobes, by convention)
    delta: Array  # specular lobe sampled
    transmit: Array  # wi on the other side of the surface
    disperse: Array  # a refraction at a dispersive dielectric: channels > 0 terminated


def _glossy_parts(albedo, glossy, exponent, wo: Vec3, wi: Vec3, ns: Vec3):
    """(f [C], pdf) of the glossy material for wi on ns's side (the normal on wo's side):
    f = k_d / pi + k_s (n + 2) / (2 pi) c^n, pdf = P_d cos_i / pi + P_g (n + 1) / (2 pi) c^n,
    c = max(cos(wi, mirror of wo), 0); P_d, P_g the lobe probabilities (`_lobe_probs`)."""
    cos_i = jnp.maximum(vec.dot(wi, ns), 0.0)
    c = vec.dot(vec.reflect(wo, ns), wi)
    pos = c > 0
    cn = jnp.where(pos, jnp.exp(exponent * jnp.log(jnp.where(pos, c, 1.0))), 0.0)  # c^n
    p_d = _lobe_probs(albedo, glossy)
    f = albedo * sampling.INV_PI + glossy * ((exponent + 2.0) * 0.5 * sampling.INV_PI * cn)
    pdf = p_d * cos_i * sampling.INV_PI + (1.0 - p_d) * (exponent + 1.0) * 0.5 * sampling.INV_PI * cn
    return f, pdf


def _lobe_probs(albedo, glossy):
    """P(Lambertian lobe) of the glossy material: mean k_d / (mean k_d + mean k_s) (a
    sampling decision: detached; 1 when both are 0)."""
    a = jax.lax.stop_gradient(jnp.mean(albedo, axis=-1))
    g = jax.lax.stop_gradient(jnp.mean(glossy, axis=-1))
    t = a + g
    return jnp.where(t > 0, a / jnp.where(t > 0, t, 1.0), 1.0)


def sample_bsdf(kind, albedo, ior, wo: Vec3, n: Vec3, u1, u2, u_lobe, radiance=True,
                glossy=None, exponent=None, front=None) -> BSDFSample:
    """Sample wi for material `kind` (a traced int selecting among the static kinds).
    `radiance`: the transport mode, a static bool or a traced per-lane flag. `glossy`,
    `exponent`: the glossy material's k_s [C] and n (None: no glossy material). `front`:
    True where the material is one-sided: seen from behind (wo against n) it is black, the
    sample's weight 0 (None: no one-sided material)."""
    cos_o = vec.dot(wo, n)
    side = jnp.where(cos_o >= 0, 1.0, -1.0).astype(n.x.dtype)
    ns = n * side  # normal on wo's side

    # ---- Lambertian ----
    loc = sampling.cosine_hemisphere(u1, u2)
    wi_d = vec.to_world(loc, ns)
    pdf_d = sampling.cosine_hemisphere_pdf(loc.z)

    # ---- mirror ----
    wi_m = vec.reflect(wo, ns)

    # ---- dielectric: eta = n_t / n_i seen from wo's side ----
    C = albedo.shape[-1]
    ones = jnp.ones((C,), n.x.dtype)
    dispersive = jnp.ndim(ior) == 1  # one index per channel (static: the array's rank)
    ior_h = ior[0] if dispersive else ior  # the hero's index drives the sample
    eta = jnp.where(cos_o >= 0, ior_h, 1.0 / ior_h)
    R, cos_t = fresnel_dielectric(cos_o, eta)
    refl = u_lobe < R
    cos_i = jnp.abs(cos_o)
    wi_t = -wo / eta + ns * (cos_i / eta - cos_t)
    wi_t = vec.normalize(wi_t)
    wi_g = vec.where(refl, wi_m, wi_t)
    if isinstance(radiance, bool):
        scale_t = 1.0 / (eta * eta) if radiance else 1.0
    else:
        scale_t = jnp.where(radiance, 1.0 / (eta * eta), 1.0)
    if dispersive:
        R_c, _ = fresnel_dielectric(cos_o, jnp.where(cos_o >= 0, ior, 1.0 / ior))
        hero = (jnp.arange(C) == 0).astype(n.x.dtype)
        w_g = jnp.where(refl, R_c / jnp.maximum(R, 1e-30), scale_t * hero)
    else:
        w_g = jnp.where(refl, 1.0, scale_t) * ones

    is_d = kind == MAT_DIFFUSE
    is_m = kind == MAT_MIRROR
    wi = vec.where(is_d, wi_d, vec.where(is_m, wi_m, wi_g))
    weight = jnp.where(is_d | is_m, albedo, w_g)
    pdf = jnp.where(is_d, pdf_d, jnp.where(is_m, 1.0, jnp.where(refl, R, 1.0 - R)))
    delta = ~is_d
    transmit = (kind == MAT_DIELECTRIC) & ~refl
    disperse = transmit & dispersive
    # A diffuse sample exactly on the horizon carries nothing.
    weight = jnp.where(is_d & (loc.z <= 0), 0.0, weight)
    if glossy is not None:
        # ---- glossy: pick a lobe with u_lobe, sample it, weight by the mixture pdf ----
        is_g = kind == MAT_GLOSSY
        p_d = _lobe_probs(albedo, glossy)
        r = vec.reflect(wo, ns)
        n_s = jax.lax.stop_gradient(exponent)  # the sampled direction: a sampling decision
        cos_a = jnp.power(u1, 1.0 / (n_s + 1.0))
        s2 = 1.0 - cos_a * cos_a
        sin_a = jnp.where(s2 > 0, jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)), 0.0)
        phi = 2.0 * jnp.pi * u2
        lobe = Vec3(sin_a * jnp.cos(phi), sin_a * jnp.sin(phi), cos_a)
        wi_gl = vec.where(u_lobe < p_d, wi_d, vec.to_world(lobe, r))
        f, pdf_gl = _glossy_parts(albedo, glossy, exponent, wo, wi_gl, ns)
        cos_i = vec.dot(wi_gl, ns)
        ok = (cos_i > 0) & (pdf_gl > 0)
        w_gl = jnp.where(ok, f * cos_i / jnp.where(ok, pdf_gl, 1.0), 0.0)
        wi = vec.where(is_g, wi_gl, wi)
        weight = jnp.where(is_g, w_gl, weight)
        pdf = jnp.where(is_g, pdf_gl, pdf)
        delta = delta & ~is_g
    if front is not None:
        weight = jnp.where(front & (cos_o <= 0), 0.0, weight)
    return BSDFSample(wi, weight, pdf, delta, transmit, disperse)


def eval_bsdf(kind, albedo, wo: Vec3, wi: Vec3, n: Vec3, glossy=None, exponent=None,
              front=None) -> tuple[Array, Array]:
    """f(wo, wi) |cos(wi, n)| and the solid-angle pdf of sampling wi; zero for delta lobes.
    Lambertian and glossy surfaces are two-sided: wo and wi must lie on the same side.
    `glossy`, `exponent`: the glossy material's k_s [C] and n (None: no glossy material).
    `front`: True where the material is one-sided (then wo must lie on n's side as well;
    None: no one-sided material)."""
    cos_o = vec.dot(wo, n)
    cos_i = vec.dot(wi, n)
    same = cos_o * cos_i > 0
    if front is not None:
        same = same & (~front | (cos_o > 0))
    is_d = (kind == MAT_DIFFUSE) & same
    f = jnp.where(is_d, albedo * (sampling.INV_PI * jnp.abs(cos_i)), 0.0)
    pdf = jnp.where(is_d, sampling.INV_PI * jnp.abs(cos_i), 0.0)
    if glossy is not None:
        is_g = (kind == MAT_GLOSSY) & same
        ns = n * jnp.where(cos_o >= 0, 1.0, -1.0).astype(n.x.dtype)
        fg, pg = _glossy_parts(albedo, glossy, exponent, wo, wi, ns)
        f = jnp.where(is_g, fg * jnp.abs(cos_i), f)
        pdf = jnp.where(is_g, pg, pdf)
    return f, pdf
