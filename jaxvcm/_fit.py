"""Fitting water coefficients to target colours of image regions (RGB mode).

Problem. Given scenes (all with water) and *regions* -- pixel rectangles
`rect = [x0, y0, x1, y1]` (half-open; x = column, y = row, row 0 at the top of the image,
as in the PNG/EXR the renderer writes) of a scene's camera image -- each with a target
colour and optional 1-sigma uncertainties, find the water's absorption and scattering
coefficients sigma_a, sigma_s (one value per channel, shared by all scenes: 6 parameters
for RGB) such that the rendered region averages match the targets.

Parameters: theta = (ln sigma_a, ln sigma_s), so both stay positive.

Forward model: every scene is rendered with `passes` passes with the fixed keys
`pass_key(seed, i)`, i = 0..passes-1 (common random numbers: the same keys at every
iterate, so the objective is a deterministic function of theta), the passes are
averaged and each region's pixels are averaged into one linear-sRGB colour. Scenes with
the same static structure (same shapes, kinds, image size) are stacked and rendered
with one `vmap`, so they share one compiled program.

Residuals: (rendered - target) / uncertainty, per region and channel, in the target's
colour space: "srgb" (linear sRGB, as rendered), "xyz" (CIE 1931 XYZ via the sRGB
matrix, Y = 1 for linear sRGB white) or "lab" (CIELAB, D65 white with Y_n = 1; the
formula below, differentiable, tested against colour-science). Default uncertainties:
1 Delta E*ab unit in "lab", and 1% of the target (plus 1e-4) in "srgb"/"xyz".

Solver: `optimistix.least_squares` with `optimistix.LevenbergMarquardt`; the Jacobian is
forward mode through the renderer (optimistix linearises with `jax.linearize`, i.e. six
JVPs for six parameters). The loss of every step is recorded with the solver's
`verbose` hook (a `jax.debug.callback`), giving the convergence history without
re-running anything.

Report: values with 1-sigma uncertainties from the Jacobian J of the residuals at the
solution, Cov(theta) = (J^T J)^-1 s^2 with s^2 = sum r^2 / (m - n) (the residual
variance; `cov_unscaled` = (J^T J)^-1 trusts the stated uncertainties instead), and
sd(sigma) = sigma sd(ln sigma) (delta method); per-region Delta E 2000 between target and
fitted colour (colour-science); iterations; wall time.

With common random numbers a *fit* is deterministic, but the rendered colours still carry
the Monte Carlo error of `passes` passes: make that error far below the target
tolerance (more passes, larger regions). If the targets come from renders with the same
keys (a synthetic recovery), that error cancels exactly at the truth.
"""

from __future__ import annotations

import dataclasses
import json
import time as _time
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._config import RenderConfig
from ._render import pass_key, render_pass
from ._scene import Scene

SPACES = ("srgb", "xyz", "lab")
FREE = ("both", "sigma_a", "sigma_s")  # which coefficients a fit adjusts

# ------------------------------------------------------------------ colour conversions
# CIE constants of CIELAB (CIE 15:2004): epsilon = (6/29)^3, kappa = (29/3)^3.
_LAB_EPS = 216.0 / 24389.0
_LAB_KAPPA = 24389.0 / 27.0


def _colour_constants() -> tuple[np.ndarray, np.ndarray]:
    """(linear sRGB -> XYZ matrix [3, 3], D65 white XYZ with Y = 1), from colour-science."""
    import colour

    M = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, np.float64)
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    white = np.asarray(colour.xyY_to_XYZ([xy[0], xy[1], 1.0]), np.float64)
    return M, white


def srgb_to_xyz(rgb, M=None):
    """Linear sRGB [..., 3] -> CIE XYZ [..., 3] (JAX; differentiable)."""
    if M is None:
        M = _colour_constants()[0]
    M = jnp.asarray(M, rgb.dtype)
    return rgb @ M.T


def xyz_to_lab(xyz, white=None):
    """CIE XYZ [..., 3] -> CIELAB [..., 3] (JAX; differentiable), CIE 1976 formula:
    f(t) = t^(1/3) for t > eps, (kappa t + 16) / 116 otherwise, t = X / X_n etc.;
    L = 116 f(Y) - 16, a = 500 (f(X) - f(Y)), b = 200 (f(Y) - f(Z))."""
    if white is None:
        white = _colour_constants()[1]
    t = xyz / jnp.asarray(white, xyz.dtype)
    f = jnp.where(t > _LAB_EPS, jnp.cbrt(jnp.maximum(t, _LAB_EPS)), (_LAB_KAPPA * t + 16.0) / 116.0)
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    return jnp.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)


