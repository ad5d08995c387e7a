"""RGB-mode fit: the water's sigma_a, sigma_s from target colours of image regions.

Problem. Given scenes (all with water) and regions (`Region`: a pixel rectangle of one
scene's image with a target colour and optional 1-sigma uncertainties), find the water's
absorption and scattering coefficients sigma_a, sigma_s (one value per channel, shared by
all scenes: 6 parameters for RGB) such that the rendered region averages match the targets.

Parameters: theta = (ln sigma_a, ln sigma_s), so both stay positive; `free` fits one of
the two alone (the other stays at its initial value). The coefficients stay in
`_bounds.SIGMA_FIT` (the scene files' range, 0 raised to 1e-9 /m): the solver moves an
unbounded variable that equals theta inside the range and approaches its bounds
exponentially in the last e-fold (`_bounds.Bounds`); initial values outside are refused.

Forward model and residuals: `_model` (common random numbers, one compiled program per
group of like scenes; residuals in the target's colour space "srgb" = linear sRGB, "xyz"
or "lab", see `_colour`). Solver and covariance: `_solver` (optimistix Levenberg-Marquardt).

Report: values with 1-sigma uncertainties, sd(sigma) = sigma sd(ln sigma) (delta method);
per-region Delta E 2000 between target and fitted colour (colour-science); iterations;
wall time; whether it converged and what is wrong with it (`_solver.assess`: not
converged, a region more than `max_delta_e` Delta E 2000 off, a coefficient at a bound).

With common random numbers a *fit* is deterministic, but the rendered colours still carry
the Monte Carlo error of `passes` passes: make that error far below the target
tolerance (more passes, larger regions). If the targets come from renders with the same
keys (a synthetic recovery), that error cancels exactly at the truth.
"""

from __future__ import annotations

import dataclasses
import time as _time
from typing import Sequence

import jax.numpy as jnp
import numpy as np

from .._config import RenderConfig
from ._bounds import SIGMA_FIT, Bounds, bound_problems
from ._colour import SPACES, delta_e2000
from ._config import FREE
from ._model import Region, _resolve, region_colours_fn, residuals, size_checks
from ._solver import MAX_DELTA_E, assess, levenberg_marquardt


