"""Spectral-mode fitting: the `WaterModel` parameters from region colours.

Same problem, solver and report as `_fit.fit` (see its docstring), but the scenes are
`SpectralScene`s rendered with `render_pass_spectral` (CIE XYZ film) and the parameters
are leaves of the water model:

    sigma_a(lambda) = a_w_scale a_w(lambda) + a_cdom exp(-S (lambda - 440)) + a_flat
    sigma_s(lambda) = b_w(lambda) + b_p (lambda / 550)^-n_p

Parameterisation: by default every fitted parameter is fitted in log space (positive by
construction; a parameter at exactly 0 cannot be fitted in log space, start it small or
fit it linearly). Names listed in `linear` are fitted as they are, unconstrained: use it for
terms whose true value may be 0 (a_cdom, a_flat of pure water), where a log fit could
only creep towards -infinity and its Jacobian uncertainty would be meaningless. A
negative total sigma_a is clamped to 0 by the renderer (`SpectralScene.at_wavelengths`).

Common random numbers include the wavelengths: every pass draws its hero wavelength from
its own key, so fixed keys fix the wavelengths too. Scenes with the same static structure
(size, shapes, n_wavelengths, ...) are stacked and rendered by one `vmap` (one compiled
renderer for all of them, as in the RGB fit).

Config files (`jaxvcm fit CONFIG` with `mode = "spectral"`): see `_fit.CONFIG_DOC`.
"""

from __future__ import annotations

import dataclasses
import json
import time as _time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._config import RenderConfig
from ._fit import (Region, _colour_constants, _result_name, default_uncertainty, delta_e2000,
                   plot_swatches_and_loss, xyz_to_lab)
from ._render import pass_key
from ._spectral import SpectralScene, render_pass_spectral

PARAMS = ("a_cdom", "S", "a_flat", "b_p", "n_p", "g", "a_w_scale")  # fittable WaterModel leaves


@dataclasses.dataclass
class SpectralFitResult:
    params: dict  # name -> fitted value
    params_sd: dict  # name -> 1 sigma (scaled by the residual variance)
    init: dict
    cov: np.ndarray  # of theta (ln p for log-space parameters, p for linear ones)
    cov_unscaled: np.ndarray
    space: str
    regions: list
    targets: np.ndarray
    fitted: np.ndarray
    initial: np.ndarray
    delta_e2000: np.ndarray
    delta_e2000_initial: np.ndarray
    iterations: int
    result: str
    wall_seconds: float
    history: list
    config: dict
    truth: dict | None = None
    linear: tuple = ()  # names fitted in linear space
    theta: np.ndarray | None = None  # the fitted theta
    jacobian: np.ndarray | None = None  # d residual / d theta at the solution
    residuals: np.ndarray | None = None  # (rendered - target) / uncertainty
    solve_seconds: float = 0.0
    water: dict | None = None  # the fitted WaterModel's fields (for plots and reports)
    model_type: type | None = None  # WaterModel or the subclass that was fitted

    def to_dict(self) -> dict:
        def f(x):
            return np.asarray(x, np.float64).tolist()

        d = {"params": {k: float(v) for k, v in self.params.items()},
             "params_sd": {k: float(v) for k, v in self.params_sd.items()},
             "init": {k: float(v) for k, v in self.init.items()},
             "linear": list(self.linear),
             "theta": None if self.theta is None else f(self.theta),
             # cov_log keeps its historical name: the covariance of theta (log for the
             # log-space parameters, linear for `linear` ones)
             "cov_log": f(self.cov), "cov_log_unscaled": f(self.cov_unscaled),
             "space": self.space,
             "regions": [{"name": r.name, "scene": r.scene, "rect": list(r.rect),
                          "target": f(self.targets[i]), "fitted": f(self.fitted[i]),
                          "initial": f(self.initial[i]),
                          "delta_e2000": float(self.delta_e2000[i]),
                          "delta_e2000_initial": float(self.delta_e2000_initial[i])}
                         for i, r in enumerate(self.regions)],
             "delta_e2000_max": float(np.max(self.delta_e2000)),
             "delta_e2000_mean": float(np.mean(self.delta_e2000)),
             "iterations": self.iterations, "result": self.result,
             "wall_seconds": round(self.wall_seconds, 3),
             "solve_seconds": round(self.solve_seconds, 3), "history": self.history,
             "config": self.config}
        if self.residuals is not None:
            d["residual_rms"] = float(np.sqrt(np.mean(self.residuals ** 2)))
        if self.water is not None:
            d["water"] = {k: (v if isinstance(v, bool) else float(v))
                          for k, v in self.water.items()}
        if self.truth:
            d["truth"] = {k: float(v) for k, v in self.truth.items()}
            d["abs_error"] = {k: float(self.params[k] - v) for k, v in self.truth.items()
                              if k in self.params}
            d["rel_error"] = {k: float(self.params[k] / v - 1) for k, v in self.truth.items()
                              if k in self.params and v != 0}
            d["error_in_sd"] = {k: float((self.params[k] - v) / self.params_sd[k])
                                for k, v in self.truth.items()
                                if k in self.params and self.params_sd[k] > 0}
        return d

    def summary(self) -> str:
        ps = ", ".join(f"{k} = {v:.4g} ± {self.params_sd[k]:.2g}"
                       for k, v in self.params.items())
        return "\n".join([
            ps,
            f"dE2000 max {np.max(self.delta_e2000):.3g}, mean {np.mean(self.delta_e2000):.3g} "
            f"(initial max {np.max(self.delta_e2000_initial):.3g}); {self.iterations} steps, "
            f"{self.result}; {self.wall_seconds:.1f} s"])


