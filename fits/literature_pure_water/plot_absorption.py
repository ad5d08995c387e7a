"""absorption.png of fits/literature_pure_water: the fitted absorption spectra vs Pope &
Fry. Left: sigma_a(lambda) on a log scale; right: the ratio to Pope & Fry, where the
differences are visible: the main fit (spectral/fit.json) with its Jacobian 1-sigma band,
the repeats with other seeds and passes (noise_check.json), and the noise-free expectation
(expected.json). Usage (from the repo root): python -m fits.literature_pure_water.plot_absorption
"""

from __future__ import annotations

import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from jaxvcm import pope_fry_table

HERE = os.path.dirname(os.path.abspath(__file__))

S = 0.015


def model(lam, p):
    wl, aw = pope_fry_table()
    return (p["a_w_scale"] * np.interp(lam, wl, aw) + p["a_cdom"] * np.exp(-S * (lam - 440))
            + p["a_flat"])


def main():
    lam = np.linspace(380.0, 720.0, 341)
    wl, aw = pope_fry_table()
    a_ref = np.interp(lam, wl, aw)
    fit = json.load(open(os.path.join(HERE, "spectral", "fit.json")))
    names = list(fit["params"])
    lin = [n in fit["linear"] for n in names]
    rng = np.random.default_rng(0)
    th = rng.multivariate_normal(fit["theta"], np.asarray(fit["cov_log"]), size=2000,
                                 method="svd")
    curves = np.stack([model(lam, {n: (t if l else np.exp(t)) for n, t, l in zip(names, row, lin)})
                       for row in th])
    lo, hi = np.percentile(curves, [16, 84], axis=0)
    main_curve = model(lam, fit["params"])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.4))
    ax.semilogy(wl, aw, "k.", ms=3, label="Pope & Fry 1997")
    ax.semilogy(lam, model(lam, fit["init"]), "C1:", label="start (a_w_scale 2, a_cdom 0.1, "
                                                           "a_flat 0.05)")
    ax.fill_between(lam, lo, hi, color="C0", alpha=0.3, lw=0)
    ax.semilogy(lam, main_curve, "C0-", lw=1, label="fitted (seed 1, 32 passes) ±1σ")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("absorption (1/m)")
    ax.legend(fontsize=8)
    ax.set_title("absorption: fitted to four floor colours vs literature", fontsize=9)
    ax2.axhline(1.0, color="k", lw=0.8)
    ax2.fill_between(lam, lo / a_ref, hi / a_ref, color="C0", alpha=0.3, lw=0,
                     label="Jacobian ±1σ of the main fit")
    ax2.plot(lam, main_curve / a_ref, "C0-", lw=1.2, label="main fit (seed 1, 32 passes)")
    p = os.path.join(HERE, "noise_check.json")
    if os.path.exists(p):
        k = 1
        for e in json.load(open(p)):
            if e["mode"] != "spectral" or (e["seed"] == 1 and e["passes"] == 32):
                continue
            ax2.plot(lam, model(lam, e["params"]) / a_ref, f"C{k + 1}-", lw=0.8,
                     label=f"seed {e['seed']}, {e['passes']} passes")
            k += 1
    p = os.path.join(HERE, "expected.json")
    if os.path.exists(p):
        e = json.load(open(p))["spectral"]["params"]
        ax2.plot(lam, model(lam, e) / a_ref, "k--", lw=1, label="no Monte Carlo error "
                                                             "(expected_fit.py)")
    ax2.set_xlabel("wavelength (nm)")
    ax2.set_ylabel("fitted σ_a / Pope & Fry a_w")
    ax2.set_ylim(0.6, 1.4)
    ax2.legend(fontsize=7)
    ax2.set_title("ratio to Pope & Fry", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "absorption.png"), dpi=110)


if __name__ == "__main__":
    main()