@dataclasses.dataclass
class FitResult:
    """The result of an RGB fit (`fit`): the fitted coefficients with their uncertainties.

    Also the regions' target, fitted and initial colours, their Delta E 2000, the solver's
    record (iterations, loss history, times) and the config; `to_dict` gives fit.json's
    content. `converged`: optimistix's result is "successful"; `problems`: one line each
    for what is wrong (not converged, fits badly, a coefficient at its bound), empty for a
    good fit (`ok`); `verdict`: one line saying which."""

    sigma_a: np.ndarray  # [C] fitted absorption, 1/m
    sigma_s: np.ndarray  # [C] fitted scattering, 1/m
    sigma_a_sd: np.ndarray  # [C] 1-sigma (scaled by the residual variance)
    sigma_s_sd: np.ndarray
    theta: np.ndarray  # [2C] ln sigma_a, ln sigma_s
    cov: np.ndarray  # [2C, 2C] covariance of theta, (J^T J)^-1 s^2
    cov_unscaled: np.ndarray  # (J^T J)^-1 (the stated uncertainties taken at face value)
    jacobian: np.ndarray  # [m, n] d residual / d (free part of theta) at the solution
    residuals: np.ndarray  # [m] (rendered - target) / uncertainty at the solution
    space: str
    regions: list  # [Region]
    targets: np.ndarray  # [R, 3] in `space`
    fitted: np.ndarray  # [R, 3] rendered colours at the solution, in `space`
    initial: np.ndarray  # [R, 3] rendered colours at the initial guess, in `space`
    delta_e2000: np.ndarray  # [R] target vs fitted
    delta_e2000_initial: np.ndarray  # [R] target vs initial
    iterations: int  # optimistix steps
    result: str  # optimistix RESULTS
    wall_seconds: float  # the whole fit, compilation included
    solve_seconds: float  # optx.least_squares call (compilation included)
    history: list  # per step: {"step", "loss", "loss_accepted", "step_size", "theta"}
    init_sigma_a: np.ndarray
    init_sigma_s: np.ndarray
    config: dict
    truth: dict | None = None  # {"sigma_a", "sigma_s"} if known (synthetic fits)
    converged: bool = False  # optimistix's result is "successful"
    problems: list = dataclasses.field(default_factory=list)  # one line each; [] if good
    verdict: str = ""  # one line: "fit converged: ..." or what is wrong
    at_bound: dict = dataclasses.field(default_factory=dict)  # "sigma_a[2]" -> "upper"
    max_delta_e: float = MAX_DELTA_E  # a worse region fits badly

    @property
    def ok(self) -> bool:
        """Converged, every region within `max_delta_e`, no coefficient at a bound."""
        return not self.problems

    def to_dict(self) -> dict:
        def f(x):
            return np.asarray(x, np.float64).tolist()

        d = {
            "sigma_a": f(self.sigma_a), "sigma_s": f(self.sigma_s),
            "sigma_a_sd": f(self.sigma_a_sd), "sigma_s_sd": f(self.sigma_s_sd),
            "theta": f(self.theta), "cov_theta": f(self.cov),
            "cov_theta_unscaled": f(self.cov_unscaled),
            "init": {"sigma_a": f(self.init_sigma_a), "sigma_s": f(self.init_sigma_s)},
            "space": self.space,
            "regions": [{
                "name": r.name, "scene": r.scene, "rect": list(r.rect),
                "target": f(self.targets[i]), "fitted": f(self.fitted[i]),
                "initial": f(self.initial[i]),
                "delta_e2000": float(self.delta_e2000[i]),
                "delta_e2000_initial": float(self.delta_e2000_initial[i]),
            } for i, r in enumerate(self.regions)],
            "delta_e2000_max": float(np.max(self.delta_e2000)),
            "delta_e2000_mean": float(np.mean(self.delta_e2000)),
            "residual_rms": float(np.sqrt(np.mean(self.residuals ** 2))),
            "iterations": self.iterations, "result": self.result,
            "converged": self.converged, "verdict": self.verdict,
            "problems": list(self.problems), "at_bound": dict(self.at_bound),
            "max_delta_e": self.max_delta_e,
            "wall_seconds": round(self.wall_seconds, 3),
            "solve_seconds": round(self.solve_seconds, 3),
            "history": self.history, "config": self.config,
        }
        if self.truth is not None:
            ta = np.asarray(self.truth["sigma_a"], np.float64)
            ts = np.asarray(self.truth["sigma_s"], np.float64)
            d["truth"] = {"sigma_a": f(ta), "sigma_s": f(ts),
                          "rel_error_sigma_a": f(self.sigma_a / ta - 1),
                          "rel_error_sigma_s": f(self.sigma_s / ts - 1)}
        return d

    def summary(self) -> str:
        def pm(v, s):
            return ", ".join(f"{a:.4g} ± {b:.2g}" for a, b in zip(v, s))

        lines = [f"sigma_a = [{pm(self.sigma_a, self.sigma_a_sd)}] 1/m",
                 f"sigma_s = [{pm(self.sigma_s, self.sigma_s_sd)}] 1/m",
                 f"dE2000 max {np.max(self.delta_e2000):.3g}, mean "
                 f"{np.mean(self.delta_e2000):.3g} (initial max "
                 f"{np.max(self.delta_e2000_initial):.3g}); {self.iterations} steps, "
                 f"{self.result}; {self.wall_seconds:.1f} s",
                 self.verdict]
        return "\n".join(lines)