def to_space(rgb, space: str):
    """Linear sRGB (JAX) -> `space` ("srgb", "xyz", "lab")."""
    if space == "srgb":
        return rgb
    M, white = _colour_constants()
    xyz = srgb_to_xyz(rgb, M)
    return xyz if space == "xyz" else xyz_to_lab(xyz, white)


def to_lab_host(c, space: str) -> np.ndarray:
    """Colours in `space` -> CIELAB (D65) with colour-science (host, float64)."""
    import colour

    c = np.asarray(c, np.float64)
    if space == "lab":
        return c
    M, white = _colour_constants()
    xyz = c @ M.T if space == "srgb" else c
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return np.asarray(colour.XYZ_to_Lab(xyz, xy), np.float64)


def to_srgb_host(c, space: str) -> np.ndarray:
    """Colours in `space` -> linear sRGB (host, float64; for swatches)."""
    import colour

    c = np.asarray(c, np.float64)
    if space == "srgb":
        return c
    M, white = _colour_constants()
    if space == "lab":
        xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
        c = np.asarray(colour.Lab_to_XYZ(c, xy), np.float64)
    return c @ np.linalg.inv(M).T


def delta_e2000(a, b, space: str) -> np.ndarray:
    import colour

    return np.asarray(colour.delta_E(to_lab_host(a, space), to_lab_host(b, space),
                                     method="CIE 2000"), np.float64)


# ------------------------------------------------------------------ problem description
@dataclasses.dataclass(frozen=True)
class Region:
    """One target: the mean colour of pixels [y0:y1, x0:x1] of scene `scene`'s image."""

    name: str
    scene: int | str  # index into the scenes, or a key of a scene dict
    rect: tuple[int, int, int, int]  # x0, y0, x1, y1 (half-open, row 0 at the top)
    target: tuple[float, float, float]  # in the fit's colour space
    uncertainty: tuple[float, float, float] | None = None  # 1 sigma, same space


@dataclasses.dataclass
class FitResult:
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
                 f"{self.result}; {self.wall_seconds:.1f} s"]
        return "\n".join(lines)


# ------------------------------------------------------------------ forward model
def _with_water(scene: Scene, sigma_a, sigma_s) -> Scene:
    return eqx.tree_at(lambda s: (s.water.sigma_a, s.water.sigma_s), scene, (sigma_a, sigma_s))


def _groups(scenes: Sequence[Scene]) -> list[tuple[list[int], Scene]]:
    """Scenes with equal static structure -> (indices, stacked scene with a leading axis)."""
    groups: list[tuple[list[int], list[Scene]]] = []
    for i, s in enumerate(scenes):
        s = dataclasses.replace(s, name="fit")  # the name is static; it must not split groups
        st = jax.tree.structure(s)
        shapes = [(a.shape, a.dtype) for a in jax.tree.leaves(s)]
        for idx, members in groups:
            m0 = members[0]
            if jax.tree.structure(m0) == st and shapes == [(a.shape, a.dtype) for a in
                                                          jax.tree.leaves(m0)]:
                idx.append(i)
                members.append(s)
                break
        else:
            groups.append(([i], [s]))
    return [(idx, jax.tree.map(lambda *a: jnp.stack(a), *members)) for idx, members in groups]


def region_colours_fn(scenes: Sequence[Scene], regions: Sequence[Region], config: RenderConfig,
                      passes: int, seed: int):
    """theta [2C] -> (region colours [R, C] linear sRGB, merge overflow flag): pure, jit- and
    jacfwd-able. Fixed keys pass_key(seed, i) (common random numbers); `fn(theta, keys,
    indices)` renders other passes (keys [P], pass indices [P]) with the same program."""
    groups = _groups(scenes)
    keys = jnp.stack([pass_key(seed, i) for i in range(passes)])
    idx = jnp.arange(passes, dtype=jnp.int32)
    where = {}  # scene index -> (group, position)
    for g, (members, _) in enumerate(groups):
        for p, i in enumerate(members):
            where[i] = (g, p)
    C = scenes[0].channels
    dtype = scenes[0].water.sigma_a.dtype

    def fn(theta, keys=keys, idx=idx):
        sa = jnp.exp(theta[:C]).astype(dtype)
        ss = jnp.exp(theta[C:]).astype(dtype)
        images = []
        overflow = jnp.zeros((), bool)
        for _, stacked in groups:
            def one(scene, key, i):
                img, diag = render_pass(_with_water(scene, sa, ss), key, config, i)
                return img, diag.merge_overflow

            def passes_of(scene):
                imgs, ov = jax.vmap(one, (None, 0, 0))(scene, keys, idx)
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


