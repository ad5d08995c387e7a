"""Spectral-mode fitting: the `WaterModel` parameters from region colours (first step).

Same problem, solver and report as `_fit.fit` (see its docstring), but the scenes are
`SpectralScene`s rendered with `render_pass_spectral` (CIE XYZ film) and the parameters
are leaves of the water model, fitted in log space (all of a_cdom, a_flat, b_p, n_p, S are
positive in practice; a parameter at exactly 0 cannot be fitted in log space, start it
small instead):

    sigma_a(lambda) = a_w(lambda) + a_cdom exp(-S (lambda - 440)) + a_flat
    sigma_s(lambda) = b_w(lambda) + b_p (lambda / 550)^-n_p

Common random numbers include the wavelengths: every pass draws its hero wavelength from
its own key, so fixed keys fix the wavelengths too. Not done: a CLI, figures, the issue's
fits 2 and 3 (literature-spectra targets, Jerlov types); `fits/recover_spectral/` is a
synthetic recovery only.
"""

from __future__ import annotations

import dataclasses
import time as _time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._config import RenderConfig
from ._fit import (Region, _colour_constants, _result_name, default_uncertainty, delta_e2000,
                   xyz_to_lab)
from ._render import pass_key
from ._spectral import SpectralScene, render_pass_spectral

PARAMS = ("a_cdom", "S", "a_flat", "b_p", "n_p", "g")


@dataclasses.dataclass
class SpectralFitResult:
    params: dict  # name -> fitted value
    params_sd: dict  # name -> 1 sigma (scaled by the residual variance)
    init: dict
    cov: np.ndarray  # of the log parameters
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

    def to_dict(self) -> dict:
        def f(x):
            return np.asarray(x, np.float64).tolist()

        d = {"params": {k: float(v) for k, v in self.params.items()},
             "params_sd": {k: float(v) for k, v in self.params_sd.items()},
             "init": {k: float(v) for k, v in self.init.items()},
             "cov_log": f(self.cov), "cov_log_unscaled": f(self.cov_unscaled),
             "space": self.space,
             "regions": [{"name": r.name, "scene": r.scene, "rect": list(r.rect),
                          "target": f(self.targets[i]), "fitted": f(self.fitted[i]),
                          "initial": f(self.initial[i]),
                          "delta_e2000": float(self.delta_e2000[i]),
                          "delta_e2000_initial": float(self.delta_e2000_initial[i])}
                         for i, r in enumerate(self.regions)],
             "iterations": self.iterations, "result": self.result,
             "wall_seconds": round(self.wall_seconds, 3), "history": self.history,
             "config": self.config}
        if self.truth:
            d["truth"] = {k: float(v) for k, v in self.truth.items()}
            d["rel_error"] = {k: float(self.params[k] / v - 1) for k, v in self.truth.items()
                              if k in self.params}
        return d


def spectral_region_colours_fn(spectral: Sequence[SpectralScene], regions: Sequence[Region],
                               names: Sequence[str], config: RenderConfig, passes: int,
                               seed: int):
    """log-parameters [n] -> region XYZ [R, 3] (and the merge overflow flag); fixed keys."""
    keys = jnp.stack([pass_key(seed, i) for i in range(passes)])
    idx = jnp.arange(passes, dtype=jnp.int32)

    def fn(theta):
        images = []
        overflow = jnp.zeros((), bool)
        for sp in spectral:
            dt = sp.scene.bounds.dtype
            water = sp.water
            for j, name in enumerate(names):
                water = dataclasses.replace(water, **{name: jnp.exp(theta[j]).astype(dt)})
            sp1 = dataclasses.replace(sp, water=water)

            def one(key, i, sp1=sp1):
                xyz, diag = render_pass_spectral(sp1, key, config, i)
                return xyz, diag.core.merge_overflow

            imgs, ov = jax.vmap(one)(keys, idx)
            images.append(jnp.mean(imgs, axis=0))
            overflow = overflow | jnp.any(ov)
        cols = []
        for r in regions:
            x0, y0, x1, y1 = r.rect
            cols.append(jnp.mean(images[r.scene][y0:y1, x0:x1], axis=(0, 1)))
        return jnp.stack(cols), overflow

    return fn


