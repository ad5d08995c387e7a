"""Noise-free versions of the two fits of fits/literature_pure_water, without the renderer.

The renderer's expectation for these scenes is the reference quadrature (reference.py)
evaluated on the renderer's own spectral tables: the sky spectrum upsampled by
jaxvcm.spectral_scene (D65 times Mallett's white, scaled to the sky's luminance), the
floor's reflectance (Mallett's white, 1 to 1e-5), Pope & Fry interpolated linearly on the
1 nm grid 380-720 nm, and the film's CIE 1931 2 deg tables (trapezoidal XYZ integral); RGB
mode is the same per linear-sRGB channel (sigma_c, sky 1 per channel). Least squares
(scipy) in CIELAB, as the rendered fits. What this separates:

* the integration differences between the renderer and colour-science's ASTM E308
  (renderer at the truth vs the targets: dE2000 <= 0.016);
* the best any 3-channel RGB model can do (no Monte Carlo error);
* what the spectral fit recovers without Monte Carlo error.

Writes expected.json here. Usage (from the repo root): python -m fits.literature_pure_water.expected_fit
"""

from __future__ import annotations

import json
import os

import colour
import numpy as np
from scipy.optimize import least_squares

from jaxvcm import cmf_table, pope_fry_table, upsample_emission, upsample_reflectance

from . import reference as R

HERE = os.path.dirname(os.path.abspath(__file__))

XY = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]


def lab(xyz):
    return colour.XYZ_to_Lab(xyz, XY)


def de(a, b):
    return colour.delta_E(a, b, method="CIE 2000")


def main():
    grid, cmf = cmf_table()
    sky = R.sky_radiance()
    Le = upsample_emission([sky] * 3) * upsample_reflectance([1.0] * 3)
    wl, aw = pope_fry_table()
    a_grid = np.interp(grid, wl, aw)
    targets = np.array([R.target_lab(d) for d in R.DEPTHS])

    def spectral_xyz(p):
        s, ac, af = p
        sig = np.maximum(s * a_grid + ac * np.exp(-0.015 * (grid - 440.0)) + af, 0.0)
        return np.array([np.trapezoid((Le * R.floor_radiance(d, sig)
                                       * np.exp(-sig * R.CAM_HEIGHT))[:, None] * cmf, grid, axis=0)
                         for d in R.DEPTHS])

    M = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ)

    def rgb_xyz(sig):
        return np.array([(sky * R.floor_radiance(d, sig) * np.exp(-np.asarray(sig)
                                                                   * R.CAM_HEIGHT)) @ M.T
                         for d in R.DEPTHS])

    out = {}
    x1 = spectral_xyz([1.0, 0.0, 0.0])
    out["renderer_expectation_at_truth_delta_e2000"] = de(lab(x1), targets).tolist()
    r = least_squares(lambda p: (lab(spectral_xyz(p)) - targets).ravel(), [2.0, 0.1, 0.05])
    out["spectral"] = {"params": dict(zip(("a_w_scale", "a_cdom", "a_flat"), r.x.tolist())),
                       "delta_e2000": de(lab(spectral_xyz(r.x)), targets).tolist(),
                       "start": [2.0, 0.1, 0.05]}
    r = least_squares(lambda t: (lab(rgb_xyz(np.exp(t))) - targets).ravel(),
                      np.log([0.1, 0.1, 0.1]))
    out["rgb"] = {"sigma_a": np.exp(r.x).tolist(),
                  "delta_e2000": de(lab(rgb_xyz(np.exp(r.x))), targets).tolist()}
    per = {}
    for i, d in enumerate(R.DEPTHS):  # the RGB sigma_a that matches each depth on its own
        rr = least_squares(lambda t: lab(rgb_xyz(np.exp(t)))[i] - targets[i],
                           np.log([0.3, 0.05, 0.005]))
        per[f"{d:g}m"] = np.exp(rr.x).tolist()
    out["rgb_per_depth_sigma_a"] = per
    with open(os.path.join(HERE, "expected.json"), "w") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
