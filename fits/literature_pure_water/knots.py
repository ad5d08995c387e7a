"""Extra of fits/literature_pure_water: a freer absorption model, to see WHICH part of the
spectrum the four floor colours constrain.

    sigma_a(lambda) = exp(interp(lambda; knots 400, 450, ..., 700 nm; l_400 ... l_700))

(log-absorption linearly interpolated between 7 knots, constant beyond the end knots;
no Pope & Fry term at all: pure_absorption = False), fitted in log space (theta_k =
l_k = ln a(lambda_k); the fit's "log space" is applied to a_k = e^(l_k)) from a flat start
a_k = 0.1 /m, to the same colour-science targets, scenes, keys and render settings as
spectral.toml. The Jacobian uncertainty of each knot says how well the colours pin the
absorption down at that wavelength. Writes knots/fit.json, knots/fit.png and
knots/absorption.png. Usage (from the repo root): python -m fits.literature_pure_water.knots
"""

from __future__ import annotations

import json
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm import (WaterModel, enable_compilation_cache, fit_spectral, load_fit_config,
                    pope_fry_table, write_spectral_fit_outputs)

HERE = os.path.dirname(os.path.abspath(__file__))

KNOTS = (400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0)
NAMES = tuple(f"a_{int(k)}" for k in KNOTS)
A0 = 0.1  # 1/m, the flat start


def _f():
    return eqx.field(converter=jnp.asarray, default=A0)


class KnotWater(WaterModel):
    """WaterModel whose absorption is log-linear between 7 knots (a_400 ... a_700, 1/m);
    the CDOM and flat terms are kept (0 here), the Pope & Fry term is off."""

    a_400: jnp.ndarray = _f()
    a_450: jnp.ndarray = _f()
    a_500: jnp.ndarray = _f()
    a_550: jnp.ndarray = _f()
    a_600: jnp.ndarray = _f()
    a_650: jnp.ndarray = _f()
    a_700: jnp.ndarray = _f()

    def sigma_a(self, lam):
        lam = jnp.asarray(lam)
        dt = lam.dtype if jnp.issubdtype(lam.dtype, jnp.floating) else jnp.float32
        logs = jnp.log(jnp.stack([getattr(self, n).astype(dt) for n in NAMES]))
        knot_sigma = jnp.exp(jnp.interp(lam.astype(dt), jnp.asarray(KNOTS, dt), logs))
        return knot_sigma + self.extra_absorption(lam)


def main():
    enable_compilation_cache()
    kw = load_fit_config(os.path.join(HERE, "spectral.toml"))
    kw.pop("mode")
    model = KnotWater(pure_absorption=False, pure_scattering=False)
    sps = {k: jaxvcm.spectral_scene(sp.scene, model, n_wavelengths=sp.n_wavelengths)
           for k, sp in kw["spectral"].items()}
    wl, aw = pope_fry_table()
    truth = {n: float(np.interp(k, wl, aw)) for n, k in zip(NAMES, KNOTS)}
    res = fit_spectral(sps, kw["regions"], list(NAMES), space=kw["space"],
                       init={n: A0 for n in NAMES}, config=kw["config"], passes=kw["passes"],
                       seed=kw["seed"], max_steps=40, rtol=kw["rtol"], atol=kw["atol"],
                       truth=truth, progress=True)
    out = os.path.join(HERE, "knots")
    write_spectral_fit_outputs(res, out)
    print(res.summary())
    # the knots vs Pope & Fry, with 1-sigma error bars (log-normal: a e^(+-sd(ln a)))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.array([res.params[n] for n in NAMES])
    sdl = np.sqrt(np.diag(res.cov))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.semilogy(wl, aw, "k-", lw=0.8, label="Pope & Fry 1997 a_w")
    ax.errorbar(KNOTS, a, yerr=[a - a * np.exp(-sdl), a * np.exp(sdl) - a], fmt="o", ms=4,
                capsize=3, color="C0", label="fitted knots ±1σ (Jacobian)")
    lam = np.linspace(380, 720, 341)
    ax.semilogy(lam, np.exp(np.interp(lam, KNOTS, np.log(a))), "C0-", lw=0.8)
    ax.axhline(A0, color="C1", ls=":", label=f"start: {A0} /m everywhere")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("absorption (1/m)")
    ax.set_title("7-knot log-absorption fitted to 4 floor colours", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "absorption.png"), dpi=110)
    summary = {n: {"lambda": k, "fitted": float(res.params[n]), "sd": float(res.params_sd[n]),
                   "sd_ln": float(s), "pope_fry": truth[n]}
               for n, k, s in zip(NAMES, KNOTS, sdl)}
    with open(os.path.join(out, "knots.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