def _spectral_groups(spectral: Sequence[SpectralScene]):
    """Spectral scenes with equal static structure -> (indices, stacked scene)."""
    groups: list[tuple[list[int], list[SpectralScene]]] = []
    for i, sp in enumerate(spectral):
        sp = dataclasses.replace(sp, scene=dataclasses.replace(sp.scene, name="fit"))
        st = jax.tree.structure(sp)
        shapes = [(a.shape, a.dtype) for a in jax.tree.leaves(sp)]
        for idx, members in groups:
            m0 = members[0]
            if jax.tree.structure(m0) == st and shapes == [(a.shape, a.dtype)
                                                          for a in jax.tree.leaves(m0)]:
                idx.append(i)
                members.append(sp)
                break
        else:
            groups.append(([i], [sp]))
    return [(idx, jax.tree.map(lambda *a: jnp.stack(a), *members)) for idx, members in groups]


def _to_values(theta, names, linear):
    """theta [n] -> parameter values [n]: exp for log-space names, identity for linear."""
    lin = jnp.asarray([n in linear for n in names])
    return jnp.where(lin, theta, jnp.exp(jnp.where(lin, 0.0, theta)))


def spectral_region_colours_fn(spectral: Sequence[SpectralScene], regions: Sequence[Region],
                               names: Sequence[str], config: RenderConfig, passes: int,
                               seed: int, linear: Sequence[str] = ()):
    """theta [n] -> (region XYZ [R, 3], merge overflow flag); fixed keys pass_key(seed, i).
    theta_j = ln p_j, or p_j itself for names in `linear`."""
    keys = jnp.stack([pass_key(seed, i) for i in range(passes)])
    idx = jnp.arange(passes, dtype=jnp.int32)
    groups = _spectral_groups(spectral)
    where = {}
    for g, (members, _) in enumerate(groups):
        for p, i in enumerate(members):
            where[i] = (g, p)
    linear = tuple(linear)

    def fn(theta):
        vals = _to_values(theta, list(names), linear)
        images = []
        overflow = jnp.zeros((), bool)
        for _, stacked in groups:
            def passes_of(sp):
                dt = sp.scene.bounds.dtype
                water = dataclasses.replace(
                    sp.water, **{n: vals[j].astype(dt) for j, n in enumerate(names)})
                sp1 = dataclasses.replace(sp, water=water)

                def one(key, i):
                    xyz, diag = render_pass_spectral(sp1, key, config, i)
                    return xyz, diag.core.merge_overflow

                imgs, ov = jax.vmap(one)(keys, idx)
                return jnp.mean(imgs, axis=0), jnp.any(ov)

            imgs, ov = jax.vmap(passes_of)(stacked)
            images.append(imgs)
            overflow = overflow | jnp.any(ov)
        cols = []
        for r in regions:
            g, p = where[r.scene]
            x0, y0, x1, y1 = r.rect
            cols.append(jnp.mean(images[g][p, y0:y1, x0:x1], axis=(0, 1)))
        return jnp.stack(cols), overflow

    return fn


