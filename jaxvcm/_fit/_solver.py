"""The one Levenberg-Marquardt driver of the fits (RGB and spectral), on optimistix.

`optimistix.least_squares` with `optimistix.LevenbergMarquardt(rtol, atol)`: Cauchy
termination on the parameters and on the loss 0.5 sum r^2. The Jacobian is forward mode
through the renderer (optimistix linearises with `jax.linearize`: one JVP per parameter).
The loss of every step is recorded with the solver's `verbose` hook (a
`jax.debug.callback`), giving the convergence history without re-running anything; the
residuals at y0 are recorded the same way from the residual function's first evaluation
(a callback on its primal output), and the residuals and the Jacobian at the solution (the
last accepted iterate) are read from the solver's state, so the compiled program holds the
renderer once: the linearisation inside the solver's loop (a separate evaluation of r(y0)
would add a second copy of the renderer to trace and compile).

Covariance of the parameters from the Jacobian J at the solution: `cov_unscaled` =
(J^T J)^-1 trusts the stated uncertainties; `cov` = (J^T J)^-1 s^2 with the residual
variance s^2 = sum r^2 / (m - n).

`assess` turns the outcome into words: converged means optimistix's result "successful";
a fit that converged still *fits badly* when its worst region is more than `max_delta_e`
Delta E 2000 from its target, and a parameter at a bound of its range (`_bounds`) is a
problem too. Why Delta E 2000 and not chi^2: the default uncertainties (1 % of the target,
or 1 Delta E*ab) set the residuals' scale, they are not measurement errors, so chi^2 would
judge the defaults rather than the fit; Delta E 2000 is the same perceptual scale whatever
the targets' space, and about 1-2 is a just-noticeable difference.
"""

from __future__ import annotations

import dataclasses
import time as _time
from typing import Callable

import jax
import numpy as np


@dataclasses.dataclass
class Solution:
    y: np.ndarray  # [n] the solution (float64)
    result: str  # optimistix RESULTS name ("successful", "max_steps_reached", ...)
    steps: int  # optimistix steps
    overflow: bool  # the residual function's aux (merge overflow flag) at the solution
    r0: np.ndarray  # [m] residuals at y0
    residuals: np.ndarray  # [m] residuals at y
    jacobian: np.ndarray  # [m, n] d residuals / d y at y
    cov_unscaled: np.ndarray  # [n, n] (J^T J)^-1
    cov: np.ndarray  # [n, n] (J^T J)^-1 s^2
    history: list  # per step: {"step", "loss", "loss_accepted", ["step_size",] "theta"}
    seconds: float  # the least_squares call, compilation included


def result_name(result) -> str:
    import optimistix as optx

    for name in ("successful", "max_steps_reached", "nonlinear_max_steps_reached",
                 "nonlinear_divergence", "singular"):
        v = getattr(optx.RESULTS, name, None)
        if v is not None and bool(result == v):
            return name
    return "failed"


MAX_DELTA_E = 2.0  # default: a worst region further than this from its target fits badly
MAX_LISTED = 5  # regions named in a "fits badly" line


def assess(result: str, steps: int, delta_e, region_names, max_delta_e: float,
           at_bound: list[str]) -> tuple[bool, list[str], str]:
    """-> (converged, problems, verdict): problems one line each (not converged, fits
    badly, each parameter at a bound); verdict one line for the report."""
    converged = result == "successful"
    problems = [] if converged else [
        f"did not converge: {result} after {steps} step{'' if steps == 1 else 's'}"]
    de = np.asarray(delta_e, np.float64)
    worst = float(np.max(de)) if de.size else 0.0
    bad = [n for n, d in zip(region_names, de) if not d <= max_delta_e]  # NaN is bad
    if bad:
        more = f" and {len(bad) - MAX_LISTED} more" if len(bad) > MAX_LISTED else ""
        problems.append(f"fits badly: max dE2000 {worst:.3g} > {max_delta_e:g} "
                        f"(regions: {', '.join(bad[:MAX_LISTED])}{more})")
    problems += list(at_bound)
    if not problems:
        verdict = f"fit converged: max dE2000 {worst:.3g} <= {max_delta_e:g}"
    else:
        verdict = ("fit converged but " if converged else "fit ") + "; ".join(problems)
    return converged, problems, verdict


