"""Spectral-mode fit: the `WaterModel` parameters from region colours.

Same problem, forward model, solver and report as the RGB fit (`_rgb`), but the scenes are
`SpectralScene`s rendered with `render_pass_spectral` (CIE XYZ film) and the parameters
are leaves of the water model:

    sigma_a(lambda) = a_w_scale a_w(lambda) + a_cdom exp(-S (lambda - 440)) + a_flat
    sigma_s(lambda) = b_w(lambda) + b_p (lambda / 550)^-n_p

Parameterisation: by default every fitted parameter is fitted in log space (positive by
construction; a parameter at exactly 0 cannot be fitted in log space, start it small or
fit it linearly). Names listed in `linear` are fitted as they are: use it for terms whose
true value may be 0 (a_cdom, a_flat of pure water), where a log fit could only creep
towards -infinity and its Jacobian uncertainty would be meaningless. A negative total
sigma_a is clamped to 0 by the renderer (`SpectralScene.at_wavelengths`). Every leaf stays
in its range (`_bounds.fit_range`: `WATER_RANGES`, a linear leaf whose range starts at 0
mirrored below it), through the bounded map of `_bounds.Bounds`; leaves of a subclass
without a range are unbounded.

Config files (`jaxvcm fit CONFIG` with `mode = "spectral"`): see `_config.CONFIG_DOC`.
"""

from __future__ import annotations

import dataclasses
import time as _time
from typing import Sequence

import jax.numpy as jnp
import numpy as np

from .._config import RenderConfig
from .._spectral import SpectralScene
from .._spectral import WaterModel
from ._bounds import Bounds, bound_problems, fit_range
from ._colour import SPACES, delta_e2000
from ._config import WATER_FIELDS
from ._model import (Region, _named, _resolve, residuals, size_checks,
                     spectral_region_colours_fn)
from ._solver import MAX_DELTA_E, assess, levenberg_marquardt


@dataclasses.dataclass
class SpectralFitResult:
    """The result of a spectral fit (`fit_spectral`): the fitted `WaterModel` parameters.

    Their uncertainties, the regions' target, fitted and initial colours, their Delta E
    2000, the solver's record (iterations, loss history, times) and the config; `to_dict`
    gives fit.json's content. `converged`, `problems`, `verdict`, `at_bound`: as in
    `FitResult`."""

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
    converged: bool = False  # optimistix's result is "successful"
    problems: list = dataclasses.field(default_factory=list)  # one line each; [] if good
    verdict: str = ""  # one line: "fit converged: ..." or what is wrong
    at_bound: dict = dataclasses.field(default_factory=dict)  # name -> "lower" / "upper"
    max_delta_e: float = MAX_DELTA_E  # a worse region fits badly

    @property
    def ok(self) -> bool:
        """Converged, every region within `max_delta_e`, no parameter at a bound."""
        return not self.problems

    def to_dict(self) -> dict:
        def f(x):
            return np.asarray(x, np.float64).tolist()

        d = {"params": {k: float(v) for k, v in self.params.items()},
             "params_sd": {k: float(v) for k, v in self.params_sd.items()},
             "init": {k: float(v) for k, v in self.init.items()},
             "linear": list(self.linear),
             "theta": None if self.theta is None else f(self.theta),
             # cov_log: the covariance of theta, whatever each parameter's space (log for
             # the log-space parameters, linear for `linear` ones)
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
             "converged": self.converged, "verdict": self.verdict,
             "problems": list(self.problems), "at_bound": dict(self.at_bound),
             "max_delta_e": self.max_delta_e,
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
            f"{self.result}; {self.wall_seconds:.1f} s",
            self.verdict])