def fit_spectral(spectral, regions: Sequence[Region], params: Sequence[str] = ("a_cdom", "b_p"),
                 *, space: str = "xyz", init: dict | None = None,
                 config: RenderConfig | None = None, passes: int = 16, seed: int = 0,
                 max_steps: int = 40, rtol: float = 1e-3, atol: float = 1e-3,
                 truth: dict | None = None, linear: Sequence[str] = (),
                 progress: bool = False) -> SpectralFitResult:
    """Fit `params` (names of `WaterModel` leaves, or scalar leaves of a `WaterModel`
    subclass, shared by all scenes) so that the region
    colours of the spectral scenes match the targets (in "xyz", "srgb" = linear sRGB, or
    "lab"). init: name -> initial value (default: the first scene's water model).
    linear: names fitted in linear space (may cross 0); the others in log space.
    Uncertainties: sd(p) = p sd(ln p) for log-space parameters, sd(p) for linear ones."""
    import optimistix as optx

    t0 = _time.perf_counter()
    from ._fit import _named, _resolve

    spectral, snames = _named(spectral, SpectralScene)
    params = list(params)
    linear = tuple(linear)
    if not params:
        raise ValueError("params: nothing to fit")
    w0 = spectral[0].water
    # WaterModel's leaves, or the scalar leaves of a subclass (e.g. a freer absorption model)
    allowed = list(PARAMS) + [f.name for f in dataclasses.fields(w0) if f.name not in PARAMS
                              and not f.metadata.get("static", False)
                              and np.ndim(getattr(w0, f.name)) == 0]
    for p in params:
        if p not in allowed:
            raise ValueError(f"params: unknown {p!r}; one of {', '.join(allowed)}")
        if params.count(p) > 1:
            raise ValueError(f"params: {p!r} listed twice")
    for p in linear:
        if p not in params:
            raise ValueError(f"linear: {p!r} is not one of the fitted params")
    if space not in ("xyz", "srgb", "lab"):
        raise ValueError(f"space: unknown {space!r}")
    if not isinstance(passes, int) or passes < 1:
        raise ValueError(f"passes: must be a positive integer, got {passes!r}")
    _, regions, _ = _resolve({k: s.scene for k, s in zip(snames, spectral)}, regions)
    config = config or RenderConfig(algorithm="pt", max_depth=6)
    init = dict(init or {})
    for k in init:
        if k not in params:
            raise ValueError(f"init: {k!r} is not one of the fitted params")
    p0 = np.array([float(init.get(p, np.asarray(getattr(w0, p)))) for p in params])
    if not np.all(np.isfinite(p0)):
        raise ValueError("init: values must be finite")
    if not all(v > 0 for v, p in zip(p0, params) if p not in linear):
        raise ValueError("init: every fitted parameter must be > 0 (log-space fit)")
    lin = np.array([p in linear for p in params])
    theta0 = np.where(lin, p0, np.log(np.where(lin, 1.0, p0)))
    pdtype = jnp.result_type(float)
    dtype = spectral[0].scene.bounds.dtype
    targets = np.array([r.target for r in regions], np.float64)
    unc = np.array([default_uncertainty(r.target, space) if r.uncertainty is None
                    else r.uncertainty for r in regions], np.float64)
    colours = spectral_region_colours_fn(spectral, regions, params, config, passes, seed,
                                         linear)
    M, white = _colour_constants()
    Minv = np.linalg.inv(M)
    tgt = jnp.asarray(targets, dtype)
    inv_unc = jnp.asarray(1.0 / unc, dtype)

    def convert(xyz):
        if space == "xyz":
            return xyz
        if space == "srgb":
            return xyz @ jnp.asarray(Minv, xyz.dtype).T
        return xyz_to_lab(xyz, white)

    def residual_fn(y, args):
        xyz, overflow = colours(y.astype(dtype))
        return ((convert(xyz) - tgt) * inv_unc).reshape(-1).astype(pdtype), overflow

    history: list[dict] = []

    def _record(kw):
        history.append({"step": int(kw["num_steps"]), "loss": float(kw["loss_this_step"]),
                        "loss_accepted": float(kw["loss_last_accepted_step"]),
                        "theta": np.asarray(kw["y"], np.float64).tolist()})
        if progress:
            print(f"  step {history[-1]['step']:3d}  loss {history[-1]['loss']:.6g}", flush=True)

    def verbose(**kw):
        jax.debug.callback(_record, {k: v[1] for k, v in kw.items()
                                     if k in ("num_steps", "loss_this_step",
                                              "loss_last_accepted_step", "y")})

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)

    @jax.jit
    def solve(y0):
        sol = optx.least_squares(residual_fn, solver, y0, has_aux=True, max_steps=max_steps,
                                 throw=False)
        r0, _ = residual_fn(y0, None)
        return (sol.value, sol.result, sol.stats["num_steps"], sol.aux, r0,
                sol.state.f_info.jac.as_matrix(), sol.state.f_info.residual)

    t1 = _time.perf_counter()
    y, result, nsteps, overflow, r0, J, r1 = solve(jnp.asarray(theta0, pdtype))
    y = np.asarray(jax.block_until_ready(y), np.float64)
    solve_seconds = _time.perf_counter() - t1
    if bool(overflow):
        raise RuntimeError("fit_spectral: the merging gather overflowed its capacity")
    res = np.asarray(r1, np.float64)
    J = np.asarray(J, np.float64)
    m, n = J.shape
    cov_u = np.linalg.pinv(J.T @ J)
    cov = cov_u * float(res @ res) / max(m - n, 1)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    vals = np.where(lin, y, np.exp(np.where(lin, 0.0, y)))
    vals_sd = np.where(lin, sd, vals * sd)
    fitted = res.reshape(-1, 3) * unc + targets
    initial = np.asarray(r0, np.float64).reshape(-1, 3) * unc + targets
    water = {f.name: getattr(w0, f.name) for f in dataclasses.fields(w0)}
    water = {k: (v if isinstance(v, bool) else float(np.asarray(v))) for k, v in water.items()}
    water.update({p: float(v) for p, v in zip(params, vals)})
    return SpectralFitResult(
        params=dict(zip(params, vals)), params_sd=dict(zip(params, vals_sd)),
        init=dict(zip(params, p0)), cov=cov, cov_unscaled=cov_u, space=space,
        regions=[dataclasses.replace(r, scene=snames[r.scene]) for r in regions],
        targets=targets, fitted=fitted, initial=initial,
        delta_e2000=delta_e2000(targets, fitted, space),
        delta_e2000_initial=delta_e2000(targets, initial, space),
        iterations=int(nsteps), result=_result_name(result),
        wall_seconds=_time.perf_counter() - t0, history=history,
        config={"render": dataclasses.asdict(config), "passes": passes, "seed": seed,
                "n_wavelengths": spectral[0].n_wavelengths, "max_steps": max_steps,
                "rtol": rtol, "atol": atol, "scenes": snames,
                "size": [[s.scene.camera.width, s.scene.camera.height] for s in spectral]},
        truth=truth, linear=linear, theta=y, jacobian=J, residuals=res,
        solve_seconds=solve_seconds, water=water, model_type=type(w0))


