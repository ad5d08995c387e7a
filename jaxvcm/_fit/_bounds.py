"""The ranges fitted parameters stay in, and the map that keeps the solver inside them.

Ranges. An RGB fit's sigma_a, sigma_s stay in `SIGMA_FIT` = (1e-9, 1e6) 1/m: the scene
files' range (`_io._schema.SIGMA`, [0, 1e6] 1/m) with its 0 raised to 1e-9 /m, because the
fit works in log space, where 0 is infinitely far (1e-9 /m is an optical depth of 1e-3
across the largest scene a file accepts, 1e6 m: clear water for any scene). A spectral fit's
`WaterModel` leaves have their ranges in `WATER_RANGES` (also those of a fit config's
[water] table and of `jaxvcm render --spectral --water`); `fit_range` gives the one a
fitted leaf stays in. Leaves of a `WaterModel` subclass without an entry are unbounded.

The map. The solver's variable u is unconstrained; the parameter x (ln p for a log-space
parameter, p for a linear one) is x = u inside (lo + band, hi - band), and within `band` of
a bound it approaches the bound exponentially,

    x = hi - band exp(-(u - (hi - band)) / band)      (and mirrored at lo),

continuous in value and slope. So the solver can never leave the range, and a fit whose
iterates stay inside (lo + band, hi - band), every practical one, takes exactly the steps
it took without bounds. A parameter whose slope dx/du has fallen below `AT_BOUND` (it is
within 1 % of `band` of the bound, and the solver can barely move it) is *at its bound*:
the targets push it out of the range, and the fit reports it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import jax.numpy as jnp
import numpy as np

from .._io._schema import HG_G, SIGMA, Range

LOG_FLOOR = 1e-9  # the lowest value of a log-space parameter whose range starts at 0
SIGMA_FIT = Range(LOG_FLOOR, SIGMA.hi, SIGMA.unit, lo_open=True, hi_open=True)

# The WaterModel leaves' ranges (units as in `WaterModel`). The coefficients take the scene
# files' SIGMA range; S: 0 (flat) to 0.1 /nm, three times the steepest natural CDOM slopes
# (~0.03 /nm); n_p: 0 (large particles, grey) to 4 (Rayleigh, particles far below the
# wavelength); g: the scene files' Henyey-Greenstein range; a_w_scale: up to where the
# scaled pure-water absorption (at most 0.65 /m over 380-720 nm) stays within SIGMA.
WATER_RANGES = {
    "a_cdom": SIGMA, "S": Range(0.0, 0.1, "1/nm"), "a_flat": SIGMA, "b_p": SIGMA,
    "n_p": Range(0.0, 4.0), "g": HG_G, "a_w_scale": Range(0.0, SIGMA.hi),
}
AT_BOUND = 0.01  # dx/du below this: the parameter is at its bound


def fit_range(name: str, linear: bool) -> Range | None:
    """The open range a fitted `WaterModel` leaf stays in (None: unbounded).

    Log space: (max(lo, LOG_FLOOR), hi). Linear space: (lo, hi), except that a leaf whose
    range starts at 0 may go as far below 0 as its range goes above: `linear` exists for
    terms whose true value may be 0, whose estimate needs room on both sides of it (the
    renderer clamps the total sigma_a and sigma_s at 0)."""
    r = WATER_RANGES.get(name)
    if r is None:
        return None
    if linear:
        lo = -r.hi if r.lo == 0 else r.lo
    else:
        lo = max(r.lo, LOG_FLOOR)
    return Range(lo, r.hi, r.unit, lo_open=True, hi_open=True)


def _to_x(xp, u, consts):
    """The map u -> x of `Bounds` in the array module `xp` (jax.numpy or numpy)."""
    lo_on, hi_on, lo, hi, a_lo, a_hi, b = consts
    x_hi = hi - b * xp.exp(xp.minimum(a_hi - u, 0.0) / b)
    x_lo = lo + b * xp.exp(xp.minimum(u - a_lo, 0.0) / b)
    return xp.where(hi_on & (u > a_hi), x_hi, xp.where(lo_on & (u < a_lo), x_lo, u))


@dataclasses.dataclass(frozen=True)
class Bounds:
    """Per parameter: x-space bounds lo < hi (ln p or p; +-inf: none) and the band width."""

    lo: np.ndarray
    hi: np.ndarray
    band: np.ndarray

    @classmethod
    def of(cls, ranges: Sequence[Range | None], log: Sequence[bool]) -> Bounds:
        """From the parameters' open ranges (in p) and whether each is fitted in log space.
        Band: one e-fold in log space, 1 % of the range in linear space, at most a quarter
        of the range."""
        lo, hi, band = [], [], []
        for r, lg in zip(ranges, log):
            if r is None:
                lo.append(-math.inf)
                hi.append(math.inf)
                band.append(1.0)
                continue
            a, b = (math.log(r.lo), math.log(r.hi)) if lg else (r.lo, r.hi)
            lo.append(a)
            hi.append(b)
            band.append(min(1.0 if lg else 0.01 * (b - a), 0.25 * (b - a)))
        return cls(np.array(lo), np.array(hi), np.array(band))

    def _consts(self):
        lo_on, hi_on = np.isfinite(self.lo), np.isfinite(self.hi)
        b = self.band
        lo = np.where(lo_on, self.lo, 0.0)
        hi = np.where(hi_on, self.hi, 0.0)
        return lo_on, hi_on, lo, hi, lo + b, hi - b, b

    def to_x(self, u):
        """u -> x (JAX, differentiable; forward and reverse mode stay finite: each tail's
        exponent is clamped at 0 where the tail is not taken)."""
        consts = tuple(jnp.asarray(c, u.dtype) if c.dtype != bool else jnp.asarray(c)
                       for c in self._consts())
        return _to_x(jnp, u, consts)

    def to_x_host(self, u) -> np.ndarray:
        """u -> x (NumPy, float64): `to_x` on the host."""
        return _to_x(np, np.asarray(u, np.float64), self._consts())

    def to_u(self, x) -> np.ndarray:
        """x -> u (NumPy, float64), the inverse of `to_x`; x strictly inside (lo, hi)."""
        lo_on, hi_on, lo, hi, a_lo, a_hi, b = self._consts()
        x = np.asarray(x, np.float64)
        up = hi_on & (x > a_hi)
        down = lo_on & (x < a_lo)
        with np.errstate(divide="ignore", invalid="ignore"):
            u_hi = a_hi - b * np.log((hi - x) / b)
            u_lo = a_lo + b * np.log((x - lo) / b)
        return np.where(up, u_hi, np.where(down, u_lo, x))

    def slope(self, u) -> np.ndarray:
        """dx/du at u (NumPy): 1 inside, in (0, 1) in the bands."""
        lo_on, hi_on, lo, hi, a_lo, a_hi, b = self._consts()
        u = np.asarray(u, np.float64)
        s_hi = np.exp(np.minimum(a_hi - u, 0.0) / b)
        s_lo = np.exp(np.minimum(u - a_lo, 0.0) / b)
        return np.where(hi_on & (u > a_hi), s_hi, np.where(lo_on & (u < a_lo), s_lo, 1.0))

    def side(self, u) -> np.ndarray:
        """Per parameter: -1 at its lower bound, +1 at its upper bound, 0 inside."""
        u = np.asarray(u, np.float64)
        at = self.slope(u) < AT_BOUND
        _, _, _, _, a_lo, a_hi, _ = self._consts()
        return np.where(at & (u > a_hi), 1, np.where(at & (u < a_lo), -1, 0))


def bound_problems(names: Sequence[str], side, ranges: Sequence[Range | None]) -> list[str]:
    """One line per parameter at a bound: 'sigma_a[2] at its upper bound 1e+06 1/m'."""
    out = []
    for n, s, r in zip(names, np.asarray(side), ranges):
        if s and r is not None:
            v, which = (r.hi, "upper") if s > 0 else (r.lo, "lower")
            out.append(f"{n} at its {which} bound {v:g}" + (f" {r.unit}" if r.unit else ""))
    return out
