"""Target colours for the Jerlov fits: a white floor at depth d under a uniform D65 sky, in
water whose diffuse attenuation is Jerlov's (1976) K_d, computed with NumPy and
colour-science only (no renderer code except the shipped data tables).

Model (per wavelength lambda, all radiances relative to a uniform sky of radiance 1 whose
spectrum is D65 with luminance Y = 1):

1. K_d(lambda) between and beyond Jerlov's 50 nm nodes (400..700 nm): K_d = a_w(lambda) +
   dK(lambda), a_w = Pope & Fry 1997 (the fine spectral shape of the water itself, e.g. its
   shoulder at 580-600 nm, which a 50 nm linear interpolation of K_d would smear), dK the
   node excess K_d - a_w interpolated linearly in lambda and extrapolated linearly from the
   end segments (400-450 below 400 nm, 650-700 above 700 nm). `interp="linear"` interpolates
   K_d itself instead (used only to state how much the choice matters).
2. Sky irradiance just below the flat surface: E_d(0-) = 2 pi int_0^theta_c n^2 (1 - R(theta))
   cos(theta) sin(theta) dtheta (in-water angles, n = 1.33468 = Daimon & Masumura n(550), the
   renderer's index; R unpolarised Fresnel).
3. Downwelling irradiance on the floor: E_d(d) = E_d(0-) exp(-K_d d) (the Jerlov K_d applied
   to this light field).
4. The floor is white (albedo 1). Its reflected light partly comes back down from the
   surface (Fresnel inside the cone, total internal reflection outside), and the rendered
   scene has that too, so the target includes it: the water is replaced, per wavelength and
   depth, by the non-scattering water of attenuation s(lambda, d) that gives the same
   E_d(d) / E_d(0-) = exp(-K_d d) for this light field (s ~ mu_d K_d, an estimate of a + b_b),
   and the floor radiance is the 1-D quadrature of tests/transport/test_spectral.sky_floor_radiance
   with all round trips: L_f = (1 / pi) E_d(d) / (1 - rho), rho = (1 / pi) 2 pi [int_0^theta_c
   R e^(-2 s d / cos) cos sin + int_theta_c^(pi/2) e^(-2 s d / cos) cos sin]. `round_trips=0`
   gives the issue's simple model L_f = (1 / pi) E_d(0-) exp(-K_d d).
5. The camera, h = 0.3 m above the floor looking straight down, sees L_f exp(-s h): nadir
   radiance from a uniform Lambertian floor loses ~a + b_b per metre (forward scattering
   from the neighbouring floor refills the beam), not the diffuse K_d = (a + b_b) / mu_d.
   So the whole target is the colour of that equivalent non-scattering water, which the
   renderer reproduces exactly (tests/transport/test_spectral.py, dE2000 0.14). `camera="kd"` gives
   the first version's exp(-K_d h) (result.json variants, NOTES.md).
6. XYZ = colour.sd_to_XYZ(L on the Pope & Fry grid 380..725 nm, CIE 1931 2 deg, D65) / 100,
   i.e. Y relative to the sky's Y = 1 (the same absolute scale as the renderer's film).
"""

from __future__ import annotations

import numpy as np

from jaxvcm import fresnel_unpolarised

N_WATER = 1.33468  # Daimon & Masumura n(550 nm) at 20 C: the renderer's default index
CAM_HEIGHT = 0.3  # m, camera above the floor


def _tables():
    from jaxvcm import jerlov_table, pope_fry_table

    return jerlov_table(), pope_fry_table()


def jerlov_kd(name: str, lam, interp: str = "water") -> np.ndarray:
    """K_d (1/m) of Jerlov type `name` at wavelengths lam (nm), see the module docstring."""
    (names, wl, kd), (pw, pa) = _tables()
    k = kd[:, names.index(name)]
    lam = np.asarray(lam, np.float64)
    if interp == "linear":
        base_nodes, base = np.zeros_like(wl), np.zeros_like(lam)
    elif interp == "water":
        base_nodes, base = np.interp(wl, pw, pa), np.interp(lam, pw, pa)
    else:
        raise ValueError(interp)
    dk = k - base_nodes
    out = np.interp(lam, wl, dk)
    lo, hi = lam < wl[0], lam > wl[-1]
    out[lo] = dk[0] + (lam[lo] - wl[0]) * (dk[1] - dk[0]) / (wl[1] - wl[0])
    out[hi] = dk[-1] + (lam[hi] - wl[-1]) * (dk[-1] - dk[-2]) / (wl[-1] - wl[-2])
    return base + out