def fit_spectral(spectral, regions: Sequence[Region], params: Sequence[str] = ("a_cdom", "b_p"),
                 *, space: str = "xyz", init: dict | None = None,
                 config: RenderConfig | None = None, passes: int = 16, seed: int = 0,
                 max_steps: int = 40, rtol: float = 1e-3, atol: float = 1e-3,
                 truth: dict | None = None) -> SpectralFitResult:
    """Fit `params` (names of `WaterModel` leaves, shared by all scenes) so that the region
    colours of the spectral scenes match the targets (in "xyz", "srgb" = linear sRGB, or
    "lab"). init: name -> initial value (default: the first scene's water model)."""
    import optimistix as optx

    t0 = _time.perf_counter()
    from ._fit import _named

    spectral, snames = _named(spectral, SpectralScene)
    for p in params:
        if p not in PARAMS:
            raise ValueError(f"params: unknown {p!r}; one of {', '.join(PARAMS)}")
    if space not in ("xyz", "srgb", "lab"):
        raise ValueError(f"space: unknown {space!r}")
    from ._fit import _resolve

    _, regions, _ = _resolve({k: s.scene for k, s in zip(snames, spectral)}, regions)
    config = config or RenderConfig(algorithm="pt", max_depth=6)
    w0 = spectral[0].water
    init = dict(init or {})
    p0 = np.array([float(init.get(p, np.asarray(getattr(w0, p)))) for p in params])
    if not np.all(p0 > 0):
        raise ValueError("init: every fitted parameter must be > 0 (log-space fit)")
    pdtype = jnp.result_type(float)
    dtype = spectral[0].scene.bounds.dtype
    targets = np.array([r.target for r in regions], np.float64)
    unc = np.array([default_uncertainty(r.target, space) if r.uncertainty is None
                    else r.uncertainty for r in regions], np.float64)
    colours = spectral_region_colours_fn(spectral, regions, list(params), config, passes, seed)
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
        xyz, overflow = colours(y)
        return ((convert(xyz) - tgt) * inv_unc).reshape(-1).astype(pdtype), overflow

    history: list[dict] = []

    def _record(kw):
        history.append({"step": int(kw["num_steps"]), "loss": float(kw["loss_this_step"]),
                        "loss_accepted": float(kw["loss_last_accepted_step"]),
                        "theta": np.asarray(kw["y"], np.float64).tolist()})

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

    y, result, nsteps, overflow, r0, J, r1 = solve(jnp.asarray(np.log(p0), pdtype))
    y = np.asarray(jax.block_until_ready(y), np.float64)
    if bool(overflow):
        raise RuntimeError("fit_spectral: the merging gather overflowed its capacity")
    res = np.asarray(r1, np.float64)
    J = np.asarray(J, np.float64)
    m, n = J.shape
    cov_u = np.linalg.pinv(J.T @ J)
    cov = cov_u * float(res @ res) / max(m - n, 1)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    vals = np.exp(y)
    fitted = res.reshape(-1, 3) * unc + targets
    initial = np.asarray(r0, np.float64).reshape(-1, 3) * unc + targets
    return SpectralFitResult(
        params=dict(zip(params, vals)), params_sd=dict(zip(params, vals * sd)),
        init=dict(zip(params, p0)), cov=cov, cov_unscaled=cov_u, space=space,
        regions=[dataclasses.replace(r, scene=snames[r.scene]) for r in regions],
        targets=targets, fitted=fitted, initial=initial,
        delta_e2000=delta_e2000(targets, fitted, space),
        delta_e2000_initial=delta_e2000(targets, initial, space),
        iterations=int(nsteps), result=_result_name(result),
        wall_seconds=_time.perf_counter() - t0, history=history,
        config={"render": dataclasses.asdict(config), "passes": passes, "seed": seed,
                "n_wavelengths": spectral[0].n_wavelengths, "max_steps": max_steps,
                "rtol": rtol, "atol": atol, "scenes": snames},
        truth=truth)