def fit_spectral(spectral, regions: Sequence[Region],
                 params: Sequence[str] = ("a_cdom", "b_p"),
                 *, space: str = "xyz", init: dict | None = None,
                 config: RenderConfig | None = None, passes: int = 16, seed: int = 0,
                 max_steps: int = 40, rtol: float = 1e-3, atol: float = 1e-3,
                 truth: dict | None = None, linear: Sequence[str] = (),
                 max_delta_e: float = MAX_DELTA_E,
                 progress: bool = False) -> SpectralFitResult:
    """Fit water-model parameters (shared by all `spectral` scenes) to the region targets.

    `params`: names of `WaterModel` leaves, or scalar leaves of a `WaterModel` subclass,
    fitted so that the region colours of the spectral scenes match the targets (in "xyz",
    "srgb" = linear sRGB, or "lab"). init: name -> initial value (default: the first
    scene's water model). linear: names fitted in linear space (may cross 0); the others in
    log space. Every parameter starts and stays inside its range (`_bounds.fit_range`).
    max_delta_e: a region further than this (Delta E 2000) from its target fits badly.
    Uncertainties: sd(p) = p sd(ln p) for log-space parameters, sd(p) for linear ones."""
    t0 = _time.perf_counter()
    spectral, snames = _named(spectral, SpectralScene)
    params = list(params)
    linear = tuple(linear)
    if not params:
        raise ValueError("params: nothing to fit")
    w0 = spectral[0].water
    # WaterModel's leaves, or the scalar leaves of a subclass (e.g. a freer absorption model)
    allowed = list(WATER_FIELDS) + [f.name for f in dataclasses.fields(w0)
                                    if f.name not in WATER_FIELDS
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
    if space not in SPACES:
        raise ValueError(f"space: unknown {space!r}")
    if not isinstance(passes, int) or passes < 1:
        raise ValueError(f"passes: must be a positive integer, got {passes!r}")
    if not max_delta_e > 0:
        raise ValueError(f"max_delta_e: must be > 0, got {max_delta_e!r}")
    _, regions, _ = _resolve({k: s.scene for k, s in zip(snames, spectral)}, regions, space)
    config = config or RenderConfig(algorithm="pt", max_depth=6)
    init = dict(init or {})
    for k in init:
        if k not in params:
            raise ValueError(f"init: {k!r} is not one of the fitted params")
    p0 = np.array([float(init.get(p, np.asarray(getattr(w0, p)))) for p in params])
    lin = np.array([p in linear for p in params])
    ranges = [fit_range(p, p in linear) if p in WATER_FIELDS else None for p in params]
    for p, v, r in zip(params, p0, ranges):
        if not np.isfinite(v):
            raise ValueError(f"init.{p}: must be finite, got {v}")
        if p not in linear and not v > 0:
            raise ValueError(f"init.{p}: must be > 0 for a log-space fit, got {v:g} (every "
                             "fitted parameter not in linear)")
        if r is not None and not r.contains(v):
            raise ValueError(f"init.{p}: must lie in {r.text()}, got {v:g}")
    theta0 = np.where(lin, p0, np.log(np.where(lin, 1.0, p0)))
    bounds = Bounds.of(ranges, ~lin)
    dtype = spectral[0].scene.bounds.dtype
    memory = size_checks([s.scene for s in spectral], config)  # int32 indices; memory
    colours = spectral_region_colours_fn(spectral, regions, params, config, passes, seed,
                                         linear)
    residual_fn, targets, unc = residuals(colours, regions, space, "xyz",
                                          lambda y: bounds.to_x(y).astype(dtype), dtype)
    sol = levenberg_marquardt(residual_fn, jnp.asarray(bounds.to_u(theta0),
                                                       jnp.result_type(float)),
                              rtol=rtol, atol=atol, max_steps=max_steps, progress=progress,
                              step_size=False, memory=memory)
    y = bounds.to_x_host(sol.y)  # theta: ln p or p
    for e in sol.history:  # the solver's variable -> theta
        e["theta"] = bounds.to_x_host(e["theta"]).tolist()
    if sol.overflow:
        raise RuntimeError("fit_spectral: the merging gather overflowed its capacity")
    res = sol.residuals
    g = bounds.slope(sol.y)  # dtheta = slope du
    cov = sol.cov * np.outer(g, g)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    vals = np.where(lin, y, np.exp(np.where(lin, 0.0, y)))
    vals_sd = np.where(lin, sd, vals * sd)
    fitted = res.reshape(-1, 3) * unc + targets
    initial = sol.r0.reshape(-1, 3) * unc + targets
    water = {f.name: getattr(w0, f.name) for f in dataclasses.fields(w0)}
    water = {k: (v if isinstance(v, bool) else float(np.asarray(v))) for k, v in water.items()}
    water.update({p: float(v) for p, v in zip(params, vals)})
    de = delta_e2000(targets, fitted, space)
    side = bounds.side(sol.y)
    converged, problems, verdict = assess(sol.result, sol.steps, de,
                                          [r.name for r in regions], max_delta_e,
                                          bound_problems(params, side, ranges))
    return SpectralFitResult(
        params=dict(zip(params, vals)), params_sd=dict(zip(params, vals_sd)),
        init=dict(zip(params, p0)), cov=cov, cov_unscaled=sol.cov_unscaled * np.outer(g, g),
        space=space, regions=[dataclasses.replace(r, scene=snames[r.scene]) for r in regions],
        targets=targets, fitted=fitted, initial=initial, delta_e2000=de,
        delta_e2000_initial=delta_e2000(targets, initial, space),
        iterations=sol.steps, result=sol.result,
        wall_seconds=_time.perf_counter() - t0, history=sol.history,
        config={"render": config.record(), "passes": passes, "seed": seed,
                "n_wavelengths": spectral[0].n_wavelengths, "max_steps": max_steps,
                "rtol": rtol, "atol": atol, "max_delta_e": max_delta_e, "scenes": snames,
                "size": [[s.scene.camera.width, s.scene.camera.height] for s in spectral]},
        truth=truth, linear=linear, theta=y,
        jacobian=sol.jacobian / np.where(g > 0, g, 1.0), residuals=res,
        solve_seconds=sol.seconds, water=water, model_type=type(w0), converged=converged,
        problems=problems, verdict=verdict,
        at_bound={p: ("upper" if s > 0 else "lower") for p, s in zip(params, side) if s},
        max_delta_e=max_delta_e)


# ------------------------------------------------------------------ absorption spectrum
def absorption_band(res: SpectralFitResult, lam, draws: int = 400, seed: int = 0):
    """sigma_a(lam) of the fitted model, and its 16th/84th percentiles over `draws` samples of
    theta ~ N(theta_hat, Cov) (the Jacobian covariance): (mean curve, lo, hi) [len(lam)].
    Parameters not fitted stay at the model's values."""
    model = res.model_type or WaterModel
    lam = np.asarray(lam, np.float64)
    names = list(res.params)
    lin = np.array([n in res.linear for n in names])
    base = {k: v for k, v in (res.water or {}).items()}

    def curve(vals):
        w = dict(base)
        w.update(dict(zip(names, vals)))
        flags = {k: w.pop(k) for k in ("pure_absorption", "pure_scattering") if k in w}
        m = model(**{k: np.float64(v) for k, v in w.items()}, **flags)
        return np.asarray(m.sigma_a(lam), np.float64)

    theta = np.asarray(res.theta, np.float64)
    rng = np.random.default_rng(seed)
    cov = 0.5 * (res.cov + res.cov.T)
    th = rng.multivariate_normal(theta, cov, size=draws, method="svd")
    vals = np.where(lin, th, np.exp(np.where(lin, 0.0, th)))
    curves = np.stack([curve(v) for v in vals])
    fit_vals = np.where(lin, theta, np.exp(np.where(lin, 0.0, theta)))
    return curve(fit_vals), np.percentile(curves, 16, 0), np.percentile(curves, 84, 0)
