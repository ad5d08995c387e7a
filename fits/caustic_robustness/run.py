"""Robustness of the water fit to caustic fireflies: image L2 vs region averages
vs robust (Cauchy IRLS) per-pixel weights, with the drift predicted from the noise.

Scene: `scene.toml` here (scenes/pool.toml with a 2 m light of the same power and the
camera under water looking down at the floor), 32x32, path tracing (max_depth 4, no
Russian roulette). The floor is lit only through the wavy refracting surface (light ->
surface -> floor -> camera; next-event estimation cannot pass the specular surface): PT
reaches the light only by BSDF sampling, so a 16-pass render is caustic fireflies (90% of
samples 0; 26% of pixels 0, the brightest 10x the mean), while the mean of all 1024
pixels x 16 passes has a Monte Carlo error of 4%.

Target: the mean of 2048 passes at the true coefficients with keys independent of the
fits' (seed 1000). Fits: sigma_a only (3 parameters, theta = ln sigma_a; sigma_s fixed at
the truth), from (0.3, 0.1, 0.03), each with 16 fixed-key passes (seeds 0..K-1), by a host
Levenberg-Marquardt (`robust.lm_fit`, robust.py here) on one compiled image+Jacobian program,
for these losses over the whole 32x32 image (FLOOR):

  pixel         every pixel its own residual, one common uncertainty (the image-L2 loss)
  blockB        averages of BxB-pixel blocks, B = 2, 4, 8, 16 (block16: four regions of
                256 pixels, the "region averages" loss); uncertainties: the Monte Carlo
                error of target + a 16-pass render of each block, from the target's
                per-pass spread (independent of the fit render's own noise)
  cauchy        per-pixel residuals with Cauchy IRLS weights (per-channel MAD scale),
                reweighted between LM solves (`irls_fit`)
  decorr        per-pixel residuals, Jacobian from independent keys: passes 0-7 vs 8-15,
                solving J_B^T r_A + J_A^T r_B = 0 (`decorrelated_fit`)

Mechanism (see robust.py): with fixed keys a residual's model value is
n g(theta) with a mean-1 noise factor n; least squares over the residuals scales g by
s = sum w R T / sum w R^2 ~ 1 / (1 + var n) (R: fit render at the truth, T: target), i.e.
sigma_a moves by ln(1 + var n) / L with L = -d ln(image sum) / d sigma_a (mean water path
length, from the Jacobian). Predicted before fitting, per seed, from the fit render's
noise at the truth: `predict_exp` (per-pixel exponential model with the path lengths
l_p = -dR_p/dsigma / R_p) and the one-L scale. Averaging k pixels per residual divides
var n by k.

Also: the block16 loss through the library (`jaxvcm.fit`, optimistix) for seed 0, as a
check that it finds the same solution.

Usage (from the repo root):
       python -m fits.caustic_robustness.run [--seeds 6] [--passes 16] [--target-passes 2048]
       [--resume] [--no-library] [--plot-only]
Writes result.json, robustness.png here (the target's passes are cached in /tmp).
The shipped result: --seeds 6 --target-passes 2048 (NOTES.md).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm import Region, RenderConfig

from . import robust as fr

HERE = os.path.dirname(os.path.abspath(__file__))

W = 32
FLOOR = (0, 0, 32, 32)  # x0, y0, x1, y1: the whole frame (floor seen from under water)
TARGET_SEED = 1000
INIT_SA = np.array([0.3, 0.1, 0.03])
CFG = RenderConfig(algorithm="pt", max_depth=4, rr_depth=100)
BLOCKS = (1, 2, 4, 8, 16)  # pixels per side of the averaged blocks (1: the image-L2 loss)
UNC_PIXEL = 0.01  # the image-L2 loss's one common uncertainty (scale-free: any value)


def target_passes(scene, n, chunk=64):
    cache = f"/tmp/caustic_robustness_target_{W}_{n}.npy"
    if os.path.exists(cache):
        return np.load(cache)

    @jax.jit
    def batch(keys, idx):
        return jax.vmap(lambda k, i: jaxvcm.render_pass(scene, k, CFG, i)[0])(keys, idx)

    out = []
    for i0 in range(0, n, chunk):
        ii = np.arange(i0, min(i0 + chunk, n))
        keys = jnp.stack([jaxvcm.pass_key(TARGET_SEED, int(i)) for i in ii])
        out.append(np.asarray(batch(keys, jnp.asarray(ii, jnp.int32)), np.float32))
    out = np.concatenate(out)
    np.save(cache, out)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--passes", type=int, default=16)
    ap.add_argument("--target-passes", type=int, default=2048)
    ap.add_argument("--no-library", action="store_true", help="skip the jaxvcm.fit check")
    ap.add_argument("--only", nargs="*", help="run only these losses (smoke tests)")
    ap.add_argument("--plot-only", action="store_true", help="redraw from result.json")
    ap.add_argument("--tag", default="",
                    help="write result_TAG.json instead (no figure): side runs, e.g. passes")
    ap.add_argument("--resume", action="store_true",
                    help="keep the finished seeds of result.json (same settings)")
    args = ap.parse_args()
    P = args.passes
    t00 = time.perf_counter()
    if args.plot_only:
        with open(os.path.join(HERE, "result.json")) as f:
            out = json.load(f)
        plot(out, np.load(f"/tmp/caustic_robustness_target_{W}_{out['target']['passes']}.npy")
             .mean(0, dtype=np.float64))
        return
    scene = jaxvcm.load_scene(os.path.join(HERE, "scene.toml"), width=W, height=W)
    truth = np.asarray(scene.water.sigma_a, np.float64)
    th_true, th0 = np.log(truth), np.log(INIT_SA)

    # ---------------- target and its per-pass statistics
    t = time.perf_counter()
    tp = target_passes(scene, args.target_passes)
    target = tp.mean(0, dtype=np.float64)
    t_target = time.perf_counter() - t
    x0, y0, x1, y1 = FLOOR
    H = W
    flo = tp[:, y0:y1, x0:x1].astype(np.float64)
    per_sample_var = flo.var(axis=0).mean((0, 1)) / target[y0:y1, x0:x1].mean((0, 1)) ** 2
    zero = float((flo.sum(-1) == 0).mean())
    print(f"target: {args.target_passes} passes in {t_target:.0f} s; floor mean "
          f"{target[y0:y1, x0:x1].mean((0, 1))}; per-sample var / mean^2 {per_sample_var}; "
          f"{100 * zero:.1f}% of floor samples are 0", flush=True)

    ops = {"pixel": fr.pixel_operator(H, W, FLOOR)}
    for b in BLOCKS[1:]:
        ops[f"block{b}"] = fr.region_operator(H, W, fr.tile_rects(FLOOR, b))
    losses, noise = {}, {}
    for name, A in ops.items():
        mean, se_t, se_f = fr.region_standard_errors(A, tp, P)
        sigma = np.full_like(mean, UNC_PIXEL) if name == "pixel" else np.hypot(se_t, se_f)
        losses[name] = fr.LinearLoss(A, mean, sigma)
        # expected var n of one residual of a P-pass fit render, weighted as least squares
        # weighs it: v = sum_m w Var(R_m) / sum_m w T_m^2, w = 1/sigma^2 -> s ~ 1/(1 + v)
        w = 1.0 / sigma ** 2
        v = np.sum(w * se_f ** 2, 0) / np.sum(w * mean ** 2, 0)
        noise[name] = {"var_n": v.tolist(), "scale_formula": (1 / (1 + v)).tolist(),
                       "rel_se_target": (se_t / mean).mean(0).tolist(),
                       "n_residuals": int(A.shape[0] * 3)}
        print(f"  {name}: {A.shape[0]} residuals/channel, var n of a {P}-pass residual {v}",
              flush=True)
    losses["cauchy"] = losses["decorr"] = losses["pixel"]
    # Monte Carlo error of the whole floor mean (what any unbiased loss is limited by)
    Af = fr.region_operator(H, W, [FLOOR])
    _, se_t_floor, se_f_floor = fr.region_standard_errors(Af, tp, P)
    fmean = target[y0:y1, x0:x1].mean((0, 1))
    rel_se_floor = (np.hypot(se_t_floor, se_f_floor)[0] / fmean)

    # ---------------- fits
    model_fn = fr.image_model(scene, CFG)
    out = {"truth": {"sigma_a": truth.tolist(), "sigma_s": np.asarray(
               scene.water.sigma_s, np.float64).tolist()},
           "init_sigma_a": INIT_SA.tolist(), "size": W, "floor_rect": FLOOR,
           "render": {"algorithm": CFG.algorithm, "max_depth": CFG.max_depth,
                      "rr_depth": CFG.rr_depth},
           "target": {"passes": args.target_passes, "seed": TARGET_SEED,
                      "seconds": round(t_target, 1),
                      "floor_per_sample_var_over_mean2": per_sample_var.tolist(),
                      "floor_zero_sample_fraction": zero},
           "fit": {"passes": P, "seeds": list(range(args.seeds))},
           "blocks": list(BLOCKS), "noise": noise, "floor_rel_se": rel_se_floor.tolist(),
           "seeds": []}
    names = list(ops) + ["cauchy", "decorr"]
    if args.only:
        names = [n for n in names if n in args.only]
    if args.resume and os.path.exists(os.path.join(HERE, "result.json")):
        with open(os.path.join(HERE, "result.json")) as f:
            old = json.load(f)
        if (old.get("fit", {}).get("passes") == P and old.get("target", {}).get("passes")
                == args.target_passes and old.get("init_sigma_a") == INIT_SA.tolist()):
            out["seeds"] = [s for s in old["seeds"] if list(s["fits"]) == names
                            and s["seed"] < args.seeds]
            print(f"resuming after seeds {[s['seed'] for s in out['seeds']]}", flush=True)
    done = {s["seed"] for s in out["seeds"]}
    for seed in range(args.seeds):
        if seed in done:
            continue
        keys = fr.keys_for(seed, P)

        def model(th, keys=keys):
            return model_fn(jnp.asarray(th), keys)

        def model_a(th, keys=keys[:P // 2]):
            return model_fn(jnp.asarray(th), keys)

        def model_b(th, keys=keys[P // 2:]):
            return model_fn(jnp.asarray(th), keys)

        t = time.perf_counter()
        R, J = (np.asarray(a, np.float64) for a in model(th_true))
        t_eval = time.perf_counter() - t
        Rf, Jf = R[y0:y1, x0:x1], J[y0:y1, x0:x1]
        # L_c = -d ln(sum R_c) / d sigma_a,c (theta = ln sigma_a: divide by sigma_a)
        L = -np.array([Jf[..., c, c].sum() / Rf[..., c].sum() for c in range(3)]) / truth
        # per-pixel water path length l_p = -(dR_p/dsigma_a) / R_p (0 where R_p = 0)
        Rp = R.reshape(H * W, 3)
        dR = np.stack([J[..., c, c] for c in range(3)], -1).reshape(H * W, 3) / truth
        lp = np.where(Rp > 0, -dR / np.where(Rp > 0, Rp, 1), 0.0)
        rec = {"seed": seed, "eval_seconds_at_truth": round(t_eval, 2), "L": L.tolist(),
               "fits": {}}
        for name in names:
            loss = losses[name]
            Am = loss.A @ Rp  # residual model values at the truth
            if name == "decorr":  # unbiased by construction (independent keys)
                s = np.ones(3)
            elif name == "cauchy":
                s, _ = fr.irls_scale(Am, loss.b, loss.sigma)
            else:
                s = fr.ls_scale(Am / loss.sigma, loss.b / loss.sigma, axis=0)
            pred_scale = truth - np.log(s) / L  # one common path length L
            pred = truth if name == "decorr" else fr.predict_exp(
                loss.A, Rp, lp, loss.b, loss.sigma, truth,
                kind="cauchy" if name == "cauchy" else None)
            hist = []
            if name == "decorr":
                sol = fr.decorrelated_fit(model_a, model_b, loss, th0, history=hist)
            elif name == "cauchy":
                sol = fr.irls_fit(model, loss, th0, kind="cauchy", channels=3, history=hist,
                                  max_steps=30, rtol=1e-4)
            else:
                sol = fr.lm_fit(model, loss, th0, history=hist, max_steps=30, rtol=1e-4)
            sa = np.exp(sol["theta"])
            sd = sa * np.sqrt(np.diag(fr.covariance(sol["J"], sol["r"],
                                                    scaled=name in ("pixel", "cauchy", "decorr"))))
            rec["fits"][name] = {
                "sigma_a": sa.tolist(), "sigma_a_sd": sd.tolist(),
                "rel_error": (sa / truth - 1).tolist(), "abs_error": (sa - truth).tolist(),
                "predicted_scale": np.asarray(s).tolist(), "predicted_sigma_a": pred.tolist(),
                "predicted_sigma_a_one_L": pred_scale.tolist(),
                "steps": sol["steps"], "evals": sol["evals"], "outer": sol.get("outer"),
                "seconds": round(sol["seconds"], 1), "loss": sol["loss"],
                "history": [{"loss": h["loss"], "sigma_a": np.exp(h["theta"]).tolist(),
                             "accepted": h["accepted"]} for h in hist]}
            if name == "cauchy":
                w = sol["weights"].reshape(-1, 3)
                rec["fits"][name]["weights_quantiles"] = np.quantile(
                    w, [0.0, 0.1, 0.5, 0.9, 1.0], axis=0).tolist()
            print(f"seed {seed} {name:6s}: sigma_a {np.round(sa, 4)} (predicted "
                  f"{np.round(pred, 4)}), {sol['steps']} steps, {sol['evals']} evals, "
                  f"{sol['seconds']:.0f} s", flush=True)
        if seed == 0:
            rec["fit_image_at_truth"] = R.tolist()
        out["seeds"].append(rec)
        _write(out, args.tag)

    # ---------------- the library path (optimistix) on the quad loss, seed 0
    if not args.no_library:
        q = losses[f"block{BLOCKS[-1]}"]
        regions = [Region(f"q{i}", 0, r, tuple(q.b[i]), tuple(q.sigma[i]))
                   for i, r in enumerate(fr.tile_rects(FLOOR, BLOCKS[-1]))]
        res = jaxvcm.fit(scene, regions, config=CFG, passes=P, seed=0, init_sigma_a=INIT_SA,
                         init_sigma_s=scene.water.sigma_s, free="sigma_a", max_steps=30,
                         rtol=1e-4, atol=1e-6)
        out["library_quad_seed0"] = {"sigma_a": res.sigma_a.tolist(),
                                     "sigma_a_sd": res.sigma_a_sd.tolist(),
                                     "iterations": res.iterations, "result": res.result,
                                     "wall_seconds": round(res.wall_seconds, 1)}
        print(f"jaxvcm.fit quad seed 0: {res.sigma_a} ({res.iterations} steps, "
              f"{res.wall_seconds:.0f} s)", flush=True)

    summarise(out)
    out["total_seconds"] = round(time.perf_counter() - t00, 1)
    _write(out, args.tag)
    if not args.tag:
        plot(out, target)
    print(f"total {out['total_seconds']:.0f} s")


def summarise(out):
    truth = np.asarray(out["truth"]["sigma_a"])
    summ = {}
    for name in out["seeds"][0]["fits"]:
        sa = np.array([s["fits"][name]["sigma_a"] for s in out["seeds"]])
        pr = np.array([s["fits"][name]["predicted_sigma_a"] for s in out["seeds"]])
        summ[name] = {"mean_sigma_a": sa.mean(0).tolist(),
                      "sd_over_seeds": (sa.std(0, ddof=1) if len(sa) > 1 else
                                        np.zeros(3)).tolist(),
                      "mean_rel_error": (sa.mean(0) / truth - 1).tolist(),
                      "mean_abs_error": (sa.mean(0) - truth).tolist(),
                      "mean_predicted_sigma_a": pr.mean(0).tolist(),
                      "mean_steps": float(np.mean([s["fits"][name]["steps"]
                                                   for s in out["seeds"]])),
                      "mean_seconds": float(np.mean([s["fits"][name]["seconds"]
                                                     for s in out["seeds"]]))}
    out["summary"] = summ


def _write(out, tag=""):
    p = os.path.join(HERE, f"result_{tag}.json" if tag else "result.json")
    with open(p + ".tmp", "w") as f:
        json.dump(out, f, indent=1)
    os.replace(p + ".tmp", p)


def plot(out, target):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = np.asarray(out["truth"]["sigma_a"])
    x0, y0, x1, y1 = out["floor_rect"]
    fig, ax = plt.subplots(2, 3, figsize=(15, 9))
    R = np.asarray(out["seeds"][0]["fit_image_at_truth"])
    scale = np.percentile(target, 99.5)

    def disp(img):
        c = np.clip(img / scale, 0, 1)
        return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)

    for a, img, title in ((ax[0, 0], target, f"target: {out['target']['passes']} PT passes "
                           f"(seed {out['target']['seed']})"),
                          (ax[0, 1], R, f"fit render at the truth: {out['fit']['passes']} "
                           "passes (seed 0), same exposure\nmax pixel / mean = "
                           f"{R[y0:y1, x0:x1].max() / R[y0:y1, x0:x1].mean():.1f}, "
                           f"{100 * np.mean(R[y0:y1, x0:x1].sum(-1) == 0):.0f}% of pixels 0")):
        a.imshow(disp(img), interpolation="nearest")
        a.add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False,
                                  ec="r", lw=0.8))
        a.set_title(title, fontsize=9)
        a.axis("off")

    # recovered sigma_a per loss, every seed, relative to truth
    names = list(out["summary"])
    a = ax[0, 2]
    cols = ["C0", "C1", "C2"]
    for k, name in enumerate(names):
        sa = np.array([s["fits"][name]["sigma_a"] for s in out["seeds"]])
        pr = np.array([s["fits"][name]["predicted_sigma_a"] for s in out["seeds"]])
        for c in range(3):
            xx = k + (c - 1) * 0.22
            a.plot(np.full(len(sa), xx), sa[:, c] - truth[c], ".", color=cols[c], ms=6,
                   label=["R", "G", "B"][c] if k == 0 else None)
            a.plot([xx - 0.09, xx + 0.09], [pr[:, c].mean() - truth[c]] * 2, "k-", lw=1)
    a.axhline(0, color="k", lw=0.6)
    a.set_xticks(range(len(names)), names)
    a.set_yscale("symlog", linthresh=0.01)
    a.set_ylabel("fitted - true sigma_a (1/m)  [symlog]")
    a.set_title(f"fitted sigma_a - truth, {len(out['seeds'])} fit seeds (dots), predicted "
                "at the truth (bars)\n(decorr: truth; its points at -0.02 (B) are fits that "
                "ran into sigma -> 0)", fontsize=9)
    a.legend(fontsize=8)

    # drift vs pixels per residual: measured (mean over seeds) and predicted
    a = ax[1, 0]
    order = [n for n in out["summary"] if n == "pixel" or n.startswith("block")]
    npix = [b * b for b in out["blocks"]]
    for c in range(3):
        m = [out["summary"][n]["mean_sigma_a"][c] - truth[c] for n in order]
        sd = [out["summary"][n]["sd_over_seeds"][c] / np.sqrt(len(out["seeds"])) for n in order]
        p = [out["summary"][n]["mean_predicted_sigma_a"][c] - truth[c] for n in order]
        a.errorbar(npix, m, yerr=sd, fmt="o", color=cols[c], label=f"{'RGB'[c]} fitted")
        a.plot(npix, p, "--", color=cols[c], label=f"{'RGB'[c]} predicted")
        L = np.mean([s["L"][c] for s in out["seeds"]])
        v = np.asarray([out["noise"][n]["var_n"][c] for n in order])
        a.plot(npix, np.log1p(v) / L, ":", color=cols[c], lw=0.8)
    a.plot([], [], "k:", lw=0.8, label="ln(1 + var n) / L")
    a.set_xscale("log")
    a.set_yscale("symlog", linthresh=0.01)
    a.axhline(0, color="k", lw=0.6)
    a.set_xlabel("pixels averaged per residual (x passes = samples)")
    a.set_ylabel("mean fitted - true sigma_a (1/m)")
    a.set_title("drift vs averaging: fitted (mean ± s.e. over seeds), predicted at the\n"
                "truth from the fit render's noise (dashed), ln(1 + var n)/L (dotted)",
                fontsize=9)
    a.legend(fontsize=7, ncol=2)

    # loss and parameter history, seed 0
    a, b = ax[1, 1], ax[1, 2]
    for k, name in enumerate(names):
        h = out["seeds"][0]["fits"][name]["history"]
        l0 = h[0]["loss"]
        a.semilogy([e["loss"] / l0 for e in h], "o-", ms=2, color=f"C{k}", label=name)
        b.plot([e["sigma_a"][0] for e in h], "o-", ms=2, color=f"C{k}", label=name)
    a.set_xlabel("model evaluation (LM trial steps; IRLS: all solves)")
    a.set_ylabel("loss / initial loss")
    a.set_title("loss history, seed 0 (decorr solves an estimating equation:\n"
                "its 'loss' 0.5 |r|^2 is only monitored)", fontsize=9)
    a.legend(fontsize=8)
    b.axhline(truth[0], color="k", lw=0.8, ls="--", label="truth")
    b.set_xlabel("model evaluation")
    b.set_ylabel("sigma_a R (1/m)")
    b.set_title("parameter history (red channel), seed 0", fontsize=9)
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "robustness.png"), dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
