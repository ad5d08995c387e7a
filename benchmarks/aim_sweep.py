"""Scale sweep of issue 13: the same flat sunlit pool at widths 2, 20 and 120 m, the same
camera (3 m above the centre, looking straight down, 2 degree field of view, 8 x 8
pixels), purely absorbing water 1.2 m deep, black walls, the sun 14 degrees from the
zenith. The camera sees only the refracted sun on the floor (light -> surface -> floor ->
surface -> camera: merging alone can render it), whose value is known in closed form
(tests/test_merge.py: E[L] = T0 / eta^2 e^{-sigma_a d} L_f, L_f = a / pi E cos_i T(i)
e^{-sigma_a d / cos_t}; max depth 4 keeps only that path). VCM and PPM render it for the
same wall time in two modes:

  bounds  today's emission (photons over the scene's bounding disk) and merge radius
          (RenderConfig's default fraction of the bounding radius);
  view    aim = 0.9 at the water's footprint, the footprint map from a pilot pass of
          camera paths and the first-pass radius from the pixel footprint
          (`jaxvcm.aim_at_view`).

Reported per (width, algorithm, mode): passes, seconds, and the relative error of the
image mean and the relative RMSE over pixels and channels against the closed form.
`python -m benchmarks.aim_sweep [--seconds S] [--out docs/benchmarks_aim-sweep.json]`.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._materials import fresnel_dielectric
from jaxvcm._render import render_pass_host

DEPTH, ALBEDO, ETA, E = 1.2, 0.7, 1.33, 3.0
SIGMA_A = (0.3, 0.1, 0.05)
THETA = math.radians(14.0)
SUN = (-math.sin(THETA), -math.cos(THETA), 0.0)
WIDTHS = (2.0, 20.0, 120.0)


def pool(width: float, aim: float = 0.0) -> dict:
    h = 0.5 * width
    black = {"type": "diffuse", "albedo": 0.0}
    return {
        "camera": {"position": [0.0, 3.0, 0.0], "target": [0.0, -1.0, 0.0],
                   "up": [0.0, 0.0, -1.0], "fov": 2.0, "width": 8, "height": 8},
        "materials": {"floor": {"type": "diffuse", "albedo": ALBEDO}, "wall": black},
        "shapes": [{"type": "basin", "min": [-h, -DEPTH, -h], "max": [h, 0.0, h],
                    "floor_material": "floor", "wall_material": "wall"}],
        "water": {"level": 0.0, "sigma_a": list(SIGMA_A), "sigma_s": 0.0, "ior": ETA},
        "lights": [{"type": "sun", "direction": list(SUN), "irradiance": E, "aim": aim}],
    }


def expected() -> np.ndarray:
    cos_i = -SUN[1]
    T = 1.0 - float(fresnel_dielectric(cos_i, ETA)[0])
    cos_t = math.sqrt(1 - (1 - cos_i**2) / ETA**2)
    sa = np.asarray(SIGMA_A)
    L_f = ALBEDO / math.pi * E * cos_i * T * np.exp(-sa * DEPTH / cos_t)
    T0 = 1 - ((ETA - 1) / (ETA + 1)) ** 2
    return T0 / ETA**2 * np.exp(-sa * DEPTH) * L_f


def run(width: float, alg: str, mode: str, seconds: float, seed: int = 0) -> dict:
    if mode == "view":
        scene = jaxvcm.scene_from_dict(pool(width, 0.9))
        scene, cfg, guide = jaxvcm.aim_at_view(scene, RenderConfig(algorithm=alg, max_depth=4))
        extra = {"radius": cfg.radius, "footprint_m": guide.footprint,
                 "aimed_cells": int((guide.aim_map > 0).sum())}
    else:
        scene = jaxvcm.scene_from_dict(pool(width))
        cfg = RenderConfig(algorithm=alg, max_depth=4)
        extra = {"radius": cfg.radius}
    img, _, cfg = render_pass_host(scene, jaxvcm.pass_key(seed, 0), cfg, 0)  # compile
    total = np.zeros_like(np.asarray(img, np.float64))
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        img, diag, cfg = render_pass_host(scene, jaxvcm.pass_key(seed, n + 1), cfg, n + 1)
        total += np.asarray(img, np.float64)
        n += 1
    dt = time.perf_counter() - t0
    mean = total / n
    ref = expected()
    rel_mean = float(np.max(np.abs(mean.mean(axis=(0, 1)) / ref - 1.0)))
    rel_rmse = float(np.sqrt(np.mean((mean / ref - 1.0) ** 2)))
    return {"width": width, "algorithm": alg, "mode": mode, "passes": n, "seconds": dt,
            "rel_error_mean": rel_mean, "rel_rmse": rel_rmse, **extra}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.aim_sweep")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--algorithms", nargs="+", default=["vcm", "ppm"])
    ap.add_argument("--widths", nargs="+", type=float, default=list(WIDTHS))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    rows = []
    for w in a.widths:
        for alg in a.algorithms:
            for mode in ("bounds", "view"):
                r = run(w, alg, mode, a.seconds)
                rows.append(r)
                print(f"{w:6.0f} m  {alg:4s} {mode:6s} passes {r['passes']:6d}  "
                      f"rel.err(mean) {r['rel_error_mean']:.3f}  relRMSE {r['rel_rmse']:.3f}  "
                      f"radius {r['radius']:.2e}", flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"seconds": a.seconds, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
