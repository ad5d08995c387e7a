"""`jaxvcm bench --dispersion`: cost and noise of the spectral dispersion modes.

For each scene and algorithm the spectral scene is rendered with dispersion "off", "hero"
(termination at dispersive refractions) and "exact" (every wavelength on its own path).
All three are compiled and run once first; then `--mis-pairs` rounds of one pass of each
mode are timed, interleaved (the order rotating every round) so that the shared machine's
load falls on all modes alike. Per mode: the median seconds per pass and the per-pass
noise of the image: the relative standard deviation over the passes of 4x4-pixel block
means of Y (CIE 1931), averaged over the blocks. Efficiency = 1 / (variance x seconds),
reported relative to "exact": how much more error-per-time the hero form buys.
"off" is not an estimator of the dispersive image (it ignores dispersion); it is there
as the cost floor.
"""

from __future__ import annotations

import time

import jax
import numpy as np

import jaxvcm

from . import _common as C

MODES = ("off", "hero", "exact")
DEFAULT_SCENES = ("pool_sun.toml",)
DEFAULT_ALGORITHMS = ("vcm",)
DEFAULT_SIZE = 48
DEFAULT_ROUNDS = 12
WAVELENGTHS = 8


def _block_y(xyz, b=4):
    y = np.asarray(xyz, np.float64)[..., 1]
    h, w = (y.shape[0] // b) * b, (y.shape[1] // b) * b
    return y[:h, :w].reshape(h // b, b, w // b, b).mean((1, 3))


def compare_dispersion(scene, config, seed: int, rounds: int) -> dict:
    ss = {m: jaxvcm.spectral_scene(scene, n_wavelengths=WAVELENGTHS, dispersion=m)
          for m in MODES}
    warm = {}
    for m in MODES:
        t0 = time.perf_counter()
        jax.block_until_ready(
            jaxvcm.render_pass_spectral_jit(ss[m], jaxvcm.pass_key(seed, 0), config, 0))
        warm[m] = time.perf_counter() - t0
    times = {m: [] for m in MODES}
    blocks = {m: [] for m in MODES}
    bad = {m: 0 for m in MODES}
    for i in range(rounds):
        order = MODES[i % 3:] + MODES[:i % 3]
        for m in order:
            t0 = time.perf_counter()
            xyz, diag = jaxvcm.render_pass_spectral_jit(ss[m], jaxvcm.pass_key(seed, 1 + i),
                                                        config, 1 + i)
            xyz = jax.block_until_ready(xyz)
            times[m].append(time.perf_counter() - t0)
            blocks[m].append(_block_y(xyz))
            bad[m] += int(diag.core.nonfinite)
    out = {"warmup_s": warm, "times_s": times, "nonfinite": bad, "median_s": {}, "rel_sd": {},
           "mean_y": {}}
    for m in MODES:
        b = np.stack(blocks[m])  # [rounds, by, bx]
        mu = b.mean(0)
        ok = mu > 1e-3 * max(float(mu.max()), 1e-30)
        out["median_s"][m] = float(np.median(times[m]))
        out["rel_sd"][m] = float(np.mean(b.std(0, ddof=1)[ok] / mu[ok]))
        out["mean_y"][m] = float(b.mean())
    eff = {m: 1.0 / (out["rel_sd"][m] ** 2 * out["median_s"][m]) for m in MODES}
    out["efficiency_vs_exact"] = {m: eff[m] / eff["exact"] for m in MODES}
    return out


def run_dispersion(a, argv, log) -> dict:
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "size": a.size, "max_depth": a.max_depth, "rounds": a.mis_pairs, "seed": a.seed,
           "wavelengths": WAVELENGTHS, "rows": []}
    for path in a.scene_paths:
        scene = jaxvcm.load_scene(path, width=a.size, height=a.size)
        for alg in a.algorithms:
            cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=a.max_depth)
            log(f"dispersion: {path.stem} {alg} {a.size}x{a.size} d{a.max_depth}: compiling "
                f"off / hero / exact, then {a.mis_pairs} interleaved rounds")
            r = compare_dispersion(scene, cfg, a.seed, a.mis_pairs)
            res["rows"].append({"scene": path.stem, "algorithm": alg, **r})
            log("  " + ", ".join(f"{m} {r['median_s'][m]:.3f} s/pass rel.sd "
                                 f"{r['rel_sd'][m]:.3g}" for m in MODES))
    C.upsert_section(a.out, "dispersion",
                     dispersion_markdown(res, C.machine_line(res["machine"])))
    C.write_json(a.out.with_name(f"{a.out.stem}_dispersion.json"), res)
    log(f"report -> {a.out}")
    return res


def dispersion_markdown(res: dict, machine_line: str) -> str:
    L = ["## Spectral dispersion: off vs hero (termination) vs exact (per-wavelength paths)",
         "", f"- {machine_line}", f"- command: `{res['command']}`",
         f"- size {res['size']}x{res['size']}, max depth {res['max_depth']}, "
         f"{res['wavelengths']} wavelengths per pass, seed {res['seed']}; each mode compiled "
         f"and run once, then {res['rounds']} rounds of one pass per mode, interleaved "
         "(rotating order). rel. sd = per-pass relative standard deviation of 4x4-pixel "
         "block means of Y, averaged over blocks (lower is better); efficiency = 1 / "
         "(rel.sd^2 x median s), relative to exact. `off` ignores dispersion: it is the "
         "cost floor, not an estimate of the same image.", "",
         "| scene | algorithm | mode | median s/pass | vs off | rel. sd | mean Y | "
         "efficiency vs exact |", "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        for m in MODES:
            L.append(f"| {r['scene']} | {r['algorithm']} | {m} | {r['median_s'][m]:.3f} | "
                     f"{r['median_s'][m] / r['median_s']['off']:.2f} | {r['rel_sd'][m]:.3g} | "
                     f"{r['mean_y'][m]:.4g} | {r['efficiency_vs_exact'][m]:.2f} |")
    return "\n".join(L) + "\n"
