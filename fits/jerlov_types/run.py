"""Worked fit 3: Jerlov water types. Fit the WaterModel's extra absorption and
particle scattering so that the RENDERED colour of a white floor at 1, 3 and 10 m under a
uniform D65 sky matches the colour computed from each Jerlov (1976) K_d spectrum.

Targets (targets.py, NumPy + colour-science only): floor irradiance E_d(0-) exp(-K_d d)
with the floor-surface interreflections of the rendered scene included, seen through the
camera's 0.3 m upward path; K_d interpolated between Jerlov's 50 nm nodes along Pope &
Fry's water spectrum. See targets.py and NOTES.md.

Start (--init surrogate, default): a render-free fit (surrogate.py) of the free terms
except b_p (held at 0.2 /m) through the non-scattering approximation sigma = a + b_b,
values clipped to >= 1e-3 /m; --init generic starts every type at a_cdom = 0.05,
b_p = 0.2, a_flat = 0.02 (the first version; it failed for C9, see NOTES.md).

Scene (per depth d): tests/_scenes.flat_water_sky - flat pool of half-width 1 km, white
Lambertian floor (albedo 1) at depth d, uniform sky (D65, Y = 1), camera under water 0.3 m
above the floor looking straight down (fov 2 deg), spectral mode (hero wavelengths),
index n(550) = 1.33468. One region = the whole image (the floor is uniform).

Fitted (log space, shared by the 3 depths): a_cdom [1/m at 440 nm], b_p [1/m at 550 nm],
a_flat [1/m]; fixed: S = 0.015 /nm, n_p = 1, HG g = 0.9 (pure water underneath). Residuals
in CIELAB (D65 white with Y = 1 = the sky), unit uncertainty, Levenberg-Marquardt
(`jaxvcm.fit_spectral`), common random numbers.

Usage (from the repo root):
    python -m fits.jerlov_types.run                       # the default types, then the figure
    python -m fits.jerlov_types.run --types II            # one type (merged into result.json)
    python -m fits.jerlov_types.run --types C7,C9 --passes 128
    python -m fits.jerlov_types.run --types III --free a_cdom,b_p,a_flat,S --tag free_S
    python -m fits.jerlov_types.run --plot                # figures from result.json only
Writes result.json, jerlov_fits.png, convergence.png here.
"""

from __future__ import annotations

import argparse
import json
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))

import jax  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.path.join(ROOT, ".jax_cache"))

import numpy as np  # noqa: E402

from . import targets as T  # noqa: E402
from .surrogate import hg_backscatter_fraction, surrogate_fit  # noqa: E402

DEPTHS = (1.0, 3.0, 10.0)
DEFAULT_TYPES = ("I", "II", "III", "C1", "C3", "C5")
PARAMS = ("a_cdom", "b_p", "a_flat")
FIXED = {"S": 0.015, "n_p": 1.0, "g": 0.9}
INIT = {"a_cdom": 0.05, "b_p": 0.2, "a_flat": 0.02}
EXTRA = ("a_cdom", "b_p", "a_flat")  # terms that are 0 unless fitted


def water_init(free) -> dict:
    """Every WaterModel leaf for a fit of `free`: free ones at INIT (S at FIXED), the
    other extra terms 0, S / n_p / g at FIXED."""
    w = dict(FIXED)
    for k in EXTRA:
        w[k] = INIT[k] if k in free else 0.0
    return w
RESULT = os.path.join(HERE, "result.json")


def model_spectra(water: dict, lam) -> dict:
    """Fitted model (all WaterModel leaves) on lam (NumPy): a, b, b_b, K_d proxy
    (a + b_b) / mu_d."""
    from jaxvcm import WaterModel

    m = WaterModel(**{k: float(v) for k, v in water.items()})
    lam = np.asarray(lam, np.float64)
    a = np.asarray(m.sigma_a(lam), np.float64)
    bw = np.asarray(m.sigma_s(lam), np.float64) - np.asarray(m.particle_scattering(lam))
    bp = np.asarray(m.particle_scattering(lam), np.float64)
    bb = 0.5 * bw + hg_backscatter_fraction(float(water["g"])) * bp
    mu = T.QUAD.mu_d()
    return {"a": a, "b": bw + bp, "b_b": bb, "kd_proxy": (a + bb) / mu, "mu_d": mu}


