"""How much of fits/literature_pure_water's residual error is Monte Carlo error: repeat the
two fits with other seeds (other fixed keys) and more passes, and render the spectral
model at the literature answer (a_w_scale = 1, a_cdom = a_flat = 0) with the fit's keys:
its dE2000 to the targets is the renderer's error at these settings (noise + the 0.03 dE
truncation of the internal round trips), the floor below which no fit can be trusted.
Writes noise_check.json here (appends one entry per run).
Usage (from the repo root): python -m fits.literature_pure_water.noise_check spectral:1:32 spectral:2:32 rgb:2:32
       (mode:seed:passes ...)
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxvcm import (Region, delta_e2000, enable_compilation_cache, fit, fit_spectral,
                    load_fit_config, spectral_region_colours_fn)

HERE = os.path.dirname(os.path.abspath(__file__))

OUT = os.path.join(HERE, "noise_check.json")


def truth_de(kw, seed, passes):
    """dE2000 per region of the spectral model at the literature answer, fit's keys."""
    names = list(kw["spectral"])
    regs = [Region(r.name, names.index(r.scene), r.rect, r.target) for r in kw["regions"]]
    params = kw["params"]
    theta = jnp.asarray([kw["truth"][p] if p in kw["linear"] else np.log(kw["truth"][p])
                         for p in params], jnp.float32)
    fn = spectral_region_colours_fn(list(kw["spectral"].values()), regs, params, kw["config"],
                                    passes, seed, kw["linear"])
    xyz = np.asarray(jax.jit(fn)(theta)[0], np.float64)
    import colour

    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab = colour.XYZ_to_Lab(xyz, xy)
    tg = np.array([r.target for r in kw["regions"]])
    return delta_e2000(tg, lab, "lab").tolist(), xyz.tolist()


def main(argv):
    enable_compilation_cache()
    done = json.load(open(OUT)) if os.path.exists(OUT) else []
    for spec in argv:
        mode, seed, passes = spec.split(":")
        seed, passes = int(seed), int(passes)
        t0 = time.perf_counter()
        kw = load_fit_config(os.path.join(HERE, f"{mode}.toml"))
        kw.pop("mode", None)
        kw.update(seed=seed, passes=passes)
        entry = {"mode": mode, "seed": seed, "passes": passes}
        if mode == "spectral":
            res = fit_spectral(**kw)
            entry.update(params=res.params, params_sd=res.params_sd)
            t1 = time.perf_counter()
            entry["truth_delta_e2000"], entry["truth_xyz"] = truth_de(kw, seed, passes)
            entry["truth_render_seconds"] = round(time.perf_counter() - t1, 1)
        else:
            res = fit(**kw)
            entry.update(sigma_a=res.sigma_a.tolist(), sigma_a_sd=res.sigma_a_sd.tolist())
        entry.update(delta_e2000=res.delta_e2000.tolist(), iterations=res.iterations,
                     result=res.result, fit_seconds=round(res.wall_seconds, 1),
                     seconds=round(time.perf_counter() - t0, 1))
        entry = json.loads(json.dumps(entry, default=float))
        print(json.dumps(entry), flush=True)
        done.append(entry)
        with open(OUT, "w") as f:
            json.dump(done, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