def levenberg_marquardt(residual_fn: Callable, y0, *, rtol: float, atol: float,
                        max_steps: int, progress: bool = False,
                        step_size: bool = True,
                        memory: Callable[[int], None] | None = None) -> Solution:
    """Minimise 0.5 |r(y)|^2 from y0; residual_fn(y, args) -> (r [m], aux) with aux a
    boolean flag (merge overflow). step_size: record the LM step size in the history.
    memory: called with the bytes XLA's memory analysis gives the compiled solver
    (temporaries, arguments, outputs) before it runs; it raises to refuse a fit that
    cannot fit (the program is compiled ahead of time, so the check costs nothing)."""
    import optimistix as optx

    fields = ("num_steps", "loss_this_step", "loss_last_accepted_step") + \
        (("step_size",) if step_size else ()) + ("y",)
    history: list[dict] = []

    def _record(kw):
        e = {"step": int(kw["num_steps"]), "loss": float(kw["loss_this_step"]),
             "loss_accepted": float(kw["loss_last_accepted_step"])}
        if step_size:
            e["step_size"] = float(kw["step_size"])
        e["theta"] = np.asarray(kw["y"], np.float64).tolist()
        history.append(e)
        if progress:
            print(f"  step {e['step']:3d}  loss {e['loss']:.6g}", flush=True)

    def verbose(**kw):
        jax.debug.callback(_record, {k: v[1] for k, v in kw.items() if k in fields})

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)
    y0_host = np.asarray(y0)
    first: list[np.ndarray] = []  # the residuals at y0, from the first evaluation there

    def _seen(y, r):
        if not first and np.array_equal(np.asarray(y), y0_host):
            first.append(np.asarray(r, np.float64))

    def recorded(y, args):
        r, aux = residual_fn(y, args)
        jax.debug.callback(_seen, y, r)
        return r, aux

    @jax.jit
    def solve(y0):
        sol = optx.least_squares(recorded, solver, y0, has_aux=True, max_steps=max_steps,
                                 throw=False)
        # residuals and Jacobian at the last accepted iterate (= sol.value), from the
        # solver's state: no further copies of the renderer in this program
        r1 = sol.state.f_info.residual
        J = sol.state.f_info.jac.as_matrix()
        return sol.value, sol.result, sol.stats["num_steps"], sol.aux, J, r1

    t1 = _time.perf_counter()
    compiled = solve.lower(y0).compile()
    if memory is not None:
        m = compiled.memory_analysis()
        if m is not None:
            memory(int(m.temp_size_in_bytes + m.argument_size_in_bytes
                       + m.output_size_in_bytes))
    y, result, nsteps, overflow, J, r1 = compiled(y0)
    y = np.asarray(jax.block_until_ready(y), np.float64)
    jax.effects_barrier()  # the callbacks have run
    seconds = _time.perf_counter() - t1
    # optimistix evaluates r at y0 first; should it ever not, one more (separate) program
    r0 = first[0] if first else np.asarray(jax.jit(residual_fn)(y0, None)[0], np.float64)
    res = np.asarray(r1, np.float64)
    J = np.asarray(J, np.float64)
    m, n = J.shape
    cov_u = np.linalg.pinv(J.T @ J)
    s2 = float(res @ res) / max(m - n, 1)
    return Solution(y=y, result=result_name(result), steps=int(nsteps),
                    overflow=bool(overflow), r0=r0, residuals=res,
                    jacobian=J, cov_unscaled=cov_u, cov=cov_u * s2, history=history,
                    seconds=seconds)
