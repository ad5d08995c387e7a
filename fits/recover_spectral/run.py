"""Spectral recovery (a first step towards the issue's fits 2 and 3): recover the
`WaterModel`'s CDOM absorption a_cdom (1/m at 440 nm) and particle scattering b_p (1/m at
550 nm) from spectral renders made with them, fitted in CIE XYZ.

Scenes: pool_sky (24x24) and the same pool with a black floor (albedo 0.02), both upsampled
with `spectral_scene` (4 hero wavelengths per pass). Truth a_cdom = 0.05, b_p = 0.1
(n_p = 1, HG g = 0.9, pure-water absorption and scattering underneath); start a_cdom =
0.1, b_p = 0.05. Targets are rendered with the same keys as the fit (common random
numbers, wavelengths included), as in fits/recover_rgb. Writes fit.json here.
Usage (from the repo root): python -m fits.recover_spectral.run
"""

from __future__ import annotations

import json
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm import (Region, RenderConfig, WaterModel, fit_spectral,
                    spectral_region_colours_fn)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))

TRUTH = {"a_cdom": 0.05, "b_p": 0.1}
INIT = {"a_cdom": 0.1, "b_p": 0.05}
RECTS = [("near_floor", 0, (6, 14, 18, 20)), ("far_floor", 0, (6, 5, 18, 9)),
         ("left_wall", 0, (2, 8, 4, 18)), ("deep_near", 1, (6, 14, 18, 20)),
         ("deep_far", 1, (6, 5, 18, 9))]
PASSES, SEED, NW = 16, 3, 4


def main():
    t0 = time.perf_counter()
    s = jaxvcm.load_scene(os.path.join(ROOT, "scenes", "pool_sky.toml"), width=24, height=24)
    dark = eqx.tree_at(lambda x: x.materials.albedo, s, s.materials.albedo.at[0].set(0.02))
    model = WaterModel(b_p=TRUTH["b_p"], a_cdom=TRUTH["a_cdom"], n_p=1.0, g=0.9)
    sps = {"pool": jaxvcm.spectral_scene(s, model, n_wavelengths=NW),
           "black_floor": jaxvcm.spectral_scene(dark, model, n_wavelengths=NW)}
    cfg = RenderConfig(algorithm="pt", max_depth=4, rr_depth=100)
    names = ["a_cdom", "b_p"]
    regs0 = [Region(n, i, r, (0.0, 0.0, 0.0)) for n, i, r in RECTS]
    fn = spectral_region_colours_fn(list(sps.values()), regs0, names, cfg, PASSES, SEED)
    theta = jnp.log(jnp.asarray([TRUTH[k] for k in names], jnp.float32))
    xyz = np.asarray(jax.jit(fn)(theta)[0], np.float64)
    print(f"targets (XYZ) in {time.perf_counter() - t0:.1f} s:\n{xyz}")
    regs = [Region(n, list(sps)[i], r, tuple(xyz[k])) for k, (n, i, r) in enumerate(RECTS)]
    res = fit_spectral(sps, regs, names, space="xyz", init=INIT, config=cfg, passes=PASSES,
                       seed=SEED, max_steps=30, truth=TRUTH)
    d = res.to_dict()
    d["targets_seconds"] = round(time.perf_counter() - t0 - res.wall_seconds, 1)
    with open(os.path.join(HERE, "fit.json"), "w") as f:
        json.dump(d, f, indent=1)
    print(json.dumps({k: d[k] for k in ("params", "params_sd", "rel_error", "iterations",
                                        "result", "wall_seconds")}, indent=1))
    print("dE2000 max", float(np.max(res.delta_e2000)), "initial max",
          float(np.max(res.delta_e2000_initial)))


if __name__ == "__main__":
    main()
