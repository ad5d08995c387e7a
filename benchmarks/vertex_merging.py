"""Two vertex-merging benchmark modes of `jaxvcm bench`:

- `--compare-mis`: seconds per pass of `mis_form="explicit"` vs `"recursive"` for each
  (scene, algorithm), the two forms interleaved pass by pass (A B A B ...) after both are
  compiled and warmed up, so that load from other processes hits both alike; medians per
  form, their ratio, and the largest relative pixel difference of the two images rendered
  from the same keys (the forms are meant to give the same weights).
- `--equal-time SEC`: every (scene, algorithm) rendered for the same wall-clock budget
  (compile excluded: one warm-up pass first), passes averaged on the host as `jaxvcm render`
  does; a grid PNG (rows scenes, columns algorithms, one exposure per row, sRGB via
  colour-science as the CLI preview) labelled with passes and seconds, plus a table of
  passes and paths/s per panel.

Each mode writes its markdown into its own `<!-- bench:TAG:begin/end -->` section of the
report (replaced in place if present, otherwise appended at the end; nothing else in the
file is touched) and its numbers into `<out stem>_<TAG>.json` next to it.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

import jaxvcm

from . import _common as C

MIS_DEFAULT_SCENES = ("pool.toml", "pool_sun.toml")
MIS_DEFAULT_ALGORITHMS = ("vcm", "bdpt")
MIS_DEFAULT_SIZE = 64
MIS_DEFAULT_PAIRS = 8
MIS_TARGET_RATIO = 1.25  # target: the explicit form within 1.25x of the recursive one
ET_DEFAULT_SCENES = ("pool.toml", "pool_sun.toml", "pool_wall.toml")
ET_DEFAULT_ALGORITHMS = ("pt", "bdpt", "ppm", "vcm")
ET_DEFAULT_SIZE = 128
ET_FIGURE = "equal_time.png"
VCM_TARGET_PATHS_PER_S = 1.14e6  # SmallVCM's measured paths/s on the 2-core machine


# ----------------------------------------------------------------------------- helpers
def _pass(scene, key, config, index):
    """One host pass (overflow re-runs with more room); returns (image, diag, config)."""
    img, diag, config = jaxvcm.render_pass_host(scene, key, config, index)
    return jax.block_until_ready(img), diag, config


def _total_paths(diag) -> int:
    return int(diag.camera_paths) + int(diag.light_paths)


# ----------------------------------------------------------------------------- MIS forms
def compare_mis(scene, config, seed: int, pairs: int) -> dict:
    """Interleaved timing of the explicit and recursive MIS forms of `config` on `scene`.
    Both are compiled and run once before timing; then pass i of both forms (same key, same
    pass index) alternates, the first form of each pair alternating too (A B, B A, ...)."""
    cfgs = {f: dataclasses.replace(config, mis_form=f) for f in ("explicit", "recursive")}
    warm = {}
    for f in cfgs:
        t0 = time.perf_counter()
        _, _, cfgs[f] = _pass(scene, jaxvcm.pass_key(seed, 0), cfgs[f], 0)
        warm[f] = time.perf_counter() - t0
    times = {f: [] for f in cfgs}
    acc = {f: None for f in cfgs}
    paths = 0
    order = list(cfgs)
    for i in range(pairs):
        for f in (order if i % 2 == 0 else order[::-1]):
            t0 = time.perf_counter()
            img, diag, cfgs[f] = _pass(scene, jaxvcm.pass_key(seed, i), cfgs[f], i)
            times[f].append(time.perf_counter() - t0)
            img = np.asarray(img, dtype=np.float64)
            acc[f] = img if acc[f] is None else acc[f] + img
            paths = _total_paths(diag)
    a, b = acc["explicit"] / pairs, acc["recursive"] / pairs
    scale = max(float(np.max(np.abs(b))), 1e-30)
    med = {f: float(np.median(t)) for f, t in times.items()}
    return {
        "warmup_s": warm, "times_s": times, "median_s": med,
        "ratio": med["explicit"] / med["recursive"],
        # per pixel, relative to the pixel's value (offset 1e-3 of the image's max)
        "max_rel_diff": float(np.max(np.abs(a - b) / (np.abs(b) + 1e-3 * scale))),
        "max_abs_diff_over_max": float(np.max(np.abs(a - b))) / scale,
        "mean_explicit": float(a.mean()), "mean_recursive": float(b.mean()),
        "paths_per_pass": paths,
    }


def run_compare_mis(a, argv, log) -> dict:
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "size": a.size, "max_depth": a.max_depth, "pairs": a.mis_pairs, "seed": a.seed,
           "rows": []}
    for path in a.scene_paths:
        scene = jaxvcm.load_scene(path, width=a.size, height=a.size)
        for alg in a.algorithms:
            cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=a.max_depth)
            log(f"mis forms: {path.stem} {alg} {a.size}x{a.size} d{a.max_depth}: "
                f"compiling both forms, then {a.mis_pairs} interleaved pairs")
            r = compare_mis(scene, cfg, a.seed, a.mis_pairs)
            r.update(scene=path.stem, algorithm=alg)
            res["rows"].append(r)
            log(f"  explicit {r['median_s']['explicit']:.3f} s, recursive "
                f"{r['median_s']['recursive']:.3f} s, ratio {r['ratio']:.3f}, "
                f"max rel diff {r['max_rel_diff']:.3g}")
    body = mis_markdown(res, C.machine_line(res["machine"]))
    C.upsert_section(a.out, "mis-forms", body)
    C.write_json(a.out.with_name(f"{a.out.stem}_mis-forms.json"), res)
    print(body)
    return res


def mis_markdown(res: dict, machine_line: str) -> str:
    L = ["## Explicit-sum vs recursive MIS: seconds per pass", "",
         f"- {machine_line}",
         f"- command: `{res['command']}`",
         f"- size {res['size']}x{res['size']}, max depth {res['max_depth']}, seed "
         f"{res['seed']}; both forms compiled and run once first, then {res['pairs']} pairs "
         "of passes interleaved (explicit, recursive / recursive, explicit / ...), the same "
         "key and pass index for both forms of a pair; each pass waited for. Ratio = median "
         f"explicit / median recursive (target: <= {MIS_TARGET_RATIO}).",
         "- image agreement over the averaged passes: max over pixels of |E - R| / (|R| + "
         "1e-3 max R), and max |E - R| / max R.", "",
         "| scene | algorithm | explicit median s | recursive median s | explicit/recursive |"
         " explicit min-max s | recursive min-max s | max rel diff | max abs diff / max |",
         "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        te, tr = r["times_s"]["explicit"], r["times_s"]["recursive"]
        L.append(f"| {r['scene']} | {r['algorithm']} | {r['median_s']['explicit']:.3f} | "
                 f"{r['median_s']['recursive']:.3f} | {r['ratio']:.3f} | "
                 f"{min(te):.3f}-{max(te):.3f} | {min(tr):.3f}-{max(tr):.3f} | "
                 f"{r['max_rel_diff']:.3g} | {r['max_abs_diff_over_max']:.3g} |")
    return "\n".join(L) + "\n"


# ----------------------------------------------------------------------------- equal time
def equal_time_render(scene, config, seed: int, budget: float) -> dict:
    """Average passes for `budget` wall seconds after a warm-up pass: a new pass starts only
    while the elapsed time plus the mean pass time so far fits the budget (>= 1 pass)."""
    t0 = time.perf_counter()
    _, _, config = _pass(scene, jaxvcm.pass_key(seed, 0), config, 0)
    warm = time.perf_counter() - t0
    acc, i, cam, light, nonfinite = None, 0, 0, 0, 0
    t0 = time.perf_counter()
    while True:
        img, diag, config = _pass(scene, jaxvcm.pass_key(seed, i), config, i)
        img = np.asarray(img, dtype=np.float64)
        acc = img if acc is None else acc + img
        cam += int(diag.camera_paths)
        light += int(diag.light_paths)
        nonfinite += int(diag.nonfinite)
        i += 1
        t = time.perf_counter() - t0
        if t + t / i > budget:
            break
    return {"image": acc / i, "passes": i, "seconds": t, "warmup_s": warm,
            "camera_paths": cam, "light_paths": light, "paths_per_s": (cam + light) / t,
            "nonfinite": nonfinite, "merge_capacity": config.tuning.merge_capacity}


def row_exposure(images) -> float:
    """One exposure (stops) per row: the median over panels of each panel's 99th percentile
    of mean-channel radiance is mapped to 1."""
    p = [float(np.percentile(np.asarray(im).mean(axis=-1), 99)) for im in images]
    p = [x for x in p if math.isfinite(x) and x > 0]
    return -math.log2(float(np.median(p))) if p else 0.0


def equal_time_figure(path: Path, grid: list[list[dict]], scenes, algorithms) -> None:
    from matplotlib.figure import Figure  # slow import, only when drawing

    nr, nc = len(grid), len(grid[0])
    fig = Figure(figsize=(2.6 * nc, 2.75 * nr + 0.3), dpi=110)
    for r, row in enumerate(grid):
        ev = row_exposure([p["image"] for p in row])
        for c, p in enumerate(row):
            ax = fig.add_subplot(nr, nc, r * nc + c + 1)
            ax.imshow(jaxvcm.to_srgb8(p["image"].astype(np.float32), ev), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{algorithms[c]}: {p['passes']} passes, {p['seconds']:.1f} s",
                         fontsize=9)
            if c == 0:
                ax.set_ylabel(f"{scenes[r]} ({ev:+.1f} EV)", fontsize=9)
    fig.tight_layout()
    with jaxvcm.atomic_path(str(path)) as tmp:
        fig.savefig(tmp, format="png")


def run_equal_time(a, argv, log) -> dict:
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "size": a.size, "max_depth": a.max_depth, "budget_s": a.equal_time, "seed": a.seed,
           "scenes": [p.stem for p in a.scene_paths], "algorithms": a.algorithms, "rows": []}
    fig = a.out.parent / ET_FIGURE
    npz = Path(tempfile.gettempdir()) / "jaxvcm_equal_time.npz"
    grid, saved = [], {}
    for path in a.scene_paths:
        scene = jaxvcm.load_scene(path, width=a.size, height=a.size)
        row = []
        for alg in a.algorithms:
            cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=a.max_depth)
            log(f"equal time: {path.stem} {alg} {a.size}x{a.size} d{a.max_depth}, "
                f"{a.equal_time:g} s")
            p = equal_time_render(scene, cfg, a.seed, a.equal_time)
            log(f"  warm-up {p['warmup_s']:.1f} s; {p['passes']} passes in "
                f"{p['seconds']:.1f} s, {p['paths_per_s']:,.0f} paths/s")
            row.append(p)
            res["rows"].append({"scene": path.stem, "algorithm": alg,
                                "mean": float(p["image"].mean()),
                                **{k: v for k, v in p.items() if k != "image"}})
        grid.append(row)
        # the linear images, so the figure can be redrawn without rendering again
        saved.update({f"{path.stem}_{alg}": q["image"] for alg, q in zip(a.algorithms, row)})
        np.savez_compressed(npz, **saved)
        log(f"images so far -> {npz}")
    equal_time_figure(fig, grid, res["scenes"], a.algorithms)
    log(f"figure -> {fig}")
    body = equal_time_markdown(res, C.machine_line(res["machine"]), fig.name)
    C.upsert_section(a.out, "equal-time", body)
    C.write_json(a.out.with_name(f"{a.out.stem}_equal-time.json"), res)
    print(body)
    return res


def equal_time_markdown(res: dict, machine_line: str, fig_name: str) -> str:
    L = [f"## Equal-time images ({res['budget_s']:g} s each)", "",
         f"- {machine_line}",
         f"- command: `{res['command']}`",
         f"- size {res['size']}x{res['size']}, max depth {res['max_depth']}, seed "
         f"{res['seed']}; per panel one warm-up pass (compile, not counted), then passes "
         "`pass_key(seed, i)` averaged on the host until the next pass would overrun the "
         "budget (predicted from the mean pass time). paths/s = (camera + light paths) / "
         "seconds. One exposure per row (99th percentile of the panels mapped to 1), sRGB "
         "via colour-science as the CLI preview.", "",
         f"![equal-time renders]({fig_name})", "",
         "| scene | algorithm | passes | seconds | paths/s | camera paths | light paths | "
         "mean radiance | warm-up s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        L.append(f"| {r['scene']} | {r['algorithm']} | {r['passes']} | {r['seconds']:.1f} | "
                 f"{r['paths_per_s']:,.0f} | {r['camera_paths']:,} | {r['light_paths']:,} | "
                 f"{r['mean']:.4g} | {r['warmup_s']:.1f} |")
    vcm = [r for r in res["rows"] if r["algorithm"] == "vcm"]
    if vcm:
        best = max(r["paths_per_s"] for r in vcm)
        L += ["", f"VCM reached at most {best:,.0f} paths/s here = "
              f"{best / VCM_TARGET_PATHS_PER_S:.3g} x the target (SmallVCM) of "
              f"{VCM_TARGET_PATHS_PER_S / 1e6:.2f} M paths/s on a 2-core machine."]
    return "\n".join(L) + "\n"