def build(depths, width, nw, water):
    import jaxvcm
    from jaxvcm import WaterModel
    from tests import _scenes as S

    sps = {}
    for d in depths:
        sc = jaxvcm.scene_from_dict(S.flat_water_sky(d, (0.0,) * 3, 1.33, 1.0, T.CAM_HEIGHT,
                                                     half=1000.0, w=width, h=width))
        sps[f"{d:g}m"] = jaxvcm.spectral_scene(sc, WaterModel(**water), n_wavelengths=nw)
    return sps


def fit_type(name, args):
    import colour

    from jaxvcm import Region, RenderConfig, fit_spectral, spectral_region_colours_fn

    t0 = time.perf_counter()
    tkw = {"interp": args.kd_interp}
    tx = np.stack([T.target_xyz(name, d, **tkw) for d in DEPTHS])
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    tlab = np.asarray(colour.XYZ_to_Lab(tx, xy), np.float64)
    free = tuple(args.free.split(","))
    w0 = water_init(free)
    if args.init == "surrogate":
        sub = [k for k in free if k != "b_p"]
        sur = surrogate_fit(name, DEPTHS, w0, sub, **tkw)
        w0.update({k: float(np.clip(v, 1e-3, 20.0)) for k, v in sur["params"].items()})
        print(f"[{name}] surrogate start {sur}")
    sps = build(DEPTHS, args.size, args.nw, w0)
    W = args.size
    regs = [Region(f"floor_{k}", k, (0, 0, W, W), tuple(tlab[i])) for i, k in enumerate(sps)]
    cfg = RenderConfig(algorithm="pt", max_depth=args.max_depth, rr_depth=100)
    res = fit_spectral(sps, regs, free, space="lab", init={k: w0[k] for k in free}, config=cfg,
                       passes=args.passes, seed=args.seed, max_steps=args.max_steps)
    d = res.to_dict()
    d["target_xyz"] = tx.tolist()
    d["free"] = list(free)
    d["init_kind"] = args.init
    if args.init == "surrogate":
        d["surrogate_start"] = sur
    d["model"] = dict(w0, **{k: float(v) for k, v in res.params.items()})
    print(f"[{name}] {res.result} in {res.iterations} steps, {res.wall_seconds:.0f} s: "
          + ", ".join(f"{k} = {res.params[k]:.4g} +- {res.params_sd[k]:.2g}" for k in free))
    print(f"[{name}] dE2000 initial {np.round(res.delta_e2000_initial, 2)} "
          f"final {np.round(res.delta_e2000, 2)}")
    if args.noise_check:
        # the same fitted water rendered with independent keys: the Monte Carlo part of the
        # residual (the fit only ever sees its own fixed keys)
        t1 = time.perf_counter()
        regs_i = [Region(r.name, i, r.rect, r.target) for i, r in enumerate(regs)]
        fn = spectral_region_colours_fn(list(sps.values()), regs_i, list(free), cfg,
                                        args.passes, args.seed + 1000)
        theta = np.log([res.params[k] for k in free])
        xyz2 = np.asarray(jax.jit(lambda t: fn(t)[0])(theta), np.float64)
        fitted_xyz = np.asarray(colour.Lab_to_XYZ(res.fitted, xy), np.float64)
        d["noise_check"] = {
            "seed": args.seed + 1000,
            "delta_e2000_vs_fit_render": [T.delta_e(a, b) for a, b in zip(xyz2, fitted_xyz)],
            "delta_e2000_vs_target": [T.delta_e(a, b) for a, b in zip(xyz2, tx)],
            "seconds": round(time.perf_counter() - t1, 1)}
        print(f"[{name}] noise check: {d['noise_check']}")
    d["total_seconds"] = round(time.perf_counter() - t0, 1)
    return d


def target_diagnostics(name):
    """How much the target model's choices move the colours (dE2000 per depth)."""
    out = {}
    for d in DEPTHS:
        ref = T.target_xyz(name, d)
        out[f"{d:g}m"] = {
            "no_round_trips": T.delta_e(T.target_xyz(name, d, round_trips=False), ref),
            "linear_kd_interp": T.delta_e(T.target_xyz(name, d, interp="linear"), ref)}
    return out