def _named(items, cls) -> tuple[list, list[str]]:
    """One item of type `cls`, a list, or a name -> item dict: (items, names)."""
    if isinstance(items, cls):
        items = [items]
    if isinstance(items, dict):
        names = list(items)
        return [items[k] for k in names], names
    items = list(items)
    return items, [str(i) for i in range(len(items))]


def _resolve(scenes, regions) -> tuple[list[Scene], list[Region], list[str]]:
    scenes, names = _named(scenes, Scene)
    if not scenes:
        raise ValueError("fit: no scenes")
    if not regions:
        raise ValueError("fit: no regions")
    C = scenes[0].channels
    out = []
    seen = set()
    for r in regions:
        if r.name in seen:
            raise ValueError(f"regions.{r.name}: duplicate region name")
        seen.add(r.name)
        if isinstance(r.scene, str) and not isinstance(r.scene, bool):
            if r.scene not in names:
                raise ValueError(f"regions.{r.name}.scene: unknown scene {r.scene!r} "
                                 f"(one of {', '.join(names)})")
            si = names.index(r.scene)
        else:
            si = int(r.scene)
            if not 0 <= si < len(scenes):
                raise ValueError(f"regions.{r.name}.scene: index {si} out of range")
        s = scenes[si]
        if not s.water.enabled:
            raise ValueError(f"regions.{r.name}.scene: scene {names[si]!r} has no water")
        if s.channels != C:
            raise ValueError(f"regions.{r.name}.scene: scenes differ in channel count")
        x0, y0, x1, y1 = (int(v) for v in r.rect)
        W, H = s.camera.width, s.camera.height
        if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
            raise ValueError(f"regions.{r.name}.rect: {list(r.rect)} is empty or outside the "
                             f"{W}x{H} image (need 0 <= x0 < x1 <= {W}, 0 <= y0 < y1 <= {H})")
        if len(r.target) != 3:
            raise ValueError(f"regions.{r.name}.target: expected 3 numbers")
        if r.uncertainty is not None and (len(r.uncertainty) != 3 or
                                          not all(u > 0 for u in r.uncertainty)):
            raise ValueError(f"regions.{r.name}.uncertainty: expected 3 numbers > 0")
        out.append(dataclasses.replace(r, scene=si, rect=(x0, y0, x1, y1)))
    return scenes, out, names


def default_uncertainty(target, space: str) -> np.ndarray:
    t = np.asarray(target, np.float64)
    if space == "lab":
        return np.ones(3)
    return 0.01 * np.abs(t) + 1e-4