_fresnel = fresnel_unpolarised


class _Quad:
    """Gauss-Legendre rules (400 points) on [0, theta_c] and [theta_c, pi / 2]."""

    def __init__(self, n=N_WATER):
        x, w = np.polynomial.legendre.leggauss(400)
        th_c = np.arcsin(1.0 / n)
        r = lambda lo, hi: (0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * (hi - lo) * w)  # noqa
        self.t1, self.w1 = r(0.0, th_c)
        self.t2, self.w2 = r(th_c, np.pi / 2)
        self.n = n
        self.R1 = _fresnel(np.cos(self.t1), 1.0 / n)
        self.cs1 = np.cos(self.t1) * np.sin(self.t1)
        self.cs2 = np.cos(self.t2) * np.sin(self.t2)

    def e_down(self, s, d):
        """Direct sky irradiance at depth d in non-scattering water of attenuation s [K]."""
        s = np.asarray(s, np.float64)[..., None]
        return 2 * np.pi * np.sum(self.w1 * self.n**2 * (1 - self.R1)
                                  * np.exp(-s * d / np.cos(self.t1)) * self.cs1, -1)

    def k_return(self, s, d):
        """Fraction (x pi) of a Lambertian floor's exitance returned to it by the surface."""
        s = np.asarray(s, np.float64)[..., None]
        return 2 * np.pi * (np.sum(self.w1 * self.R1 * np.exp(-2 * s * d / np.cos(self.t1))
                                   * self.cs1, -1)
                            + np.sum(self.w2 * np.exp(-2 * s * d / np.cos(self.t2)) * self.cs2,
                                     -1))

    def mu_d(self):
        """Mean cosine E_d / E_0 of the refracted uniform sky just below the surface."""
        e0 = 2 * np.pi * np.sum(self.w1 * self.n**2 * (1 - self.R1) * np.sin(self.t1))
        return float(self.e_down(0.0, 0.0) / e0)

    def equivalent_attenuation(self, kd, d):
        """s with e_down(s, d) / e_down(0, 0) = exp(-kd d) (bisection, vectorised)."""
        kd = np.asarray(kd, np.float64)
        e0 = self.e_down(0.0, 0.0)
        goal = np.exp(-kd * d)
        lo, hi = np.zeros_like(kd), np.maximum(kd, 1e-12)  # e_down(kd)/e0 <= exp(-kd d)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            too_dark = self.e_down(mid, d) / e0 < goal
            hi = np.where(too_dark, mid, hi)
            lo = np.where(too_dark, lo, mid)
        return 0.5 * (lo + hi)


QUAD = _Quad()


def grid():
    return _tables()[1][0]


def floor_radiance(name: str, depth: float, round_trips: bool = True, interp: str = "water",
                   lam=None, camera: str = "s") -> np.ndarray:
    """Radiance seen by the camera (sky radiance 1 at every wavelength) on `lam` (default:
    the Pope & Fry grid)."""
    lam = grid() if lam is None else np.asarray(lam, np.float64)
    kd = jerlov_kd(name, lam, interp)
    e = QUAD.e_down(0.0, 0.0) * np.exp(-kd * depth)
    s = QUAD.equivalent_attenuation(kd, depth)
    if round_trips:
        rho = QUAD.k_return(s, depth) / np.pi
        e = e / (1.0 - rho)
    return e / np.pi * np.exp(-(kd if camera == "kd" else s) * CAM_HEIGHT)


def to_xyz(lam, values) -> np.ndarray:
    import colour

    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        return np.asarray(colour.sd_to_XYZ(
            colour.SpectralDistribution(np.asarray(values), np.asarray(lam)),
            colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
            colour.SDS_ILLUMINANTS["D65"]), np.float64) / 100.0


def target_xyz(name: str, depth: float, **kw) -> np.ndarray:
    return to_xyz(grid(), floor_radiance(name, depth, **kw))


def delta_e(xyz1, xyz2) -> float:
    """CIEDE2000 between two XYZ (white: D65 with Y = 1, the sky)."""
    from jaxvcm import delta_e2000

    return float(delta_e2000(np.asarray(xyz1)[None], np.asarray(xyz2)[None], "xyz")[0])