def load():
    if os.path.exists(RESULT):
        with open(RESULT) as f:
            return json.load(f)
    return {"types": {}}


def plot(data):
    import colour
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxvcm import jerlov_table

    names, wl, kd = jerlov_table()
    types = [t for t in names if t in data["types"]]
    if not types:
        return
    lam = np.arange(380.0, 721.0, 2.0)
    n = len(types)
    ncol = 2
    nrow = (n + ncol - 1) // ncol
    fig = plt.figure(figsize=(6.6 * ncol, 3.0 * nrow), constrained_layout=True)
    sub = fig.subfigures(nrow, ncol)
    sub = np.atleast_1d(sub).reshape(-1)
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    M = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB)
    expo = 1.0 / 1.3  # one exposure for every swatch: the brightest floor has Y ~ 1.25
    for i, t in enumerate(types):
        r = data["types"][t]
        ax, axs = sub[i].subplots(1, 2, width_ratios=[2.2, 1])
        sp = model_spectra(r.get("model") or dict(FIXED, **r["params"]), lam)
        ax.semilogy(lam, sp["a"], "C0-", lw=1.2, label="fitted a")
        ax.semilogy(lam, sp["b"], "C2-", lw=1.2, label="fitted b")
        ax.semilogy(lam, sp["kd_proxy"], "C3-", lw=1.8,
                    label=f"fitted (a+b_b)/mu_d, mu_d={sp['mu_d']:.3f}")
        for tag, st in (("free_S", "--"),):
            v = data.get("variants", {}).get(tag, {}).get(t)
            if v:
                ax.semilogy(lam, model_spectra(v["model"], lam)["kd_proxy"], "C3" + st, lw=1,
                            label=f"same, S free (S={v['params']['S']:.4f}, max dE "
                                  f"{max(g['delta_e2000'] for g in v['regions']):.2f})")
        ax.semilogy(lam, T.jerlov_kd(t, lam), "k:", lw=1, label="K_d target interp.")
        ax.semilogy(wl, kd[:, names.index(t)], "ko", ms=4, label="Jerlov K_d")
        ax.set_ylim(3e-3, 5)
        ax.set_xlim(380, 720)
        ax.set_title(f"Jerlov {t}: " + ", ".join(f"{k}={v:.3g}" for k, v in
                                                  r["params"].items()), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("wavelength (nm)", fontsize=7)
        ax.set_ylabel("1/m", fontsize=7)
        ax.legend(fontsize=5.5, loc="upper center", ncol=2, framealpha=0.6)
        # swatches: rows = depths, left = target, right = fitted render
        tx = np.asarray(r["target_xyz"])
        fx = np.asarray(colour.Lab_to_XYZ(np.array([g["fitted"] for g in r["regions"]]), xy))
        img = np.zeros((len(tx), 2, 3))
        for k in range(len(tx)):
            for j, c in enumerate((tx[k], fx[k])):
                rgb = np.clip(M @ (c * expo), 0, 1)
                img[k, j] = colour.cctf_encoding(rgb)
        axs.imshow(img, interpolation="nearest", aspect="auto")
        axs.set_xticks([0, 1], ["target", "fit"], fontsize=7)
        axs.set_yticks(range(len(tx)),
                       [f"{g['name'][6:]} dE {g['delta_e2000']:.1f}" for g in r["regions"]],
                       fontsize=7)
        axs.yaxis.tick_right()
    fig.suptitle("Jerlov types: fitted WaterModel spectra vs Jerlov K_d (left), "
                 "floor swatches target vs fitted render (right; sRGB, exposure 1/1.3)",
                 fontsize=9)
    fig.savefig(os.path.join(HERE, "jerlov_fits.png"), dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.4), constrained_layout=True)
    for t in types:
        h = [x for x in data["types"][t]["history"] if x["step"] >= 1]  # step 0: no loss yet
        if h:
            ax.semilogy([x["step"] for x in h], [x["loss_accepted"] for x in h], "-o", ms=2,
                        label=t)
    ax.set_title("Levenberg-Marquardt, 3 parameters, S fixed", fontsize=9)
    ax.set_xlabel("LM step")
    ax.set_ylabel("loss of last accepted step (0.5 sum dLab^2)")
    ax.legend(fontsize=7)
    fig.savefig(os.path.join(HERE, "convergence.png"), dpi=110)
    plt.close(fig)


