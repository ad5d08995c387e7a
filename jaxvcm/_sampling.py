"""Warping functions: uniform numbers in [0,1)^k -> directions and points, with pdfs.

Each sampler has a matching `*_pdf`; the test suite checks that every pdf integrates to
one and that histograms of the samplers match the pdfs (chi-square).
Directions are in a local frame with z along the normal/axis unless stated otherwise.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._fuse import computed_once
from ._vec import Vec3

INV_PI = 1.0 / jnp.pi
INV_4PI = 0.25 / jnp.pi


def sincos(phi):
    """(cos phi, sin phi), each computed once (`_fuse.computed_once`: otherwise the CPU
    backend recomputes both in every fusion that reads the sampled direction)."""
    return computed_once(jnp.cos(phi), jnp.sin(phi))


def concentric_disk(u1, u2):
    """Shirley-Chiu map of [0,1)^2 onto the unit disk (area pdf 1/pi)."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    use_a = jnp.abs(a) > jnp.abs(b)
    r = jnp.where(use_a, a, b)
    safe_a = jnp.where(a == 0, 1.0, a)
    safe_b = jnp.where(b == 0, 1.0, b)
    phi = jnp.where(use_a, (jnp.pi / 4) * (b / safe_a), (jnp.pi / 2) - (jnp.pi / 4) * (a / safe_b))
    zero = (a == 0) & (b == 0)
    r = jnp.where(zero, 0.0, r)
    c, s = sincos(phi)
    return r * c, r * s


def cosine_hemisphere(u1, u2) -> Vec3:
    x, y = concentric_disk(u1, u2)
    z = jnp.sqrt(jnp.maximum(0.0, 1.0 - x * x - y * y))
    return Vec3(x, y, z)


def cosine_hemisphere_pdf(cos_theta):
    return jnp.maximum(cos_theta, 0.0) * INV_PI


def uniform_sphere(u1, u2) -> Vec3:
    z = 1.0 - 2.0 * u1
    r = jnp.sqrt(jnp.maximum(0.0, 1.0 - z * z))
    c, s = sincos(2.0 * jnp.pi * u2)
    return Vec3(r * c, r * s, z)


def uniform_sphere_pdf():
    return INV_4PI


def _around_axis(cos_t, u2) -> Vec3:
    sin_t = jnp.sqrt(jnp.maximum(0.0, 1.0 - cos_t * cos_t))
    c, s = sincos(2.0 * jnp.pi * u2)
    return Vec3(sin_t * c, sin_t * s, cos_t)


# ---- Henyey-Greenstein. Convention: mu = cos of the angle between the incoming
# propagation direction and the scattered direction (forward scattering: mu -> 1).
def hg_pdf(mu, g):
    denom = 1.0 + g * g - 2.0 * g * mu
    return INV_4PI * (1.0 - g * g) / (denom * jnp.sqrt(jnp.maximum(denom, 1e-30)))


def hg_sample_mu(u1, g):
    """Inverse CDF of HG in mu; isotropic limit for |g| < 1e-3."""
    sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1)
    g_safe = jnp.where(jnp.abs(g) < 1e-3, 1.0, g)
    mu_hg = (1.0 + g * g - sq * sq) / (2.0 * g_safe)
    mu = jnp.where(jnp.abs(g) < 1e-3, 1.0 - 2.0 * u1, mu_hg)
    return jnp.clip(mu, -1.0, 1.0)


def hg_sample(u1, u2, g) -> Vec3:
    """Local direction (z = propagation direction of the incoming light)."""
    return _around_axis(hg_sample_mu(u1, g), u2)


# ---- pure-water phase function p(mu) = 3 (1 + b mu^2) / (4 pi (3 + b)) (Morel 1974, b = 0.835).
def water_phase_pdf(mu, b):
    return 3.0 * (1.0 + b * mu * mu) / (4.0 * jnp.pi * (3.0 + b))


def water_phase_sample_mu(u1, b):
    """Invert CDF(mu) = (mu + b mu^3/3 + 1 + b/3) / (2 + 2b/3) = u: the depressed cubic
    (b/3) mu^3 + mu + c = 0 with b > 0 has a single real root (Cardano)."""
    b = jnp.maximum(b, 1e-6)
    c = -(u1 * (2.0 + 2.0 * b / 3.0) - 1.0 - b / 3.0)
    # mu^3 + p mu + q = 0 with p = 3/b, q = 3c/b
    p = 3.0 / b
    q = 3.0 * c / b
    disc = jnp.sqrt(q * q / 4.0 + p * p * p / 27.0)
    mu = jnp.cbrt(-q / 2.0 + disc) + jnp.cbrt(-q / 2.0 - disc)
    return jnp.clip(mu, -1.0, 1.0)


def water_phase_sample(u1, u2, b) -> Vec3:
    return _around_axis(water_phase_sample_mu(u1, b), u2)


def isotropic_sample(u1, u2) -> Vec3:
    return uniform_sphere(u1, u2)


# ---- discrete
def sample_discrete(weights, u):
    """Index i with probability weights[i] / sum(weights); returns (i, prob)."""
    cdf = jnp.cumsum(weights)
    total = cdf[-1]
    i = jnp.sum(cdf <= u * total).astype(jnp.int32)
    i = jnp.minimum(i, weights.shape[0] - 1)
    return i, weights[i] / total
