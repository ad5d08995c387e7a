"""Image-space losses that stay unbiased under caustic fireflies.

Why an image-L2 fit drifts. With common random numbers (fixed keys) a rendered pixel is
R_p(theta) = n_p g_p(theta), where g_p is its expectation and n_p a mean-1 noise factor
that does not change with theta (the same paths are re-weighted). Fitting one brightness
scale s (R_p -> s R_p) to a converged target t_p = g_p(theta*) by per-pixel least squares
gives

    s = sum_p w_p R_p t_p / sum_p w_p R_p^2            (`ls_scale`; w_p = 1: plain L2)
      ~ E[n g^2] / E[n^2 g^2] = 1 / (1 + var n)        (n independent of g),

so the model must be darkened by 1 / (1 + var n) to "match": heavy-tailed noise (caustic
fireflies, var n >> 1) pushes sigma_a *up*, by ln(1 + var n) / L where
L = -d ln g / d sigma_a is the mean path length in water. A region average replaces n_p
by the mean of pixels x passes samples: var n shrinks by that count and the drift with it.

This module renders the image and its Jacobian once per iterate (`image_model`), so every
loss that is a linear function of the image -- per-pixel residuals, region averages --
reuses one compiled program, and fits them with a small host-side Levenberg-Marquardt
(`lm_fit`), iteratively reweighted least squares (`irls_fit`: robust Cauchy/Huber
weights recomputed between LM solves) or the decorrelated estimating equation
(`decorrelated_fit`: Jacobian from keys independent of the residual's). `ls_scale`,
`irls_scale` and `predict_exp` predict where a loss's minimum lies from the noise of a
render at the truth. `jaxvcm.fit` (optimistix) remains the fitting API; this is study code for
fits/caustic_robustness (run.py), on jaxvcm's public API only.

`lm_fit` is not `jaxvcm`'s optimistix driver: it takes the Jacobian from the same model
call as the image (one render per step), clips steps to 2 in ln sigma, and stops on the
step size and the relative loss decrease; switching would change the study's recorded
results (result.json, NOTES.md).

Robust weights are not a cure for this drift: when per-pixel noise is Poisson-like there
are no outliers to reject, and when there are, rejecting them leaves the bulk of a skewed
estimator, which lies below its mean (tests/fit/test_fit_robust.py). Average, or decorrelate.
"""

from __future__ import annotations

import time as _time
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxvcm import RenderConfig, Scene, pass_key, render_pass


def _with_water(scene: Scene, sigma_a, sigma_s) -> Scene:
    return eqx.tree_at(lambda s: (s.water.sigma_a, s.water.sigma_s), scene, (sigma_a, sigma_s))


# ------------------------------------------------------------------ forward model
def keys_for(seed: int, passes: int):
    """The fixed keys pass_key(seed, i), i < passes (as `jaxvcm.fit` uses them)."""
    return jnp.stack([pass_key(seed, i) for i in range(passes)])


def image_model(scene: Scene, config: RenderConfig, *, sigma_s=None):
    """-> jitted f(theta, keys) = (image [H, W, C], d image / d theta [H, W, C, C]) with
    theta = ln sigma_a [C] (sigma_s fixed: `sigma_s` or the scene's), the image the mean of
    the passes with keys `keys` [P] (pass indices 0..P-1). Keys are an argument, so other
    seeds reuse the compiled program. Forward mode (`jax.jacfwd`: C JVPs)."""
    ss = (scene.water.sigma_s if sigma_s is None
          else jnp.asarray(sigma_s, scene.water.sigma_s.dtype))
    dtype = scene.water.sigma_a.dtype

    def image(theta, keys):
        sc = _with_water(scene, jnp.exp(theta).astype(dtype), ss)
        idx = jnp.arange(keys.shape[0], dtype=jnp.int32)
        imgs = jax.vmap(lambda k, i: render_pass(sc, k, config, i)[0])(keys, idx)
        return jnp.mean(imgs, axis=0)

    @jax.jit
    def f(theta, keys):
        theta = jnp.asarray(theta, dtype)
        return image(theta, keys), jax.jacfwd(image)(theta, keys)

    return f