def fit(scenes, regions: Sequence[Region], *, space: str = "srgb",
        config: RenderConfig | None = None, passes: int = 16, seed: int = 0,
        init_sigma_a=None, init_sigma_s=None, free: str = "both", max_steps: int = 40,
        rtol: float = 1e-4, atol: float = 1e-5, truth: dict | None = None,
        max_delta_e: float = MAX_DELTA_E, progress: bool = False) -> FitResult:
    """Fit the water's sigma_a, sigma_s (shared by all `scenes`) to the region targets.

    scenes: a Scene, a list of Scenes or a dict name -> Scene; regions refer to them by
    index or name. space: colour space of targets and residuals ("srgb" = linear sRGB,
    "xyz", "lab"). config: render configuration (default PT, max_depth 6). passes, seed:
    the fixed keys pass_key(seed, i), i < passes, used at every iterate. init_*: the
    initial guess (default: the first scene's water). free: "both" (6 parameters), or
    "sigma_a" / "sigma_s" alone (the other stays at its initial value); the initial values
    must lie in `SIGMA_FIT`, (1e-9, 1e6) 1/m, and the fitted ones stay there. rtol/atol:
    optimistix's Cauchy termination on theta = ln sigma and on the loss. max_delta_e: a
    region further than this (Delta E 2000) from its target fits badly. See the module
    docstring."""
    t0 = _time.perf_counter()
    if space not in SPACES:
        raise ValueError(f"space: unknown {space!r}; one of {', '.join(SPACES)}")
    if not isinstance(passes, int) or passes < 1:
        raise ValueError(f"passes: must be a positive integer, got {passes!r}")
    config = config or RenderConfig(algorithm="pt", max_depth=6)
    if not max_delta_e > 0:
        raise ValueError(f"max_delta_e: must be > 0, got {max_delta_e!r}")
    scenes, regions, names = _resolve(scenes, regions, space)
    C = scenes[0].channels
    w0 = scenes[0].water
    sa0 = np.asarray(w0.sigma_a if init_sigma_a is None else init_sigma_a, np.float64)
    ss0 = np.asarray(w0.sigma_s if init_sigma_s is None else init_sigma_s, np.float64)
    sa0 = np.broadcast_to(sa0, (C,)).copy()
    ss0 = np.broadcast_to(ss0, (C,)).copy()
    for k, v in (("sigma_a", sa0), ("sigma_s", ss0)):
        if not all(SIGMA_FIT.contains(x) for x in v):  # NaN fails too
            raise ValueError(f"init.{k}: must lie in {SIGMA_FIT.text()} in every channel, "
                             f"got {v.tolist()}")
    if free not in FREE:
        raise ValueError(f"free: unknown {free!r}; one of {', '.join(FREE)}")
    free_idx = {"both": np.arange(2 * C), "sigma_a": np.arange(C),
                "sigma_s": np.arange(C, 2 * C)}[free]
    pnames = [f"{k}[{c}]" for k in ("sigma_a", "sigma_s") for c in range(C)]
    pnames = [pnames[i] for i in free_idx]
    bounds = Bounds.of([SIGMA_FIT] * len(free_idx), [True] * len(free_idx))
    # parameters in the solver's dtype (see `residuals`); the renderer stays in the scene's
    pdtype = jnp.result_type(float)
    theta_host0 = np.concatenate([np.log(sa0), np.log(ss0)])
    theta_full0 = jnp.asarray(theta_host0, pdtype)
    memory = size_checks(scenes, config)  # the image fits int32 indices; later, memory
    colours = region_colours_fn(scenes, regions, config, passes, seed)
    residual_fn, targets, unc = residuals(
        colours, regions, space, "srgb",
        # the free ones through the bounded map, the fixed ones at their initial values
        lambda y: theta_full0.at[free_idx].set(bounds.to_x(y)),
        w0.sigma_a.dtype)
    sol = levenberg_marquardt(residual_fn, jnp.asarray(bounds.to_u(theta_host0[free_idx]),
                                                       pdtype),
                              rtol=rtol, atol=atol, max_steps=max_steps, progress=progress,
                              memory=memory)
    theta = np.asarray(theta_full0, np.float64).copy()
    theta[free_idx] = bounds.to_x_host(sol.y)
    for e in sol.history:  # the solver's variable -> ln sigma
        e["theta"] = bounds.to_x_host(e["theta"]).tolist()
    if sol.overflow:
        raise RuntimeError("fit: the merging gather overflowed its capacity; pass a config "
                           "with more room, config.tuned(merge_capacity=...)")
    rgb0 = sol.r0.reshape(-1, 3) * unc + targets  # initial, in `space`
    res = sol.residuals
    fitted = res.reshape(-1, 3) * unc + targets
    # covariance and Jacobian of theta from those of the solver's u: dtheta = slope du
    g = bounds.slope(sol.y)
    cov_u = np.zeros((2 * C, 2 * C))  # fixed parameters: zero rows and columns
    cov_u[np.ix_(free_idx, free_idx)] = sol.cov_unscaled * np.outer(g, g)
    cov = np.zeros((2 * C, 2 * C))
    cov[np.ix_(free_idx, free_idx)] = sol.cov * np.outer(g, g)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sa, ss = np.exp(theta[:C]), np.exp(theta[C:])
    de = delta_e2000(targets, fitted, space)
    side = bounds.side(sol.y)
    converged, problems, verdict = assess(
        sol.result, sol.steps, de, [r.name for r in regions], max_delta_e,
        bound_problems(pnames, side, [SIGMA_FIT] * len(pnames)))
    return FitResult(
        sigma_a=sa, sigma_s=ss, sigma_a_sd=sa * sd[:C], sigma_s_sd=ss * sd[C:], theta=theta,
        cov=cov, cov_unscaled=cov_u, jacobian=sol.jacobian / np.where(g > 0, g, 1.0),
        residuals=res, space=space,
        regions=[dataclasses.replace(r, scene=names[r.scene]) for r in regions],
        targets=targets, fitted=fitted, initial=rgb0, delta_e2000=de,
        delta_e2000_initial=delta_e2000(targets, rgb0, space),
        iterations=sol.steps, result=sol.result,
        wall_seconds=_time.perf_counter() - t0, solve_seconds=sol.seconds,
        history=sol.history, init_sigma_a=sa0, init_sigma_s=ss0,
        config={"render": config.record(), "passes": passes, "seed": seed,
                "max_steps": max_steps, "rtol": rtol, "atol": atol, "free": free,
                "max_delta_e": max_delta_e,
                "scenes": names, "size": [[s.camera.width, s.camera.height] for s in scenes]},
        truth=truth, converged=converged, problems=problems, verdict=verdict,
        at_bound={n: ("upper" if s > 0 else "lower") for n, s in zip(pnames, side) if s},
        max_delta_e=max_delta_e,
    )
