"""Robustness to caustic noise (issue 5): region averages vs a per-pixel L2 loss.

scenes/pool.toml: the floor seen from above the water is lit only through the refracting
surface by a small bright area light (a specular-diffuse-specular path). Path tracing
reaches it only by BSDF-sampled paths that happen to hit the light (at 24x24 and 16 passes
PT renders the floor black: no path hits it), so the fits use VCM (`algorithm = "vcm"`):
merging renders the caustics, and the PT-hit technique, weighted by MIS, still leaves
fireflies. The target is a 64-pass render at the true coefficients with
keys independent of the fit's (seed 1000 vs 0); both fits adjust ln sigma_a (3 parameters,
sigma_s fixed at the truth) from a perturbed start with 16 passes at 24x24:

  regions: the mean colour of four 6x6 floor blocks (uncertainty 1% of the target)
  pixels:  every pixel of the same 12x12 block is its own target (uncertainty 0.01
           absolute: a plain image L2)

Why the per-pixel loss drifts: with fixed keys the rendered pixel is n_p g_p(theta),
n_p a mean-1 noise factor; the least-squares solution of sum_p (n_p g - t_p)^2 scales g by
sum n_p t_p / sum n_p^2 ~ 1 / (1 + var(n)): fireflies (huge var(n)) make the fit darken
the water, i.e. overestimate sigma_a. A region average has var(n) ~ var / (pixels x passes).

Writes result.json and robustness.png here. Usage: python fits/caustic_robustness/run.py
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, ROOT)

import jaxvcm  # noqa: E402
from jaxvcm import RenderConfig  # noqa: E402
from jaxvcm._fit import Region  # noqa: E402

W = 24
BLOCK = (6, 6, 18, 18)  # x0, y0, x1, y1: floor seen through the water
TARGET_PASSES, TARGET_SEED = 64, 1000
PASSES, SEED = 16, 0
INIT_SA = [0.3, 0.1, 0.03]


def main():
    t00 = time.perf_counter()
    scene = jaxvcm.load_scene(os.path.join(ROOT, "scenes", "pool.toml"), width=W, height=W)
    cfg = RenderConfig(algorithm="vcm", max_depth=4, rr_depth=100)
    truth_a = np.asarray(scene.water.sigma_a, np.float64)
    truth_s = np.asarray(scene.water.sigma_s, np.float64)
    rp = jax.jit(jaxvcm.render_pass, static_argnums=2)
    acc = np.zeros((W, W, 3))
    for i in range(TARGET_PASSES):
        acc += np.asarray(rp(scene, jaxvcm.pass_key(TARGET_SEED, i), cfg)[0], np.float64)
    target = acc / TARGET_PASSES
    x0, y0, x1, y1 = BLOCK
    blk = target[y0:y1, x0:x1]
    print(f"target: {time.perf_counter() - t00:.1f} s; block mean {blk.mean((0, 1))}, "
          f"max pixel/mean {blk.max() / blk.mean():.1f}")
    quads = []
    for qy in (y0, (y0 + y1) // 2):
        for qx in (x0, (x0 + x1) // 2):
            r = (qx, qy, qx + (x1 - x0) // 2, qy + (y1 - y0) // 2)
            quads.append(Region(f"q{len(quads)}", 0, r,
                                tuple(target[r[1]:r[3], r[0]:r[2]].mean((0, 1)))))
    pixels = [Region(f"p{y}_{x}", 0, (x, y, x + 1, y + 1), tuple(target[y, x]), (0.01,) * 3)
              for y in range(y0, y1) for x in range(x0, x1)]
    out = {"truth": {"sigma_a": truth_a.tolist(), "sigma_s": truth_s.tolist()},
           "init_sigma_a": INIT_SA, "target": {"passes": TARGET_PASSES, "seed": TARGET_SEED},
           "fit": {"passes": PASSES, "seed": SEED, "size": W, "block": BLOCK}}
    for name, regs in (("regions", quads), ("pixels", pixels)):
        res = jaxvcm.fit(scene, regs, config=cfg, passes=PASSES, seed=SEED, init_sigma_a=INIT_SA,
                         init_sigma_s=truth_s, free="sigma_a", max_steps=30, rtol=1e-3, atol=1e-3)
        err = res.sigma_a / truth_a - 1
        print(f"{name}: sigma_a {res.sigma_a} (rel. error {err}), {res.iterations} steps, "
              f"{res.wall_seconds:.1f} s")
        out[name] = {"sigma_a": res.sigma_a.tolist(), "sigma_a_sd": res.sigma_a_sd.tolist(),
                     "rel_error": err.tolist(), "iterations": res.iterations,
                     "result": res.result, "wall_seconds": round(res.wall_seconds, 1),
                     "history": [h["loss"] for h in res.history],
                     "n_residuals": int(res.residuals.size)}
    with open(os.path.join(HERE, "result.json"), "w") as f:
        json.dump(out, f, indent=1)
    plot(out, target)
    print(f"total {time.perf_counter() - t00:.1f} s")


def plot(out, target):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4))
    x0, y0, x1, y1 = BLOCK
    a0.imshow(np.clip(target / np.percentile(target, 99), 0, 1) ** (1 / 2.2),
              interpolation="nearest")
    a0.add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, ec="r"))
    a0.set_title(f"target ({out['target']['passes']} VCM passes), fitted block in red",
                 fontsize=9)
    a0.axis("off")
    t = np.asarray(out["truth"]["sigma_a"])
    w = 0.35
    for k, (name, col) in enumerate((("regions", "C0"), ("pixels", "C3"))):
        e = 100 * np.asarray(out[name]["rel_error"])
        sd = 100 * np.asarray(out[name]["sigma_a_sd"]) / t
        a1.bar(np.arange(3) + (k - 0.5) * w, e, w, yerr=sd, color=col,
               label=f"{name} ({out[name]['n_residuals']} residuals)")
    a1.axhline(0, color="k", lw=0.8)
    a1.set_xticks(range(3), ["sigma_a R", "sigma_a G", "sigma_a B"])
    a1.set_ylabel("fitted / truth - 1 (%)")
    a1.legend(fontsize=8)
    a1.set_title("caustic noise: region averages vs per-pixel L2", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "robustness.png"), dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