def table(data, which="types") -> str:
    """Markdown table of the fits in result.json (per type: values +- 1 sigma, dE2000 per
    depth initial -> final, independent-key render dE, steps, wall time)."""
    from jaxvcm import jerlov_table

    src = data["types"] if which == "types" else data.get("variants", {}).get(which, {})
    names = [t for t in jerlov_table()[0] if t in src]
    if not names:
        return ""
    free = list(src[names[0]]["params"])
    head = ("| type | " + " | ".join(free) + " | dE2000 1/3/10 m initial | final | "
            "other keys vs target | steps | fit s |")
    rows = [head, "|" + "---|" * (len(free) + 6)]
    for t in names:
        r = src[t]
        ps = " | ".join(f"{r['params'][k]:.3g} ± {r['params_sd'][k]:.2g}" for k in free)
        di = "/".join(f"{g['delta_e2000_initial']:.2f}" for g in r["regions"])
        df = "/".join(f"{g['delta_e2000']:.2f}" for g in r["regions"])
        nc = r.get("noise_check")
        nv = "/".join(f"{x:.2f}" for x in nc["delta_e2000_vs_target"]) if nc else "-"
        rows.append(f"| {t} | {ps} | {di} | {df} | {nv} | {r['iterations']} | "
                    f"{r['wall_seconds']:.0f} |")
    return "\n".join(rows)


def _git() -> str:
    """HEAD commit, with "+dirty" when jaxvcm/ has uncommitted changes (library state)."""
    import subprocess

    try:
        h = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                           capture_output=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "jaxvcm"], cwd=ROOT, text=True,
                               capture_output=True).stdout.strip()
        return h + ("+dirty" if dirty else "")
    except OSError:
        return "unknown"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--types", default=",".join(DEFAULT_TYPES),
                    help="comma-separated Jerlov types (I IA IB II III C1 C3 C5 C7 C9)")
    ap.add_argument("--size", type=int, default=4, help="image width = height (pixels)")
    ap.add_argument("--passes", type=int, default=128)
    ap.add_argument("--nw", type=int, default=8, help="wavelengths per pass")
    ap.add_argument("--max-depth", type=int, default=16)
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise-check", action="store_true",
                    help="also render the fitted water with independent keys")
    ap.add_argument("--free", default=",".join(PARAMS),
                    help="fitted WaterModel leaves (the other extra terms are 0)")
    ap.add_argument("--tag", default="",
                    help="store under variants/TAG in result.json (not the main table)")
    ap.add_argument("--kd-interp", choices=("water", "linear"), default="water",
                    help="K_d between Jerlov's nodes: along Pope & Fry (default) or linear")
    ap.add_argument("--init", choices=("surrogate", "generic"), default="surrogate")
    ap.add_argument("--plot", action="store_true", help="only remake the figures")
    ap.add_argument("--table", default="",
                    help="print the markdown table of 'types' or of a variant tag and exit")
    args = ap.parse_args()
    data = load()
    if args.table:
        print(table(data, args.table))
        return
    if not args.plot:
        for t in args.types.split(","):
            r = fit_type(t, args)
            r["target_model_sensitivity"] = target_diagnostics(t)
            r["run"] = {k: getattr(args, k) for k in ("size", "passes", "nw", "max_depth",
                                                      "max_steps", "seed", "free", "init",
                                                      "kd_interp")}
            r["run"]["git"] = _git()
            data = load()  # merge: another run may have written other types meanwhile
            if args.tag:
                data.setdefault("variants", {}).setdefault(args.tag, {})[t] = r
            else:
                data["types"][t] = r
            data["depths_m"] = list(DEPTHS)
            data["mu_d"] = T.QUAD.mu_d()
            with open(RESULT, "w") as f:
                json.dump(data, f, indent=1)
    plot(data)


if __name__ == "__main__":
    main()