# ------------------------------------------------------------------ absorption spectrum
def absorption_band(res: SpectralFitResult, lam, draws: int = 400, seed: int = 0):
    """sigma_a(lam) of the fitted model, and its 16th/84th percentiles over `draws` samples of
    theta ~ N(theta_hat, Cov) (the Jacobian covariance): (mean curve, lo, hi) [len(lam)].
    Parameters not fitted stay at the model's values."""
    from ._spectral import WaterModel

    WaterModel = res.model_type or WaterModel  # noqa: N806
    lam = np.asarray(lam, np.float64)
    names = list(res.params)
    lin = np.array([n in res.linear for n in names])
    base = {k: v for k, v in (res.water or {}).items()}

    def curve(vals):
        w = dict(base)
        w.update(dict(zip(names, vals)))
        flags = {k: w.pop(k) for k in ("pure_absorption", "pure_scattering") if k in w}
        m = WaterModel(**{k: np.float64(v) for k, v in w.items()}, **flags)
        return np.asarray(m.sigma_a(lam), np.float64)

    theta = np.asarray(res.theta, np.float64)
    rng = np.random.default_rng(seed)
    cov = 0.5 * (res.cov + res.cov.T)
    th = rng.multivariate_normal(theta, cov, size=draws, method="svd")
    vals = np.where(lin, th, np.exp(np.where(lin, 0.0, th)))
    curves = np.stack([curve(v) for v in vals])
    fit_vals = np.where(lin, theta, np.exp(np.where(lin, 0.0, theta)))
    return curve(fit_vals), np.percentile(curves, 16, 0), np.percentile(curves, 84, 0)


