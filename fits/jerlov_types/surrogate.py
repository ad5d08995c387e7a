"""Render-free surrogate of the rendered floor colour, for a starting point and diagnostics.

For NON-scattering water of attenuation sigma(lambda) the renderer's floor colour is exactly
the quadrature in targets.py (sky refracted in, all floor-surface round trips, camera path
exp(-sigma h)); tests/transport/test_spectral.py checks the renderer against it (dE2000 0.14). With
particle scattering we approximate sigma = a + b_b (the HG phase with g = 0.9
back-scatters 2.3% of b_p; forward-scattered light is counted as unscattered). A bounded
least-squares fit (scipy, trust-region reflective, log-space bounds) in CIELAB of the
WaterModel's terms through this surrogate gives
  * the rendered fit's starting point (run.py --init surrogate), and
  * what the model family can reach at best without render noise (analysis.py).
"""

from __future__ import annotations

import numpy as np

from . import targets as T

LO = {"a_cdom": 1e-6, "b_p": 1e-6, "a_flat": 1e-6, "S": 0.003}
HI = {"a_cdom": 20.0, "b_p": 20.0, "a_flat": 20.0, "S": 0.04}


def hg_backscatter_fraction(g: float) -> float:
    """b_b / b of a Henyey-Greenstein phase function."""
    return (1 - g) / (2 * g) * ((1 + g) / np.sqrt(1 + g * g) - 1)


def lab(xyz):
    import colour

    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return np.asarray(colour.XYZ_to_Lab(xyz, xy), np.float64)


def pure_floor(lam):
    """a_w + b_w / 2 (Pope & Fry, Zhang): the least attenuation the model can have."""
    from jaxvcm import pure_water_absorption, pure_water_scattering

    lam = np.asarray(lam, np.float64)
    return (np.asarray(pure_water_absorption(lam), np.float64)
            + 0.5 * np.asarray(pure_water_scattering(lam), np.float64))


def surrogate_xyz(sigma, d):
    lam = T.grid()
    e = T.QUAD.e_down(sigma, d)
    rho = T.QUAD.k_return(sigma, d) / np.pi
    return T.to_xyz(lam, e / (np.pi * (1 - rho)) * np.exp(-sigma * T.CAM_HEIGHT))


def model_sigma(w: dict, lam):
    """a + b_b of the WaterModel with leaves w (a_cdom, S, a_flat, b_p, n_p, g)."""
    a = w["a_cdom"] * np.exp(-w["S"] * (lam - 440.0)) + w["a_flat"]
    bb = hg_backscatter_fraction(w["g"]) * w["b_p"] * (lam / 550.0) ** (-w["n_p"])
    return pure_floor(lam) + a + bb


def surrogate_fit(name: str, depths, w0: dict, free, **target_kw) -> dict:
    """Fit `free` leaves (the others at w0) to the Jerlov-type targets through the surrogate."""
    from scipy.optimize import least_squares

    lam = T.grid()
    tx = [T.target_xyz(name, d, **target_kw) for d in depths]
    tl = np.stack([lab(x) for x in tx])
    free = list(free)

    def colours(th):
        w = dict(w0, **dict(zip(free, np.exp(th))))
        sig = model_sigma(w, lam)
        return [surrogate_xyz(sig, d) for d in depths]

    def res(th):
        return (np.stack([lab(x) for x in colours(th)]) - tl).ravel()

    sol = least_squares(res, np.log([w0[k] for k in free]), method="trf",
                        bounds=(np.log([LO[k] for k in free]), np.log([HI[k] for k in free])))
    fx = colours(sol.x)
    return {"params": {k: float(v) for k, v in zip(free, np.exp(sol.x))},
            "delta_e2000": [T.delta_e(a, b) for a, b in zip(fx, tx)]}
