"""Seconds per forward evaluation and per Jacobian evaluation of the recovery fit's model
(the 5 regions of fit.toml, 2 scenes x 16 passes x 24x24, PT max_depth 4), after
compilation; median of 5. Usage (from the repo root): python -m fits.recover_rgb.bench"""

from __future__ import annotations

import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxvcm import Region, load_fit_config, region_colours_fn

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    kw = load_fit_config(os.path.join(HERE, "fit.toml"))
    names = list(kw["scenes"])
    regs = [Region(r.name, names.index(r.scene), r.rect, r.target) for r in kw["regions"]]
    fn = region_colours_fn([kw["scenes"][k] for k in names], regs, kw["config"], kw["passes"],
                           kw["seed"])
    theta = jnp.log(jnp.asarray(np.concatenate([kw["init_sigma_a"], kw["init_sigma_s"]]),
                                jnp.float32))
    fwd = jax.jit(lambda t: fn(t)[0])
    jac = jax.jit(jax.jacfwd(lambda t: fn(t)[0]))
    out = {}
    for name, f in (("forward", fwd), ("jacobian (jacfwd, 6 tangents)", jac)):
        t0 = time.perf_counter()
        jax.block_until_ready(f(theta))
        comp = time.perf_counter() - t0
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            jax.block_until_ready(f(theta))
            ts.append(time.perf_counter() - t0)
        out[name] = (comp, float(np.median(ts)))
        print(f"{name}: first call (compile + run) {comp:.1f} s, then median {np.median(ts):.3f} s")
    return out


if __name__ == "__main__":
    main()