def fit(scenes, regions: Sequence[Region], *, space: str = "srgb",
        config: RenderConfig | None = None, passes: int = 16, seed: int = 0,
        init_sigma_a=None, init_sigma_s=None, free: str = "both", max_steps: int = 40, rtol: float = 1e-4,
        atol: float = 1e-5, truth: dict | None = None, progress: bool = False) -> FitResult:
    """Fit the water's sigma_a, sigma_s (shared by all `scenes`) to the region targets.

    scenes: a Scene, a list of Scenes or a dict name -> Scene; regions refer to them by
    index or name. space: colour space of targets and residuals ("srgb" = linear sRGB,
    "xyz", "lab"). config: render configuration (default PT, max_depth 6). passes, seed:
    the fixed keys pass_key(seed, i), i < passes, used at every iterate. init_*: the
    initial guess (default: the first scene's water). free: "both" (6 parameters), or
    "sigma_a" / "sigma_s" alone (the other stays at its initial value). rtol/atol: optimistix's Cauchy
    termination on theta = ln sigma and on the loss. See the module docstring."""
    import optimistix as optx

    t0 = _time.perf_counter()
    if space not in SPACES:
        raise ValueError(f"space: unknown {space!r}; one of {', '.join(SPACES)}")
    if not isinstance(passes, int) or passes < 1:
        raise ValueError(f"passes: must be a positive integer, got {passes!r}")
    config = config or RenderConfig(algorithm="pt", max_depth=6)
    scenes, regions, names = _resolve(scenes, regions)
    C = scenes[0].channels
    w0 = scenes[0].water
    sa0 = np.asarray(w0.sigma_a if init_sigma_a is None else init_sigma_a, np.float64)
    ss0 = np.asarray(w0.sigma_s if init_sigma_s is None else init_sigma_s, np.float64)
    sa0 = np.broadcast_to(sa0, (C,)).copy()
    ss0 = np.broadcast_to(ss0, (C,)).copy()
    if not (np.all(sa0 > 0) and np.all(ss0 > 0)):
        raise ValueError("init: sigma_a and sigma_s must be > 0 in every channel "
                         "(the fit works in log space)")
    dtype = w0.sigma_a.dtype
    # the solver's dtype: optimistix builds its damping terms in the default float type,
    # which is float64 under jax_enable_x64; parameters and residuals follow it (the
    # renderer stays in the scene's dtype)
    pdtype = jnp.result_type(float)
    targets = np.array([r.target for r in regions], np.float64)
    unc = np.array([default_uncertainty(r.target, space) if r.uncertainty is None
                    else r.uncertainty for r in regions], np.float64)
    colours = region_colours_fn(scenes, regions, config, passes, seed)
    tgt = jnp.asarray(targets, dtype)
    inv_unc = jnp.asarray(1.0 / unc, dtype)

    if free not in FREE:
        raise ValueError(f"free: unknown {free!r}; one of {', '.join(FREE)}")
    free_idx = {"both": np.arange(2 * C), "sigma_a": np.arange(C),
                "sigma_s": np.arange(C, 2 * C)}[free]
    theta_full0 = jnp.asarray(np.concatenate([np.log(sa0), np.log(ss0)]), pdtype)

    def residual_fn(y, args):
        theta = theta_full0.at[free_idx].set(y)  # the fixed ones stay at their initial value
        rgb, overflow = colours(theta)
        r = (to_space(rgb, space) - tgt) * inv_unc
        return r.reshape(-1).astype(pdtype), overflow

    history: list[dict] = []

    def _record(kw):
        history.append({
            "step": int(kw["num_steps"]), "loss": float(kw["loss_this_step"]),
            "loss_accepted": float(kw["loss_last_accepted_step"]),
            "step_size": float(kw["step_size"]),
            "theta": np.asarray(kw["y"], np.float64).tolist(),
        })
        if progress:
            print(f"  step {history[-1]['step']:3d}  loss {history[-1]['loss']:.6g}", flush=True)

    def verbose(**kw):
        jax.debug.callback(_record, {k: v[1] for k, v in kw.items()
                                     if k in ("num_steps", "loss_this_step",
                                              "loss_last_accepted_step", "step_size", "y")})

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)
    theta0 = theta_full0[free_idx]

    @jax.jit
    def solve(theta0):
        sol = optx.least_squares(residual_fn, solver, theta0, has_aux=True,
                                 max_steps=max_steps, throw=False)
        r0, _ = residual_fn(theta0, None)
        # residuals and Jacobian at the last accepted iterate (= sol.value), from the
        # solver's state: no further copies of the renderer in this program
        r1 = sol.state.f_info.residual
        J = sol.state.f_info.jac.as_matrix()
        return sol.value, sol.result, sol.stats["num_steps"], sol.aux, r0, J, r1

    t1 = _time.perf_counter()
    y, result, nsteps, overflow, r0, J, r1 = solve(theta0)
    theta = np.asarray(theta_full0, np.float64).copy()
    theta[free_idx] = np.asarray(jax.block_until_ready(y), np.float64)
    solve_seconds = _time.perf_counter() - t1
    if bool(overflow):
        raise RuntimeError("fit: the merging gather overflowed its capacity; raise "
                           "RenderConfig.merge_capacity")
    rgb0 = np.asarray(r0, np.float64).reshape(-1, 3) * unc + targets  # initial, in `space`
    res = np.asarray(r1, np.float64)
    fitted = res.reshape(-1, 3) * unc + targets
    J = np.asarray(J, np.float64)
    m, n = J.shape
    JtJ = J.T @ J
    cov_u = np.zeros((2 * C, 2 * C))  # fixed parameters: zero rows and columns
    cov_u[np.ix_(free_idx, free_idx)] = np.linalg.pinv(JtJ)
    s2 = float(res @ res) / max(m - n, 1)
    cov = cov_u * s2
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sa, ss = np.exp(theta[:C]), np.exp(theta[C:])
    return FitResult(
        sigma_a=sa, sigma_s=ss, sigma_a_sd=sa * sd[:C], sigma_s_sd=ss * sd[C:], theta=theta,
        cov=cov, cov_unscaled=cov_u, jacobian=J, residuals=res, space=space,
        regions=[dataclasses.replace(r, scene=names[r.scene]) for r in regions],
        targets=targets, fitted=fitted, initial=rgb0,
        delta_e2000=delta_e2000(targets, fitted, space),
        delta_e2000_initial=delta_e2000(targets, rgb0, space),
        iterations=int(nsteps), result=_result_name(result),
        wall_seconds=_time.perf_counter() - t0, solve_seconds=solve_seconds,
        history=history, init_sigma_a=sa0, init_sigma_s=ss0,
        config={"render": dataclasses.asdict(config), "passes": passes, "seed": seed,
                "max_steps": max_steps, "rtol": rtol, "atol": atol, "free": free,
                "scenes": names, "size": [[s.camera.width, s.camera.height] for s in scenes]},
        truth=truth,
    )