# ------------------------------------------------------------------ figure and outputs
def plot_fit_spectral(res: SpectralFitResult, path: str) -> None:
    """Target vs fitted (and initial) swatches per region, the loss per step, and the fitted
    absorption spectrum with a 1-sigma band vs the initial model and Pope & Fry."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ._spectral import WaterModel, pope_fry_table

    WaterModel = res.model_type or WaterModel  # noqa: N806
    R = len(res.regions)
    fig, (ax, ax2, ax3) = plt.subplots(1, 3, figsize=(15, max(0.9 * R + 2.2, 4.2)),
                                       gridspec_kw={"width_ratios": [1.2, 1, 1.1]})
    plot_swatches_and_loss(res, ax, ax2)
    ax2.set_title("\n".join(f"{k} = {v:.4g} ± {res.params_sd[k]:.2g}"
                            for k, v in res.params.items())
                  + f"\n{res.iterations} steps, {res.wall_seconds:.1f} s", fontsize=8)
    lam = np.linspace(380.0, 720.0, 341)
    mid, lo, hi = absorption_band(res, lam)
    base = dict(res.water or {})
    flags = {k: base.pop(k) for k in ("pure_absorption", "pure_scattering") if k in base}
    b0 = dict(base)
    b0.update(res.init)
    a_init = np.asarray(WaterModel(**{k: np.float64(v) for k, v in b0.items()},
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
        a_true = np.asarray(WaterModel(**{k: np.float64(v) for k, v in bt.items()},
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
    """fit.json + fit.png in out_dir (like `_fit.write_outputs`)."""
    import os

    os.makedirs(out_dir, exist_ok=True)
    jp = os.path.join(out_dir, "fit.json")
    pp = os.path.join(out_dir, "fit.png")
    d = res.to_dict()
    d["mode"] = "spectral"
    with open(jp + ".tmp", "w") as f:
        json.dump(d, f, indent=1)
    os.replace(jp + ".tmp", jp)
    plot_fit_spectral(res, pp)
    return jp, pp
