"""NumPy reference formulas shared by the tests and the worked fits (float64, no JAX).

`sky_floor_radiance` is the closed-form-plus-quadrature radiance of a white Lambertian
floor at the bottom of a wide flat pool under a uniform sky of radiance 1, per absorption
coefficient: sky light refracted in (Fresnel, n^2 radiance gain), attenuated on its slanted
way down, and the floor's light reflected back down by the surface (partially inside the
critical angle, totally beyond it), summed over round trips:

    E_sky = 2 pi int_0^th_c n^2 (1 - R(th)) exp(-s d / cos th) cos th sin th dth
    K     = 2 pi [int_0^th_c R(th) exp(-2 s d / cos th) cos sin dth
                  + int_th_c^pi/2 exp(-2 s d / cos th) cos sin dth]
    L_f   = (a / pi) E_sky sum_j ((a / pi) K)^j

(th: the angle in the water; th_c = asin(1/n)). Gauss-Legendre rules with 400 points on
each side of th_c. The transport tests (tests/transport/test_transport.py) check the same
formulas with adaptive quadrature, and the spectral tests (tests/transport/test_spectral.py)
check this vectorised form against them. `sun_floor_radiance` is the same floor under the
sun: its direct irradiance through the flat surface in place of E_sky.
"""

from __future__ import annotations

import numpy as np


def fresnel_unpolarised(cos_i, eta):
    """Unpolarised Fresnel reflectance, relative index eta = n_t / n_i (NumPy, vectorised).

    1 under total internal reflection."""
    sin2_t = (1 - cos_i**2) / eta**2
    cos_t = np.sqrt(np.maximum(0.0, 1 - sin2_t))
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return np.where(sin2_t >= 1, 1.0, 0.5 * (rp * rp + rs * rs))


def _gauss(th_c):
    """Gauss-Legendre nodes and weights on [0, th_c] and [th_c, pi/2] (400 points each)."""
    x, w = np.polynomial.legendre.leggauss(400)

    def rule(lo, hi):
        return 0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * (hi - lo) * w

    return rule(0.0, th_c), rule(th_c, np.pi / 2)


def floor_exchange(depth, sigma_a, n):
    """K [K] of the module doc: the irradiance that a flat pool's surface returns to a
    floor of unit radiance (Fresnel reflection inside the critical angle, total beyond it),
    attenuated over the round trip, per absorption coefficient sigma_a [K] (1/m)."""
    th_c = np.arcsin(1.0 / n)
    (t1, w1), (t2, w2) = _gauss(th_c)
    R1 = fresnel_unpolarised(np.cos(t1), 1.0 / n)
    sa = np.atleast_1d(np.asarray(sigma_a, np.float64))[:, None]
    cs1, cs2 = np.cos(t1) * np.sin(t1), np.cos(t2) * np.sin(t2)
    return 2 * np.pi * (np.sum(w1 * R1 * np.exp(-2 * sa * depth / np.cos(t1)) * cs1, -1)
                        + np.sum(w2 * np.exp(-2 * sa * depth / np.cos(t2)) * cs2, -1))


def _series(rho, round_trips):
    return (1.0 / (1.0 - rho) if round_trips is None
            else sum(rho**j for j in range(round_trips + 1)))


def sky_floor_radiance(depth, sigma_a, n, albedo=1.0, round_trips=None):
    """Radiance of a Lambertian floor at the bottom of a flat pool under a uniform sky.

    Sky light refracted in (Fresnel, n^2 radiance gain) and attenuated on its slanted way
    down, the floor's light reflected back down by the surface, summed over round trips,
    by Gauss-Legendre quadrature in the water's polar angle: L_f [K] for absorption
    coefficients sigma_a [K] (1/m) at `depth` (m), water index n, floor albedo `albedo`.
    round_trips: the number of floor -> surface -> floor returns to sum (a path tracer with
    max_depth D makes (D - 3) // 2 of them), or None for the whole geometric series."""
    th_c = np.arcsin(1.0 / n)
    (t1, w1), _ = _gauss(th_c)
    R1 = fresnel_unpolarised(np.cos(t1), 1.0 / n)
    sa = np.atleast_1d(np.asarray(sigma_a, np.float64))[:, None]
    cs1 = np.cos(t1) * np.sin(t1)
    e_sky = 2 * np.pi * np.sum(w1 * n**2 * (1 - R1) * np.exp(-sa * depth / np.cos(t1)) * cs1, -1)
    rho = albedo / np.pi * floor_exchange(depth, sigma_a, n)
    return albedo / np.pi * e_sky * _series(rho, round_trips)


def sun_floor_radiance(depth, sigma_a, n, albedo, irradiance, cos_i, round_trips=None):
    """Radiance of a Lambertian floor at the bottom of a wide flat pool under the sun.

    The sun's parallel beam (irradiance E normal to it, at cos_i from the zenith) keeps its
    horizontal footprint through the flat surface, so the floor's direct irradiance is
    E cos_i T(i) exp(-sigma_a depth / cos_t) (T: Fresnel transmittance, t: the refracted
    angle); the floor's light then returns by the surface as in `sky_floor_radiance`:
    L_f = (a / pi) E_direct sum_j ((a / pi) K)^j, K = `floor_exchange`. round_trips as
    there (a path that starts at a camera above the water, camera -> surface -> floor ->
    ... -> surface -> sun, makes (D - 4) // 2 of them at max_depth D)."""
    sa = np.atleast_1d(np.asarray(sigma_a, np.float64))
    cos_t = np.sqrt(1.0 - (1.0 - cos_i**2) / n**2)
    T = 1.0 - fresnel_unpolarised(cos_i, n)
    e_dir = irradiance * cos_i * T * np.exp(-sa * depth / cos_t)
    rho = albedo / np.pi * floor_exchange(depth, sigma_a, n)
    return albedo / np.pi * e_dir * _series(rho, round_trips)