def _result_name(result) -> str:
    import optimistix as optx

    for name in ("successful", "max_steps_reached", "nonlinear_max_steps_reached",
                 "nonlinear_divergence", "singular"):
        v = getattr(optx.RESULTS, name, None)
        if v is not None and bool(result == v):
            return name
    return "failed"


# ------------------------------------------------------------------ figure
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
    txt = "\n".join([f"sa = " + ", ".join(f"{v:.4g}" for v in res.sigma_a),
                     f"ss = " + ", ".join(f"{v:.4g}" for v in res.sigma_s),
                     f"{res.iterations} steps, {res.wall_seconds:.1f} s"])
    ax2.set_title(txt, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(res: FitResult, out_dir: str) -> tuple[str, str]:
    import os

    os.makedirs(out_dir, exist_ok=True)
    jp = os.path.join(out_dir, "fit.json")
    pp = os.path.join(out_dir, "fit.png")
    with open(jp + ".tmp", "w") as f:
        json.dump(res.to_dict(), f, indent=1)
    os.replace(jp + ".tmp", jp)
    plot_fit(res, pp)
    return jp, pp


# ------------------------------------------------------------------ TOML configs
CONFIG_DOC = """Fit config (TOML), for `jaxvcm fit CONFIG [--out DIR]`:

  mode = "rgb"                        # rgb (default) | spectral
  space = "srgb"                      # targets' colour space: srgb (linear) | xyz | lab
  [render]    algorithm = "pt", max_depth = 6, rr_depth, radius, passes = 16, seed = 0,
              width, height           (image size of every scene; default: the files')
  [solver]    max_steps = 40, rtol = 1e-4, atol = 1e-5,
              free = "both" | "sigma_a" | "sigma_s"   (RGB only: which coefficients are fitted)
  [init]      sigma_a, sigma_s        (spectra; default: the first scene's water)
  [truth]     sigma_a, sigma_s        (optional; only reported: relative errors)
  [scenes.NAME]  file = "scene.toml"  (relative to the config file)
                 override = { ... }   (tables deep-merged into the scene file, e.g.
                                       override.materials.floor.albedo = 0.02)
  [[regions]] name, scene = NAME, rect = [x0, y0, x1, y1] (pixels, half-open, row 0 at
              the top), target = [3 numbers], uncertainty = number | [3 numbers] (optional)

Spectral mode (mode = "spectral"; jaxvcm.fit_spectral, the scenes upsampled with
jaxvcm.spectral_scene; the water is a jaxvcm.WaterModel, the scenes' RGB sigma_a and
sigma_s are not used):

  params = ["a_cdom", ...]            # fitted WaterModel leaves: a_cdom, S, a_flat, b_p, n_p,
                                      # g, a_w_scale (required)
  linear = ["a_cdom", ...]            # fitted as they are (may cross 0); the others in log
                                      # space (default: none)
  [spectral]  n_wavelengths = 8, ior = "data" | "scene" | number, phase = "auto" | "scene",
              sun = "D65" | "blackbody", sun_temperature = 5778, dispersion = false
  [water]     the model's fixed fields (and the default initial values): a_cdom, S, a_flat,
              b_p, n_p, g, a_w_scale (numbers), pure_absorption, pure_scattering (booleans);
              default: pure water
  [init]      NAME = value for names in params (default: [water]'s value)
  [truth]     NAME = value (optional; only reported: errors)
  [solver]    max_steps, rtol, atol (no free)
"""

WATER_FIELDS = ("a_cdom", "S", "a_flat", "b_p", "n_p", "g", "a_w_scale")
WATER_FLAGS = ("pure_absorption", "pure_scattering")
SPECTRAL_KEYS = ("params", "linear", "spectral", "water")  # top-level, spectral mode only


class FitConfigError(ValueError):
    """A malformed fit config. str() is one line: 'FILE: FIELD: problem'."""


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else v
    return out


def load_fit_config(path) -> dict:
    """Parse and validate a fit config -> keyword arguments of `fit` (scenes loaded).
    A spectral config (mode = "spectral") gives the keyword arguments of
    `fit_spectral` plus mode = "spectral" (scenes upsampled to `SpectralScene`s)."""
    import math
    import os
    import tomllib

    from ._loader import _Ctx, scene_from_dict

    src = os.fspath(path)

    class Ctx(_Ctx):
        def fail(self, field, msg):
            raise FitConfigError(f"{self.src}: {field}: {msg}")

    ctx = Ctx(src)
    try:
        with open(src, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise FitConfigError(f"{src}: file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise FitConfigError(f"{src}: TOML syntax: {e}") from None
    mode = ctx.string(doc.get("mode", "rgb"), "mode", ("rgb", "spectral"))
    spectral = mode == "spectral"
    top = {"mode", "space", "render", "solver", "init", "truth", "scenes", "regions"}
    if not spectral:
        for k in SPECTRAL_KEYS:
            if k in doc:
                ctx.fail(k, 'only in spectral configs (mode = "spectral")')
    else:
        top |= set(SPECTRAL_KEYS)
    ctx.table(doc, top, {"scenes", "regions"} | ({"params"} if spectral else set()), "")
    space = ctx.string(doc.get("space", "srgb"), "space", SPACES)
    r = doc.get("render", {})
    ctx.table(r, {"algorithm", "max_depth", "rr_depth", "radius", "passes", "seed", "width",
                  "height"}, set(), "render")
    from ._config import ALGORITHMS

    cfg = {"algorithm": ctx.string(r.get("algorithm", "pt"), "render.algorithm", ALGORITHMS)}
    for k in ("max_depth", "rr_depth"):
        if k in r:
            cfg[k] = ctx.integer(r[k], f"render.{k}")
    cfg.setdefault("max_depth", 6)
    if "radius" in r:
        cfg["radius"] = ctx.number(r["radius"], "render.radius", positive=True)
    config = RenderConfig(**cfg)
    passes = ctx.integer(r.get("passes", 16), "render.passes")
    seed = ctx.integer(r.get("seed", 0), "render.seed", lo=0)
    width = ctx.integer(r["width"], "render.width") if "width" in r else None
    height = ctx.integer(r["height"], "render.height") if "height" in r else None
    s = doc.get("solver", {})
    ctx.table(s, {"max_steps", "rtol", "atol"} | (set() if spectral else {"free"}), set(),
              "solver")
    free = ctx.string(s.get("free", "both"), "solver.free", FREE)
    max_steps = ctx.integer(s.get("max_steps", 40), "solver.max_steps")
    rtol = ctx.number(s.get("rtol", 1e-4), "solver.rtol", positive=True)
    atol = ctx.number(s.get("atol", 1e-5), "solver.atol", positive=True)

    if spectral:
        sp = _spectral_settings(ctx, doc)
    else:
        def spectra(table, field, required):
            if table is None:
                return None
            ctx.table(table, {"sigma_a", "sigma_s"}, required, field)
            out = {}
            for k in ("sigma_a", "sigma_s"):
                if k in table:
                    v = ctx.spectrum(table[k], f"{field}.{k}")
                    if not np.all(v > 0):
                        ctx.fail(f"{field}.{k}", "must be > 0 in every channel (log-space fit)")
                    out[k] = v
            return out

        init = spectra(doc.get("init"), "init", set()) or {}
        truth = spectra(doc.get("truth"), "truth", {"sigma_a", "sigma_s"})

    sc = doc["scenes"]
    if not isinstance(sc, dict) or not sc:
        ctx.fail("scenes", "expected a table of named scenes ([scenes.NAME] file = ...)")
    base = os.path.dirname(os.path.abspath(src))
    scenes = {}
    for name, e in sc.items():
        ctx.table(e, {"file", "override"}, {"file"}, f"scenes.{name}")
        f = ctx.string(e["file"], f"scenes.{name}.file")
        fp = f if os.path.isabs(f) else os.path.join(base, f)
        fshow = os.path.relpath(fp) if not os.path.isabs(f) else f
        try:
            with open(fp, "rb") as fh:
                sdoc = tomllib.load(fh)
        except FileNotFoundError:
            ctx.fail(f"scenes.{name}.file", f"file not found: {fshow}")
        except tomllib.TOMLDecodeError as err:
            raise FitConfigError(f"{fshow}: TOML syntax: {err}") from None
        ov = e.get("override", {})
        if not isinstance(ov, dict):
            ctx.fail(f"scenes.{name}.override", "expected a table")
        scene = scene_from_dict(_deep_merge(sdoc, ov), fshow, width=width, height=height)
        if not scene.water.enabled:
            ctx.fail(f"scenes.{name}", "the scene has no water to fit")
        scenes[name] = scene

    regs = doc["regions"]
    if not isinstance(regs, list) or not regs:
        ctx.fail("regions", "expected an array of tables ([[regions]])")
    regions = []
    for i, e in enumerate(regs):
        fld = f"regions[{i}]"
        ctx.table(e, {"name", "scene", "rect", "target", "uncertainty"},
                  {"name", "scene", "rect", "target"}, fld)
        nm = ctx.string(e["name"], f"{fld}.name")
        scn = ctx.string(e["scene"], f"{fld}.scene")
        if scn not in scenes:
            ctx.fail(f"{fld}.scene", f"unknown scene {scn!r} (one of: {', '.join(scenes)})")
        rect = e["rect"]
        if not isinstance(rect, list) or len(rect) != 4:
            ctx.fail(f"{fld}.rect", "expected [x0, y0, x1, y1]")
        rect = [ctx.integer(v, f"{fld}.rect[{j}]", lo=0) for j, v in enumerate(rect)]
        cam = scenes[scn].camera
        if not (rect[0] < rect[2] <= cam.width and rect[1] < rect[3] <= cam.height):
            ctx.fail(f"{fld}.rect", f"{rect} is empty or outside the {cam.width}x{cam.height} "
                                    "image (need x0 < x1 <= width, y0 < y1 <= height)")
        tgt = ctx.vec(e["target"], f"{fld}.target")
        unc = None
        if "uncertainty" in e:
            u = e["uncertainty"]
            unc = (ctx.vec(u, f"{fld}.uncertainty") if isinstance(u, list)
                   else np.full(3, ctx.number(u, f"{fld}.uncertainty")))
            if not np.all(unc > 0):
                ctx.fail(f"{fld}.uncertainty", "must be > 0")
            unc = tuple(float(x) for x in unc)
        if any(rg.name == nm for rg in regions):
            ctx.fail(f"{fld}.name", f"duplicate region name {nm!r}")
        regions.append(Region(nm, scn, tuple(rect), tuple(float(x) for x in tgt), unc))
    if not all(math.isfinite(x) for r in regions for x in r.target):  # pragma: no cover
        ctx.fail("regions", "targets must be finite")
    if spectral:
        from ._spectral import WaterModel, spectral_scene

        model = WaterModel(**sp["water"])
        try:
            sps = {k: spectral_scene(v, model, **sp["scene_kw"]) for k, v in scenes.items()}
        except ValueError as err:  # pragma: no cover (the settings are validated above)
            ctx.fail("spectral", str(err))
        return dict(mode="spectral", spectral=sps, regions=regions, params=sp["params"],
                    space=space, init=sp["init"], config=config, passes=passes, seed=seed,
                    max_steps=max_steps, rtol=rtol, atol=atol, truth=sp["truth"],
                    linear=sp["linear"])
    return dict(scenes=scenes, regions=regions, space=space, config=config, passes=passes,
                seed=seed, init_sigma_a=init.get("sigma_a"), init_sigma_s=init.get("sigma_s"),
                free=free, max_steps=max_steps, rtol=rtol, atol=atol, truth=truth)


def _spectral_settings(ctx, doc) -> dict:
    """The spectral-only parts of a fit config: params, linear, [spectral], [water], [init],
    [truth] (validated; one-line errors naming the field)."""
    from ._fit_spectral import PARAMS

    def names(v, field):
        if not isinstance(v, list):
            ctx.fail(field, "expected a list of parameter names")
        out = []
        for j, x in enumerate(v):
            x = ctx.string(x, f"{field}[{j}]", PARAMS)
            if x in out:
                ctx.fail(f"{field}[{j}]", f"{x!r} listed twice")
            out.append(x)
        return out

    params = names(doc["params"], "params")
    if not params:
        ctx.fail("params", f"nothing to fit (list some of {', '.join(PARAMS)})")
    linear = names(doc.get("linear", []), "linear")
    for j, x in enumerate(linear):
        if x not in params:
            ctx.fail(f"linear[{j}]", f"{x!r} is not in params")

    spt = doc.get("spectral", {})
    ctx.table(spt, {"n_wavelengths", "ior", "phase", "sun", "sun_temperature", "dispersion"},
              set(), "spectral")
    kw = {"n_wavelengths": ctx.integer(spt.get("n_wavelengths", 8), "spectral.n_wavelengths")}
    ior = spt.get("ior", "data")
    if isinstance(ior, str):
        kw["ior"] = ctx.string(ior, "spectral.ior", ("data", "scene"))
    else:
        kw["ior"] = ctx.number(ior, "spectral.ior", positive=True)
    kw["phase"] = ctx.string(spt.get("phase", "auto"), "spectral.phase", ("auto", "scene"))
    kw["sun"] = ctx.string(spt.get("sun", "D65"), "spectral.sun", ("D65", "blackbody"))
    kw["sun_temperature"] = ctx.number(spt.get("sun_temperature", 5778.0),
                                       "spectral.sun_temperature", positive=True)
    disp = spt.get("dispersion", False)
    if not isinstance(disp, bool):
        ctx.fail("spectral.dispersion", f"expected true or false, got {type(disp).__name__}")
    kw["dispersion"] = disp

    wt = doc.get("water", {})
    ctx.table(wt, set(WATER_FIELDS) | set(WATER_FLAGS), set(), "water")
    water = {}
    for k in WATER_FIELDS:
        if k in wt:
            if k == "g":
                v = ctx.number(wt[k], "water.g")
                if not -1.0 < v < 1.0:
                    ctx.fail("water.g", f"must be in (-1, 1), got {v}")
            else:
                v = ctx.number(wt[k], f"water.{k}", nonneg=True)
            water[k] = v
    for k in WATER_FLAGS:
        if k in wt:
            if not isinstance(wt[k], bool):
                ctx.fail(f"water.{k}", f"expected true or false, got {type(wt[k]).__name__}")
            water[k] = wt[k]
    defaults = {"a_cdom": 0.0, "S": 0.015, "a_flat": 0.0, "b_p": 0.0, "n_p": 1.0, "g": 0.9,
                "a_w_scale": 1.0}

    def values(table, field, allowed):
        if table is None:
            return None
        ctx.table(table, set(allowed), set(), field)
        return {k: ctx.number(v, f"{field}.{k}") for k, v in table.items()}

    init = values(doc.get("init"), "init", params) or {}
    for k in params:
        v = init.get(k, water.get(k, defaults[k]))
        if k not in linear and not v > 0:
            ctx.fail(f"init.{k}", f"must be > 0 for a log-space fit, got {v} (set init.{k}, "
                                  "or list it in linear)")
        init[k] = v
    truth = values(doc.get("truth"), "truth", PARAMS)
    return {"params": params, "linear": linear, "scene_kw": kw, "water": water,
            "init": init, "truth": truth}
