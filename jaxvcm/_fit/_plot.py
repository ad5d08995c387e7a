"""Figures and output files of a fit: fit.json + fit.png (`write_outputs`,
`write_outputs_spectral`). matplotlib is imported only when a figure is drawn."""

from __future__ import annotations

import json
import os
import textwrap

import numpy as np

from .._io import atomic_path
from .._spectral import WaterModel, pope_fry_table
from ._colour import to_srgb_host
from ._rgb import FitResult
from ._spectral import SpectralFitResult, absorption_band


def _wrap(text: str, width: int = 70) -> str:
    """A failed fit's verdict for a figure title (lines of at most `width` characters)."""
    return "\n".join(textwrap.wrap(text, width))


def plot_swatches_and_loss(res, ax, ax2) -> None:
    """The two panels every fit figure has: initial / target / fitted swatches per region
    (one display exposure for all) on `ax`, the loss per Levenberg-Marquardt step on `ax2`.
    `res`: a FitResult or SpectralFitResult (regions, targets, fitted, initial, space,
    delta_e2000(_initial), history)."""
    import matplotlib.pyplot as plt

    R = len(res.regions)
    tg = to_srgb_host(res.targets, res.space)
    ft = to_srgb_host(res.fitted, res.space)
    it = to_srgb_host(res.initial, res.space)
    scale = 0.8 / max(float(np.max(tg)), 1e-6)  # one exposure for all swatches

    def disp(c):
        c = np.clip(np.asarray(c) * scale, 0.0, 1.0)
        return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)

    for i, r in enumerate(res.regions):
        y = R - 1 - i
        for j, c in enumerate((it[i], tg[i], ft[i])):
            ax.add_patch(plt.Rectangle((j * 1.1, y), 1.0, 0.85, color=disp(c)))
        ax.text(3.4, y + 0.42, f"{r.name}  ({r.scene})\n"
                f"ΔE00 {res.delta_e2000_initial[i]:.3g} -> {res.delta_e2000[i]:.2g}",
                va="center", fontsize=8)
    for j, lab in enumerate(("initial", "target", "fitted")):
        ax.text(j * 1.1 + 0.5, R + 0.05, lab, ha="center", va="bottom", fontsize=9)
    ax.set_xlim(0, 6.2)
    ax.set_ylim(-0.1, R + 0.5)
    ax.axis("off")
    ax.set_title(f"regions (display sRGB, common exposure x{scale:.3g})", fontsize=9)
    h = res.history
    if h:
        st = [e["step"] for e in h]
        ax2.semilogy(st, [max(e["loss"], 1e-30) for e in h], "o-", ms=3, label="loss of step")
        acc = [(e["step"], e["loss_accepted"]) for e in h if e["step"] > 0]  # none at step 0
        if acc:
            ax2.semilogy(*zip(*acc), "s--", ms=3, label="last accepted")
        ax2.set_xlabel("Levenberg-Marquardt step")
        ax2.set_ylabel("loss 0.5 sum r^2 (r = residual / uncertainty)")
        ax2.legend(fontsize=8)


def plot_fit(res: FitResult, path: str) -> None:
    """Target vs fitted (and initial) swatches per region + the loss per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    R = len(res.regions)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 0.9 * R + 2.2),
                                  gridspec_kw={"width_ratios": [1.2, 1]})
    plot_swatches_and_loss(res, ax, ax2)
    txt = "\n".join(["sa = " + ", ".join(f"{v:.4g}" for v in res.sigma_a),
                     "ss = " + ", ".join(f"{v:.4g}" for v in res.sigma_s),
                     f"{res.iterations} steps, {res.wall_seconds:.1f} s"]
                    + ([_wrap(res.verdict)] if res.problems else []))
    ax2.set_title(txt, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _write(record: dict, draw, res, out_dir: str) -> tuple[str, str]:
    """fit.json (atomically) + fit.png (`draw(res, path)`) in out_dir -> their paths."""
    os.makedirs(out_dir, exist_ok=True)
    jp = os.path.join(out_dir, "fit.json")
    pp = os.path.join(out_dir, "fit.png")
    with atomic_path(jp) as tmp:
        with open(tmp, "w") as f:
            json.dump(record, f, indent=1)
    draw(res, pp)
    return jp, pp


def write_outputs(res: FitResult, out_dir: str) -> tuple[str, str]:
    """Write an RGB fit's fit.json and fit.png into `out_dir`; returns their paths.

    fit.json is `FitResult.to_dict` (written atomically), fit.png `plot_fit`'s figure."""
    return _write(res.to_dict(), plot_fit, res, out_dir)


def plot_fit_spectral(res: SpectralFitResult, path: str) -> None:
    """Target vs fitted (and initial) swatches per region, the loss per step, and the fitted
    absorption spectrum with a 1-sigma band vs the initial model and Pope & Fry."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = res.model_type or WaterModel
    R = len(res.regions)
    fig, (ax, ax2, ax3) = plt.subplots(1, 3, figsize=(15, max(0.9 * R + 2.2, 4.2)),
                                       gridspec_kw={"width_ratios": [1.2, 1, 1.1]})
    plot_swatches_and_loss(res, ax, ax2)
    ax2.set_title("\n".join(f"{k} = {v:.4g} ± {res.params_sd[k]:.2g}"
                            for k, v in res.params.items())
                  + f"\n{res.iterations} steps, {res.wall_seconds:.1f} s"
                  + (f"\n{_wrap(res.verdict)}" if res.problems else ""), fontsize=8)
    lam = np.linspace(380.0, 720.0, 341)
    mid, lo, hi = absorption_band(res, lam)
    base = dict(res.water or {})
    flags = {k: base.pop(k) for k in ("pure_absorption", "pure_scattering") if k in base}
    b0 = dict(base)
    b0.update(res.init)
    a_init = np.asarray(model(**{k: np.float64(v) for k, v in b0.items()},
                              **flags).sigma_a(lam), np.float64)
    wl, aw = pope_fry_table()
    sel = (wl >= 380) & (wl <= 720)
    ax3.fill_between(lam, lo, hi, color="C0", alpha=0.3, lw=0, label="fit ±1σ (Jacobian)")
    ax3.semilogy(lam, mid, "C0-", lw=1.2, label="fitted σ_a(λ)")
    ax3.semilogy(lam, a_init, "C1:", lw=1.2, label="initial model")
    ax3.semilogy(wl[sel], aw[sel], "k.", ms=3, label="Pope & Fry 1997 a_w")
    if res.truth:
        bt = dict(base)
        bt.update(res.truth)
        a_true = np.asarray(model(**{k: np.float64(v) for k, v in bt.items()},
                                  **flags).sigma_a(lam), np.float64)
        ax3.semilogy(lam, a_true, "k-", lw=0.6, alpha=0.6, label="truth")
    ax3.set_xlabel("wavelength (nm)")
    ax3.set_ylabel("absorption σ_a (1/m)")
    ax3.set_ylim(max(1e-3, float(np.min(np.maximum(lo, 1e-4))) * 0.5), None)
    ax3.legend(fontsize=7)
    ax3.set_title("fitted absorption spectrum", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs_spectral(res: SpectralFitResult, out_dir: str) -> tuple[str, str]:
    """Write a spectral fit's fit.json and fit.png into `out_dir`; returns their paths.

    As for an RGB fit (`jaxvcm.write_fit_outputs`), with mode = "spectral" in fit.json and
    `plot_fit_spectral`'s figure."""
    return _write({**res.to_dict(), "mode": "spectral"}, plot_fit_spectral, res, out_dir)
