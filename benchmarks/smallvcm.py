"""SmallVCM's scene 0 at equal time: jaxvcm's error and paths per second against the figures
of SmallVCM, the C++ reference implementation by the VCM paper's authors.

The scene (`scenes/cornell_sun.toml`): SmallVCM's Cornell box with the small mirror and
glass spheres, lit by the sun through the open front, glossy floor. Both renderers run it
with the same settings: 256 x 256, max depth 10, the balance heuristic, a first merging
radius of 0.00665 m (SmallVCM's default, 0.003 of its scene sphere's radius; here a
fraction of `Scene.view_radius`) reduced with alpha = 0.75, one camera and one light path
per pixel and pass. SmallVCM's figures (`SMALLVCM`) were measured on the 2-core machine
these benchmarks run on, with 2 threads at a load of 3-4: RMSE over pixels and channels
against its own 4,441-iteration VCM reference after 10 / 30 / 90 s, and camera + light
paths per second (camera paths only for PT). jaxvcm's long VCM render of the scene equals
SmallVCM's reference within noise (whole-image ratio 0.9994 +- 0.0027 R, 0.9996 +- 0.0012
G; `docs/benchmarks.md`), so a long jaxvcm VCM reference serves here; its own noise, from
its even and odd passes, is taken out of each RMSE in quadrature (`rmse_corrected`).
SmallVCM's reference is not noise-free either: at 90 s its VCM has done about a twelfth of
its reference's iterations, which puts about 4 % of its 90 s RMSE on the reference's noise,
less at shorter times; its figures are used as measured.

`jaxvcm bench --smallvcm [--reference-time S] [--algorithms ...]` writes the section
'SmallVCM scene 0: equal time' of docs/benchmarks.md; the targets: RMSE ratio
jaxvcm / SmallVCM at most 1 at 30 and 90 s for VCM, BPM and PPM, and paths per second
within 2x of SmallVCM's for every algorithm.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

import jaxvcm

SCENE = "scenes/cornell_sun.toml"
SIZE = 256
MAX_DEPTH = 10
RADIUS_M = 0.00665  # SmallVCM's first radius: 0.003 x its scene sphere's radius
ALPHA = 0.75
MIS = "balance"
BUDGETS = (10.0, 30.0, 90.0)
DEFAULT_ALGORITHMS = ["pt", "bdpt", "ppm", "bpm", "vcm"]
REFERENCE_ALGORITHM = "vcm"
DEFAULT_REFERENCE_TIME = 600.0
TAG = "smallvcm"

# SmallVCM on the 2-core machine (2 threads, load 3-4), the same settings: RMSE against its
# 4,441-iteration VCM reference at 10 / 30 / 90 s, and paths per second (camera + light;
# PT: camera paths).
SMALLVCM = {
    "vcm": {"rmse": (0.0954, 0.0489, 0.0322), "paths_per_s": 532e3},
    "ppm": {"rmse": (0.1716, 0.0884, 0.0570), "paths_per_s": 2.4e6},
    "bpm": {"rmse": (0.1966, 0.1249, 0.0796), "paths_per_s": 950e3},
    "bdpt": {"rmse": (0.1211, 0.1132, 0.1095), "paths_per_s": 710e3},
    "pt": {"rmse": (0.1240, 0.1229, 0.1215), "paths_per_s": 806e3},
}
TARGET_RMSE_ALGORITHMS = ("vcm", "bpm", "ppm")  # RMSE ratio <= 1 at 30 and 90 s
TARGET_PATHS_RATIO = 2.0  # SmallVCM's paths/s over jaxvcm's at most this


def config(alg: str, scene) -> jaxvcm.RenderConfig:
    """The run's configuration of `alg`: SmallVCM's settings (module doc)."""
    from .bench import render_config
    return render_config(alg, max_depth=MAX_DEPTH, mis=MIS, alpha=ALPHA,
                         radius=RADIUS_M / float(scene.view_radius))


def rmse_corrected(rmse: float, ref_noise: float) -> float:
    """The RMSE against a noise-free reference: measured MSE = true MSE + the reference's
    own noise squared (independent samples), so sqrt(max(rmse^2 - noise^2, 0))."""
    return math.sqrt(max(rmse * rmse - ref_noise * ref_noise, 0.0))


def rows_for(alg: str, runs: list[dict], ref: np.ndarray, ref_noise: float) -> list[dict]:
    """One row per budget: passes, seconds, paths/s, RMSE (raw and without the
    reference's noise) and the ratios to SmallVCM's figures."""
    theirs = SMALLVCM.get(alg.partition("+")[0])
    out = []
    for k, r in enumerate(runs):
        d = r["image"] - ref
        rmse = float(np.sqrt(np.mean(d * d)))
        rc = rmse_corrected(rmse, ref_noise)
        paths = r["camera_paths"] + (r["light_paths"] or 0)
        pps = paths / r["seconds"]
        row = {"algorithm": alg, "budget": r["budget"], "passes": r["passes"],
               "seconds": r["seconds"], "paths_per_s": pps, "rmse": rmse,
               "rmse_corrected": rc, "over_budget": r["over_budget"]}
        if theirs is not None and k < len(theirs["rmse"]) and r["budget"] == BUDGETS[k]:
            row["smallvcm_rmse"] = theirs["rmse"][k]
            row["rmse_ratio"] = rc / theirs["rmse"][k]
            row["smallvcm_paths_per_s"] = theirs["paths_per_s"]
            row["paths_ratio"] = theirs["paths_per_s"] / pps
        out.append(row)
    return out


def run_smallvcm(a, argv, log) -> dict:
    """`jaxvcm bench --smallvcm`: the reference (stored and reused), then every algorithm
    for the budgets, one after the other in one process."""
    from . import _common as C
    from . import bench as B
    path = B.repo_root() / SCENE
    size = 32 if a.quick else SIZE
    budgets = (1.0, 2.0, 4.0) if a.quick else BUDGETS
    scene = jaxvcm.load_scene(path, width=size, height=size)
    ref_cfg = config(REFERENCE_ALGORITHM, scene)
    a.max_depth = MAX_DEPTH
    ref, meta, reused = B._get_reference(a, path, scene, f"{path.stem}_smallvcm", B._sha256(path), log,
                                         config=ref_cfg)
    noise = float(meta["noise_rmse"])
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "size": size, "max_depth": MAX_DEPTH, "radius_m": RADIUS_M, "alpha": ALPHA,
           "mis": MIS, "budgets": list(budgets),
           "reference": {**{k: meta.get(k) for k in ("passes", "seconds", "seed", "mean")},
                         "noise_rmse": noise, "reused": reused},
           "rows": []}
    for alg in a.algorithms:
        cfg = config(alg, scene)
        tw = B._warm_up(scene, cfg, a.seed)
        t0 = time.perf_counter()
        runs = B._budget_run(scene, cfg, a.seed, budgets)
        log(f"smallvcm {alg}: warm-up {tw:.1f} s, {runs[-1]['passes']} passes in "
            f"{time.perf_counter() - t0:.0f} s")
        for row in rows_for(alg, runs, ref, noise):
            row["warm_up_s"] = tw
            res["rows"].append(row)
    C.publish(Path(a.out), TAG, res, markdown(res), log)
    return res


def _f(x, fmt):
    return "–" if x is None or not math.isfinite(x) else format(x, fmt)


def markdown(res: dict) -> str:
    from . import _common as C
    ref = res["reference"]
    L = C.section_head("SmallVCM scene 0: equal time", res) + [
        f"- `{SCENE}` at {res['size']}x{res['size']}, max depth {res['max_depth']}, "
        f"{res['mis']} heuristic, first radius {res['radius_m']:g} m, alpha "
        f"{res['alpha']:g}: SmallVCM's settings (`benchmarks/smallvcm.py`). Each algorithm "
        "renders after a warm-up pass (the compilation: its seconds in the last column); a "
        "row is the image after the last pass within the budget. RMSE over pixels and "
        f"channels against a jaxvcm VCM reference ({ref['passes']} passes, "
        f"{_f(ref['seconds'], '.0f')} s, noise RMSE {ref['noise_rmse']:.4g}), then without "
        "the reference's noise (in quadrature); SmallVCM's RMSE and paths/s are its figures "
        "measured on the same machine (2 threads), against its own long reference. Ratios: "
        "RMSE jaxvcm / SmallVCM (target <= 1 at 30 and 90 s for VCM, BPM and PPM), paths/s "
        f"SmallVCM / jaxvcm (target <= {TARGET_PATHS_RATIO:g}).", "",
        "| algorithm | budget s | passes | paths/s | RMSE | RMSE w/o ref. noise | SmallVCM "
        "RMSE | RMSE ratio | SmallVCM paths/s | paths/s ratio | warm-up s |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        star = "*" if r["over_budget"] else ""
        L.append(f"| {r['algorithm']} | {r['budget']:g}{star} | {r['passes']} | "
                 f"{r['paths_per_s']:,.0f} | {r['rmse']:.4f} | {r['rmse_corrected']:.4f} | "
                 f"{_f(r.get('smallvcm_rmse'), '.4f')} | {_f(r.get('rmse_ratio'), '.2f')} | "
                 f"{_f(r.get('smallvcm_paths_per_s'), ',.0f')} | "
                 f"{_f(r.get('paths_ratio'), '.2f')} | {r['warm_up_s']:.1f} |")
    L += ["", "- Targets: " + verdict(res["rows"]), ""]
    return "\n".join(L) + "\n"


def verdict(rows: list[dict]) -> str:
    """One line: which targets the run meets."""
    met, missed = [], []
    for r in rows:
        if "rmse_ratio" not in r:
            continue
        alg = r["algorithm"]
        if alg in TARGET_RMSE_ALGORITHMS and r["budget"] in (30.0, 90.0):
            (met if r["rmse_ratio"] <= 1.0 else missed).append(
                f"{alg} RMSE at {r['budget']:g} s ({r['rmse_ratio']:.2f})")
        if r["budget"] == BUDGETS[-1]:
            (met if r["paths_ratio"] <= TARGET_PATHS_RATIO else missed).append(
                f"{alg} paths/s ({r['paths_ratio']:.2f}x)")
    if not met and not missed:
        return "no row at SmallVCM's budgets (a --quick run)."
    return (f"met: {', '.join(met) or 'none'}; missed: {', '.join(missed) or 'none'}.")
