"""Path-depth truncation check: render a type's fitted water (result.json) at the fit's
max_depth and at a larger one with the same keys, and report dE2000 between them per depth.
Usage (from the repo root): python -m fits.jerlov_types.check_depth [TYPE] [DEPTH2]   (default I 24)
Appends to result.json["depth_checks"].
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from . import run  # (sets the compilation cache)
from . import targets as T

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    import jax

    from jaxvcm import Region, RenderConfig, spectral_region_colours_fn

    t = sys.argv[1] if len(sys.argv) > 1 else "I"
    d2 = int(sys.argv[2]) if len(sys.argv) > 2 else 24
    data = run.load()
    r = data["types"][t]
    ru = r["run"]
    sps = run.build(run.DEPTHS, ru["size"], ru["nw"], r["model"])
    W = ru["size"]
    regs = [Region(k, i, (0, 0, W, W), (0.0, 0.0, 0.0)) for i, k in enumerate(sps)]
    out = {}
    t0 = time.perf_counter()
    for D in (ru["max_depth"], d2):
        cfg = RenderConfig(algorithm="pt", max_depth=D, rr_depth=100)
        fn = spectral_region_colours_fn(list(sps.values()), regs, [], cfg, ru["passes"],
                                        ru["seed"])
        out[D] = np.asarray(jax.jit(lambda th: fn(th)[0])(np.zeros(0)), np.float64)
    de = [T.delta_e(a, b) for a, b in zip(out[ru["max_depth"]], out[d2])]
    tx = np.asarray(r["target_xyz"])
    rec = {"type": t, "max_depths": [ru["max_depth"], d2], "delta_e2000_between": de,
           "delta_e2000_vs_target": {str(D): [T.delta_e(a, b) for a, b in zip(out[D], tx)]
                                     for D in out},
           "seconds": round(time.perf_counter() - t0, 1)}
    print(json.dumps(rec))
    data = run.load()
    data.setdefault("depth_checks", []).append(rec)
    with open(run.RESULT, "w") as f:
        json.dump(data, f, indent=1)


if __name__ == "__main__":
    main()