def render_passes(scene: Scene, config: RenderConfig, seed: int, passes: int,
                  sigma_a=None) -> np.ndarray:
    """Per-pass images [P, H, W, C] (float64) with keys pass_key(seed, i): for targets and
    their per-pass standard errors."""
    if sigma_a is not None:
        scene = _with_water(scene, jnp.asarray(sigma_a, scene.water.sigma_a.dtype),
                            scene.water.sigma_s)
    rp = jax.jit(lambda s, k, i: render_pass(s, k, config, i)[0])
    return np.stack([np.asarray(rp(scene, pass_key(seed, i), i), np.float64)
                     for i in range(passes)])


# ------------------------------------------------------------------ linear losses
def pixel_operator(H: int, W: int, rect) -> np.ndarray:
    """[m, H*W] selection matrix: every pixel of rect (x0, y0, x1, y1) its own residual."""
    x0, y0, x1, y1 = rect
    rows = [y * W + x for y in range(y0, y1) for x in range(x0, x1)]
    A = np.zeros((len(rows), H * W))
    A[np.arange(len(rows)), rows] = 1.0
    return A


def region_operator(H: int, W: int, rects) -> np.ndarray:
    """[R, H*W] averaging matrix: one row per rect (x0, y0, x1, y1), the mean of its pixels."""
    A = np.zeros((len(rects), H * W))
    for i, (x0, y0, x1, y1) in enumerate(rects):
        m = np.zeros((H, W))
        m[y0:y1, x0:x1] = 1.0 / ((x1 - x0) * (y1 - y0))
        A[i] = m.reshape(-1)
    return A


def tile_rects(rect, tile: int) -> list[tuple[int, int, int, int]]:
    """Split rect into tile x tile blocks (the last row/column of blocks may be smaller)."""
    x0, y0, x1, y1 = rect
    return [(x, y, min(x + tile, x1), min(y + tile, y1))
            for y in range(y0, y1, tile) for x in range(x0, x1, tile)]


class LinearLoss:
    """Residuals r = (A vec(image) - b) / sigma, [m, C] flattened, A [m, H*W] shared by the
    channels; b, sigma [m, C]. Per-pixel L2 and region averages are both of this form."""

    def __init__(self, A, b, sigma):
        self.A = np.asarray(A, np.float64)
        self.b = np.asarray(b, np.float64)
        self.sigma = np.broadcast_to(np.asarray(sigma, np.float64), self.b.shape).copy()

    def __call__(self, img, jac):
        H, W, C = img.shape
        I = np.asarray(img, np.float64).reshape(H * W, C)
        r = (self.A @ I - self.b) / self.sigma
        Jr = None
        if jac is not None:
            n = jac.shape[-1]
            Jm = np.asarray(jac, np.float64).reshape(H * W, C * n)
            Jr = (self.A @ Jm).reshape(-1, C, n) / self.sigma[..., None]
            Jr = Jr.reshape(-1, n)
        return r.reshape(-1), Jr

    @classmethod
    def from_target(cls, A, target_img, sigma):
        H, W, C = target_img.shape
        return cls(A, A @ np.asarray(target_img, np.float64).reshape(H * W, C), sigma)


def region_standard_errors(A, passes_imgs: np.ndarray, fit_passes: int) -> tuple:
    """Region means of the per-pass images [P, H, W, C] and the 1-sigma Monte Carlo error of
    (a) the mean of those P passes (the target) and (b) a `fit_passes`-pass render:
    sd over passes / sqrt(P) and / sqrt(fit_passes). Computed from the target's passes, so
    the uncertainties do not depend on the fit render's own noise (weights estimated from
    the fit render itself would correlate with its fireflies)."""
    P, H, W, C = passes_imgs.shape
    per = np.einsum("mk,pkc->pmc", A, passes_imgs.reshape(P, H * W, C))
    sd = per.std(axis=0, ddof=1)
    return per.mean(axis=0), sd / np.sqrt(P), sd / np.sqrt(fit_passes)


