"""docs/caustics_reference.png: the sun caustics of scenes/pool_sun.toml (purely absorbing
water, black walls; the test scenes of tests/transport/test_caustics.py at a larger size) rendered
by VCM and BDPT against the float64 NumPy ray-mapping reference (tests/_caustic_ref.py),
seen from under the water and from above, plus the tile error of VCM vs passes.

    python -m docs.make_caustics_figure [--size 64] [--passes 128]   # from the repo root

Takes a few minutes on two cores (four compilations, then the passes). Also writes the
numbers to docs/caustics_reference.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
os.chdir(ROOT)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", os.path.join(ROOT, ".jax_cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

import numpy as np  # noqa: E402

import jaxvcm  # noqa: E402
from jaxvcm import RenderConfig  # noqa: E402
from tests import _caustic_ref as R  # noqa: E402
from tests.transport import test_caustics as TC  # noqa: E402


def rel_rms(img_tiles, ref_tiles):
    lit = ref_tiles > 0.05 * ref_tiles.mean()
    return float(np.sqrt(np.mean(((img_tiles - ref_tiles)[lit] / ref_tiles[lit]) ** 2)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--passes", type=int, default=128)
    ap.add_argument("--tile", type=int, default=0, help="tile side in pixels (default size/4)")
    ap.add_argument("--out", default="docs/caustics_reference.png")
    a = ap.parse_args()
    size, passes = a.size, a.passes
    tile = a.tile or size // 4

    pool = R.pool_from_dict(TC.scene_doc("under"))
    t0 = time.perf_counter()
    fm = R.floor_irradiance(pool, 3000, 600)
    t_fm = time.perf_counter() - t0
    checkpoints = [n for n in (2, 4, 8, 16, 32, 64, 128, 256, 512) if n <= passes]
    res = {}
    for view, v in TC.VIEWS.items():
        scene = jaxvcm.scene_from_dict(TC.scene_doc(view, size), view)
        cam = R.cam_from_dict(TC.camera(view, size))
        t0 = time.perf_counter()
        ref = v["render"](pool, fm, cam, ss=32)
        t_ref = time.perf_counter() - t0
        runs = {}
        for alg in ("vcm", "bdpt"):
            cfg = RenderConfig(algorithm=alg, max_depth=v["depth"], radius=TC.RADIUS)
            t0 = time.perf_counter()
            imgs = TC.render_passes(scene, cfg, passes, v["seed"] + (0 if alg == "vcm" else 1))
            runs[alg] = (imgs, time.perf_counter() - t0)
            print(f"{view} {alg}: {passes} passes at {size}x{size} in {runs[alg][1]:.1f} s "
                  f"(incl. compilation)", flush=True)
        imgs = runs["vcm"][0]
        rt = R.tiles(ref, tile)
        curve = []
        for n in checkpoints:
            blur = v["render"](pool, R.disk_blur(fm, TC.surface_radii(scene, TC.RADIUS, n)), cam,
                               ss=32)
            x = R.tiles(imgs[:n], tile)
            m, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(n)
            lit = rt > 0.05 * rt.mean()
            curve.append(dict(passes=n, rel_rms_vs_ref=rel_rms(m, rt),
                              rel_rms_vs_blurred=rel_rms(m, R.tiles(blur, tile)),
                              rel_rms_se=float(np.sqrt(np.mean((se[lit] / rt[lit]) ** 2))),
                              rel_rms_radius_bias=rel_rms(R.tiles(blur, tile), rt)))
        res[view] = dict(ref=ref, vcm=imgs.mean(0), bdpt=runs["bdpt"][0].mean(0), curve=curve,
                         seconds=dict(vcm=runs["vcm"][1], bdpt=runs["bdpt"][1], reference=t_ref),
                         bdpt_max=float(runs["bdpt"][0].mean(0).max()),
                         image_mean=dict(ref=ref.mean(axis=(0, 1)).tolist(),
                                         vcm=imgs.mean(axis=(0, 1, 2)).tolist(),
                                         bdpt=runs["bdpt"][0].mean(axis=(0, 1, 2)).tolist()))
    plot(res, size, passes, tile, a.out)
    meta = {view: {k: r[k] for k in ("curve", "seconds", "bdpt_max", "image_mean")}
            for view, r in res.items()}
    meta.update(size=size, passes=passes, tile=tile, radius=TC.RADIUS,
                floor_map=dict(rays=3000, bins=600, seconds=t_fm))
    with open(os.path.splitext(a.out)[0] + ".json", "w") as f:
        json.dump(meta, f, indent=1)
    print(json.dumps(meta, indent=1))


def plot(res, size, passes, tile, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(15, 7.4),
                             gridspec_kw=dict(width_ratios=[1, 1, 1, 1.25]))
    titles = {"under": "from under the water (max_depth 3)",
              "above": "from above the water (max_depth 4)"}
    for row, view in enumerate(("under", "above")):
        r = res[view]
        scale = np.percentile(r["ref"], 99.5)
        for col, (key, name) in enumerate((("ref", "float64 ray-mapping reference"),
                                           ("vcm", f"VCM, {passes} passes"),
                                           ("bdpt", f"BDPT, {passes} passes"))):
            ax = axes[row, col]
            img = np.clip(r[key] / scale, 0, 1) ** (1 / 2.2)
            ax.imshow(img, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            for k in range(1, size // tile):
                ax.axhline(k * tile - 0.5, color="w", lw=0.3, alpha=0.5)
                ax.axvline(k * tile - 0.5, color="w", lw=0.3, alpha=0.5)
            ax.set_title(name, fontsize=9)
            if col == 0:
                ax.set_ylabel(titles[view], fontsize=9)
        ax = axes[row, 3]
        c = r["curve"]
        n = np.array([x["passes"] for x in c])
        ax.loglog(n, [x["rel_rms_vs_ref"] for x in c], "o-", label="VCM vs reference")
        ax.loglog(n, [x["rel_rms_vs_blurred"] for x in c], "s--", ms=4,
                  label="VCM vs reference blurred by the merging disk")
        ax.loglog(n, [x["rel_rms_se"] for x in c], ":", color="k", label="standard error (passes)")
        ax.loglog(n, [max(x["rel_rms_radius_bias"], 1e-4) for x in c], "-.", color="gray",
                  label="radius bias (reference blurred vs sharp)")
        ax.set_xlabel("passes")
        ax.set_ylabel(f"rms relative tile error ({tile}x{tile} px tiles)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"pool_sun caustics (sigma_s = 0, black walls), {size}x{size}: VCM vs a float64 "
                 "ray-mapping reference; BDPT cannot render the floor seen from above", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=90)


if __name__ == "__main__":
    main()
