"""Literature reference for fits/literature_pure_water (no renderer involved).

A white Lambertian floor (albedo 1) at depth d at the bottom of a wide, flat pool of pure
water under a uniform sky; a camera under water, H = 0.3 m above the floor, looks straight
down. Per wavelength, with sigma = a_w(lambda) (Pope & Fry 1997, the CSV shipped in
jaxvcm/data, read here with NumPy) and n = n(550 nm) = 1.33468 (Daimon & Masumura 2007, one
index for all wavelengths, as the renderer's default):

    R(lambda) = L_f(sigma, d) exp(-sigma H)           (radiance seen by the camera)
    L_f = (1/pi) E_sky / (1 - K / pi)                 (all internal round trips)
    E_sky = 2 pi int_0^theta_c n^2 (1 - F(theta)) e^(-sigma d / cos) cos sin dtheta
    K = 2 pi [int_0^theta_c F e^(-2 sigma d / cos) cos sin + int_theta_c^pi/2 e^(...) cos sin]

(theta: angle in the water; theta_c = asin(1/n); F: unpolarised Fresnel reflectance at the
surface seen from below; the sky's radiance 1 is refracted in with the n^2 radiance gain;
light going back up is reflected down by the surface, totally beyond theta_c, and the
white floor re-reflects it: a geometric series). This is the formula of
tests/transport/test_spectral.py::sky_floor_radiance with the series summed to infinity (the tests
truncate it to match a renderer's max_depth), vectorised with 400-point Gauss-Legendre
rules.

Scattering is NOT included (pure-water b_w is 0.002-0.005 /m; no closed form with the
surface's internal reflections): the reference is pure absorption, and the fits render
with `WaterModel(pure_scattering=False)` / sigma_s ~ 0 to match.

Colour: XYZ = colour.sd_to_XYZ(R on the Pope & Fry 5 nm grid 380-725 nm, CIE 1931 2 deg,
D65) / 100 (ASTM E308 integration; Y = 1 for R = 1 under a D65 sky of luminance 1), times
the sky radiance SKY = 1 / L_f(0): the sky is dimmed so that the floor seen through
absorption-free water (L_f(sigma = 0), the same at every depth) has Y = 1, i.e. L* = 100.
"""

from __future__ import annotations

import numpy as np

from jaxvcm import fresnel_unpolarised, sky_floor_radiance

N_WATER = 1.33468  # Daimon & Masumura n(550 nm), 20 C (jaxvcm's spectral default)
CAM_HEIGHT = 0.3  # m above the floor
DEPTHS = (0.5, 1.0, 2.0, 4.0)  # m


_fresnel = fresnel_unpolarised  # (bias_check.py uses it)


def floor_radiance(depth, sigma, n=N_WATER):
    """L_f [K] of the white floor for absorption sigma [K] (1/m), sky radiance 1: the
    round trips between floor and surface summed to infinity."""
    return sky_floor_radiance(depth, sigma, n, 1.0, None)


def sky_radiance() -> float:
    """The sky's radiance that makes the floor through absorption-free water Y = 1."""
    return float(1.0 / floor_radiance(1.0, [0.0])[0])


def pope_fry():
    """(wavelength nm, a_w 1/m) read from the shipped CSV with NumPy."""
    import importlib.resources

    text = importlib.resources.files("jaxvcm").joinpath(
        "data", "water_absorption_pope_fry_1997.csv").read_text()
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")][1:]
    r = np.array([[float(v) for v in ln.split(",")] for ln in rows])
    return r[:, 0], r[:, 1]


def target_xyz(depth, absorption=None) -> np.ndarray:
    """CIE XYZ of the floor at `depth` (sky radiance `sky_radiance()`), colour-science.
    absorption: a_w on the Pope & Fry grid (default: Pope & Fry)."""
    import colour

    wl, a = pope_fry()
    if absorption is not None:
        a = np.asarray(absorption, np.float64)
    R = floor_radiance(depth, a) * np.exp(-a * CAM_HEIGHT) * sky_radiance()
    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        xyz = colour.sd_to_XYZ(colour.SpectralDistribution(R, wl),
                               colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
                               colour.SDS_ILLUMINANTS["D65"]) / 100.0
    return np.asarray(xyz, np.float64)


def target_lab(depth) -> np.ndarray:
    """CIELAB (D65 white, Y_n = 1) of `target_xyz(depth)`."""
    import colour

    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return np.asarray(colour.XYZ_to_Lab(target_xyz(depth), xy), np.float64)


def scene_dict(depth, sky, half=1000.0, size=8, fov=2.0):
    """jaxvcm scene dict (as tests/_scenes.flat_water_sky): the pool of `depth`, a sky of
    radiance `sky`, camera CAM_HEIGHT above the white floor looking down."""
    y = -depth + CAM_HEIGHT
    return {
        "name": f"white_floor_{depth:g}m",
        "camera": {"position": [0.0, y, 0.0], "target": [0.0, -depth - 1.0, 0.0],
                   "up": [0.0, 0.0, -1.0], "fov": fov, "width": size, "height": size},
        "materials": {"floor": {"type": "diffuse", "albedo": 1.0}},
        "shapes": [{"type": "rect", "center": [0.0, -depth, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [2 * half, 2 * half], "material": "floor"}],
        "water": {"level": 0.0, "sigma_a": 0.1, "sigma_s": 1e-6, "ior": N_WATER,
                  "footprint": [-half, half, -half, half], "floor": -depth - 0.01},
        "lights": [{"type": "sky", "radiance": sky}],
    }


if __name__ == "__main__":
    import colour

    print("sky radiance", sky_radiance())
    for d in DEPTHS:
        xyz = target_xyz(d)
        print(d, xyz, target_lab(d), colour.XYZ_to_xy(xyz))