# ------------------------------------------------------------------ robust weights
def mad_scale(r) -> float:
    """Robust scale of residuals: 1.4826 median |r - median r| (= sd for a Gaussian)."""
    r = np.asarray(r, np.float64)
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def cauchy_weights(r, c: float) -> np.ndarray:
    """IRLS weights of the Cauchy (Lorentzian) loss rho(r) = c^2/2 ln(1 + (r/c)^2):
    w = rho'(r) / r = 1 / (1 + (r/c)^2)."""
    u = np.asarray(r, np.float64) / c
    return 1.0 / (1.0 + u * u)


def huber_weights(r, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss: 1 for |r| <= k, k / |r| beyond."""
    a = np.abs(np.asarray(r, np.float64))
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))


CAUCHY_C = 2.3849  # 95% efficiency at the Gaussian (Holland & Welsch 1977)
HUBER_K = 1.345  # likewise


def robust_weights(r, kind: str = "cauchy", scale: float | None = None,
                   channels: int | None = None) -> np.ndarray:
    """Weights of residuals r with the MAD scale (or `scale`) and the 95%-efficient
    tuning constant of `kind` ("cauchy" | "huber"). With `channels`, r is [m * channels]
    in channel-minor order and each channel gets its own MAD scale."""
    if channels is not None and scale is None:
        rr = np.asarray(r, np.float64).reshape(-1, channels)
        return np.stack([robust_weights(rr[:, c], kind) for c in range(channels)],
                        axis=1).reshape(-1)
    s = mad_scale(r) if scale is None else scale
    s = max(s, 1e-12)
    if kind == "cauchy":
        return cauchy_weights(np.asarray(r) / s, CAUCHY_C)
    if kind == "huber":
        return huber_weights(np.asarray(r) / s, HUBER_K)
    raise ValueError(f"kind: unknown {kind!r}; cauchy | huber")


# ------------------------------------------------------------------ mechanism
def ls_scale(R, T, w=None, axis=None):
    """Least-squares brightness scale of a model image R against a target T:
    argmin_s sum w (s R - T)^2 = sum w R T / sum w R^2 (over `axis`)."""
    R = np.asarray(R, np.float64)
    T = np.asarray(T, np.float64)
    w = np.ones_like(R) if w is None else np.broadcast_to(np.asarray(w, np.float64), R.shape)
    return np.sum(w * R * T, axis=axis) / np.sum(w * R * R, axis=axis)


def irls_scale(R, T, sigma, kind="cauchy", iters=50):
    """The robust analogue of `ls_scale` (one scale per channel; R, T, sigma [m, C]):
    IRLS on r = (s R - T) / sigma with weights from `robust_weights` (one MAD scale per
    channel, as `irls_fit(..., channels=C)`) -> (s [C], weights [m, C])."""
    R, T, sigma = (np.asarray(a, np.float64) for a in (R, T, sigma))
    sigma = np.broadcast_to(sigma, R.shape)
    s = ls_scale(R / sigma, T / sigma, axis=0)
    for _ in range(iters):
        w = robust_weights(((s * R - T) / sigma).reshape(-1), kind,
                           channels=R.shape[1]).reshape(R.shape)
        s = ls_scale(R / sigma, T / sigma, w, axis=0)
    return s, w


def predict_exp(A, R, l, b, sigma, sigma_true, kind: str | None = None, iters: int = 30):
    """Where a loss's minimum lies, predicted from the noise at the truth alone.

    Per-pixel exponential model around the truth: R_p(sigma) = R_p exp(-l_p (sigma -
    sigma_true)) per channel, with l_p = -(d R_p / d sigma) / R_p from the Jacobian at the
    truth. Exact for a pixel whose paths share one water path length (absorption enters a
    path as exp(-sigma_a l)). Minimises sum_m w_m (sum_p A_mp R_p(sigma) - b_m)^2 / sigma_m^2
    per channel (kind=None: w = 1; "cauchy"/"huber": IRLS weights as `irls_fit`).
    A [m, N]; R, l [N, C]; b, sigma [m, C]; sigma_true [C] -> sigma [C]."""
    import scipy.sparse as sp

    R, l, b, sigma = (np.asarray(a, np.float64) for a in (R, l, b, sigma))
    A = sp.csr_matrix(np.asarray(A, np.float64))  # selection / averaging: sparse
    sigma = np.broadcast_to(sigma, b.shape)
    C = R.shape[1]
    grid = np.linspace(-1.0, 3.0, 801)  # sigma - sigma_true (1/m), then golden refinement

    def model(d, c):
        return A @ (R[:, c] * np.exp(-l[:, c] * d))

    def best(c, w):
        lo_hi = np.clip(grid, -sigma_true[c] * 0.999, None)
        f = [np.sum(w * ((model(d, c) - b[:, c]) / sigma[:, c]) ** 2) for d in lo_hi]
        k = int(np.argmin(f))
        lo, hi = lo_hi[max(k - 1, 0)], lo_hi[min(k + 1, len(lo_hi) - 1)]
        g = (np.sqrt(5) - 1) / 2
        for _ in range(60):
            m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
            f1 = np.sum(w * ((model(m1, c) - b[:, c]) / sigma[:, c]) ** 2)
            f2 = np.sum(w * ((model(m2, c) - b[:, c]) / sigma[:, c]) ** 2)
            lo, hi = (lo, m2) if f1 < f2 else (m1, hi)
        return 0.5 * (lo + hi)

    d = np.array([best(c, np.ones(A.shape[0])) for c in range(C)])
    if kind is not None:
        for _ in range(iters):
            r = np.stack([(model(d[c], c) - b[:, c]) / sigma[:, c] for c in range(C)], 1)
            w = robust_weights(r.reshape(-1), kind, channels=C).reshape(-1, C)
            d = np.array([best(c, w[:, c]) for c in range(C)])
    return np.asarray(sigma_true, np.float64) + d


# ------------------------------------------------------------------ solvers
def lm_fit(model: Callable, loss: Callable, theta0, *, weights=None, max_steps: int = 40,
           rtol: float = 1e-4, atol: float = 1e-8, lam0: float = 1e-3, history=None) -> dict:
    """Levenberg-Marquardt (Marquardt's diagonal scaling) of 0.5 sum w r^2 over theta.

    model(theta) -> (image, jacobian); loss(image, jacobian) -> (r [m], J [m, n]).
    Stops when the accepted step changes every theta by less than rtol (absolute, theta is
    ln sigma) or the loss by less than atol (relative). One model call per step (the
    Jacobian comes with the image). Returns {"theta", "loss", "steps", "evals",
    "seconds", "r", "J"}; appends per-evaluation records to `history`."""
    t0 = _time.perf_counter()
    theta = np.asarray(theta0, np.float64).copy()
    sw = None if weights is None else np.sqrt(np.asarray(weights, np.float64))

    def evaluate(th):
        img, jac = model(th)
        r, J = loss(np.asarray(img), np.asarray(jac))
        if sw is not None:
            r, J = r * sw, J * sw[:, None]
        return r, J, 0.5 * float(r @ r)

    r, J, f = evaluate(theta)
    evals, steps, lam = 1, 0, lam0
    if history is not None:
        history.append({"theta": theta.tolist(), "loss": f, "accepted": True})
    while steps < max_steps:
        g = J.T @ r
        A = J.T @ J
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        try:
            step = -np.linalg.solve(A + lam * D, g)
        except np.linalg.LinAlgError:
            lam *= 10
            if lam > 1e10:
                break
            continue
        step = np.clip(step, -2.0, 2.0)  # at most a factor e^2 per step in sigma
        if np.max(np.abs(step)) < rtol:  # converged (float32 renders: no further decrease)
            break
        th_new = theta + step
        r_new, J_new, f_new = evaluate(th_new)
        evals += 1
        ok = np.isfinite(f_new) and f_new <= f
        if history is not None:
            history.append({"theta": th_new.tolist(), "loss": f_new, "accepted": bool(ok)})
        if ok:
            steps += 1
            done = np.max(np.abs(step)) < rtol or (f - f_new) <= atol * max(f, 1e-300)
            theta, r, J, f = th_new, r_new, J_new, f_new
            lam = max(lam / 3, 1e-9)
            if done:
                break
        else:
            lam *= 4
            if lam > 1e10:
                break
    return {"theta": theta, "loss": f, "steps": steps, "evals": evals,
            "seconds": _time.perf_counter() - t0, "r": r, "J": J}


def irls_fit(model: Callable, loss: Callable, theta0, *, kind: str = "cauchy",
             outer: int = 8, tol: float = 1e-3, channels: int | None = None, history=None,
             **lm_kw) -> dict:
    """Robust fit by iteratively reweighted least squares: weights w = robust_weights(r)
    (MAD scale, per channel with `channels`) of the *unweighted* residuals at the current
    theta, then an LM solve of 0.5 sum w r^2 with w fixed; repeat until theta moves by
    less than `tol` or after `outer` solves. Returns lm_fit's dict plus "weights",
    "outer", "evals" (all solves)."""
    t0 = _time.perf_counter()
    theta = np.asarray(theta0, np.float64).copy()
    img, _ = model(theta)
    evals = 1
    r, _ = loss(np.asarray(img), None)  # unweighted residuals at theta
    for k in range(outer):
        w = robust_weights(r, kind, channels=channels)
        sol = lm_fit(model, loss, theta, weights=w, history=history, **lm_kw)
        evals += sol["evals"]
        moved = np.max(np.abs(sol["theta"] - theta))
        theta = sol["theta"]
        r = sol["r"] / np.sqrt(w)  # unweighted residuals at the new theta (w > 0)
        if moved < tol:
            break
    sol.update(theta=theta, weights=w, outer=k + 1, evals=evals,
               seconds=_time.perf_counter() - t0)
    return sol


def covariance(J, r, scaled: bool = True) -> np.ndarray:
    """(J^T J)^-1, times the residual variance sum r^2 / (m - n) if `scaled`."""
    J = np.asarray(J, np.float64)
    m, n = J.shape
    C = np.linalg.pinv(J.T @ J)
    return C * (float(r @ r) / max(m - n, 1)) if scaled else C


def decorrelated_fit(model_a: Callable, model_b: Callable, loss: Callable, theta0, *,
                     max_steps: int = 30, rtol: float = 1e-4, history=None) -> dict:
    """Per-pixel residuals without the firefly bias: the Jacobian is taken from renders with
    keys independent of the residual's (two halves A, B of the pass budget).

    The least-squares normal equation J^T r = 0 multiplies each pixel's residual by its
    own noisy Jacobian: with R = n g, sum n g' (n g - t) weights the fireflies by n^2,
    whence the 1 / (1 + var n) scale. With independent keys, sum n_B g' (n_A g - t) has
    expectation sum g' (g - t): the estimating equation (symmetrised)
        J_B^T r_A + J_A^T r_B = 0
    is unbiased to first order (an instrumental-variable estimator; the analogue of the
    decorrelated gradients of differentiable rendering). Solved by Newton-like steps
    d = -(J_B^T J_A + J_A^T J_B)^-1 (J_B^T r_A + J_A^T r_B); no objective is minimised, so
    there is no line search (steps clipped to 2 in ln sigma). Returns {"theta", "steps",
    "evals", "seconds", "loss" (0.5 |r_A|^2 + 0.5 |r_B|^2 / 2), "r", "J"}."""
    t0 = _time.perf_counter()
    theta = np.asarray(theta0, np.float64).copy()
    steps = evals = 0
    while True:
        ia, ja = model_a(theta)
        ib, jb = model_b(theta)
        evals += 2
        ra, Ja = loss(np.asarray(ia), np.asarray(ja))
        rb, Jb = loss(np.asarray(ib), np.asarray(jb))
        f = 0.25 * float(ra @ ra + rb @ rb)
        if history is not None:
            history.append({"theta": theta.tolist(), "loss": f, "accepted": True})
        if steps >= max_steps:
            break
        g = Jb.T @ ra + Ja.T @ rb
        Hm = Jb.T @ Ja + Ja.T @ Jb
        d = np.clip(-np.linalg.solve(Hm, g), -2.0, 2.0)
        theta = theta + d
        steps += 1
        if np.max(np.abs(d)) < rtol:
            break
    J = np.concatenate([Ja, Jb])
    r = np.concatenate([ra, rb])
    return {"theta": theta, "loss": f, "steps": steps, "evals": evals,
            "seconds": _time.perf_counter() - t0, "r": r, "J": J}
