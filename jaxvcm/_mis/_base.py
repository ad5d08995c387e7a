"""The interface of an MIS form: how the renderer weights each technique at its join.

A form keeps, per subpath, what the weights of every technique through that subpath need
(`subpaths`), and weights one technique (s, t) from the two sides' entries and the four
pdfs the join re-evaluates (`join_weight`, or `entries` + `join` where one side is built
per item). Two forms implement it with the same weights (tests/mis): the explicit sums in
log space from per-subpath partial sums (`ExplicitMIS`) and the recursive dVCM / dVC / dVM
quantities carried along the subpaths as they are traced (`RecursiveMIS`). The full-path
sums (`mis_weight`, `mis_weight_recursive`) are the oracles both are tested against.

Arguments common to the methods (all per lane, broadcastable):
    s, t        light and camera vertices of the technique (s = 0 emitter hit, s = 1
                next-event estimation, t = 1 light tracing; with `merge`, merging at
                x_s = z_{t-1} with the photon y_s);
    A_s, A_s1   the light side's pdfs of x_s = z_{t-1} and x_{s+1} = z_{t-2}, re-evaluated
                at the join (A_s is the photon's own pdf for a merge);
    B_s1, B_s2  the camera side's pdfs of x_{s-1} = y_{s-1} and x_{s-2} = y_{s-2};
    delta_light, infinite_light: the path's light is a delta light / at infinity;
    log_n_lt    log of light tracing's multiplicity (`_path.log_n_light_tracing`).
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx

from .._config import RenderConfig


class AbstractMIS(eqx.Module):
    """An implementation of the MIS weights at the joins (diffrax's `AbstractSolver`
    pattern: stateless, chosen by `RenderConfig.mis_form` through `mis_form`)."""

    # ---- carried while tracing (None where the form carries nothing)
    def trace_context(self, cfg: RenderConfig, etas, log_n_lt, dtype) -> Any:
        """Per-pass constants the subpath tracer hands to every step."""
        return None

    def camera_carry(self, cfg: RenderConfig, n_paths: int, etas, dtype) -> Any:
        """What the camera subpaths carry from the pinhole z_0."""
        return None

    def light_carry(self, cfg: RenderConfig, emission, etas, dtype) -> Any:
        """What the light subpaths carry from y_0."""
        return None

    # ---- per subpath
    @abc.abstractmethod
    def subpaths(self, cfg: RenderConfig, lends, cends, delta_light, log_n_lt, etas,
                 light_mnee=None):
        """(light, camera) per-subpath MIS state from the traced subpaths (`PathEnds`, or
        None for a side the algorithm does not trace); `light_mnee`: (ok [N], lm [N]) of the
        light subpaths' manifold connections at y_2 (`_mnee.light_factors`), or None."""

    @abc.abstractmethod
    def empty_light(self, cfg: RenderConfig, dtype, etas):
        """The light side of an emitter hit (s = 0: no light vertex), one lane."""

    @abc.abstractmethod
    def pinhole(self, cfg: RenderConfig, log_n_lt, dtype, etas):
        """The camera side of light tracing (t = 1: the pinhole z_0 alone), one lane."""

    # ---- per technique
    @abc.abstractmethod
    def entries(self, cfg: RenderConfig, P, n, other, index=()):
        """What a technique whose side P has n vertices (the other side `other`) reads from
        it; `index`: the lane (trailing-axis indices of P's fields)."""

    @abc.abstractmethod
    def start_entries(self, cfg: RenderConfig, A0, delta_light, leta0=0.0):
        """The light side's entries when it is the lone fresh light sample y_0 of
        next-event estimation (pdf A0), in closed form."""

    @abc.abstractmethod
    def join(self, cfg: RenderConfig, s, t, Le, Ce, A_s, A_s1, B_s1, B_s2, delta_light,
             infinite_light, log_n_lt, merge=False):
        """The weight of technique (s, t) from both sides' entries; elementwise."""

    @abc.abstractmethod
    def join_weight(self, cfg: RenderConfig, s, t, L, C, A_s, A_s1, B_s1, B_s2, delta_light,
                    infinite_light, log_n_lt, merge=False, lanes=((), ())):
        """The weight of technique (s, t) for one lane (`lanes`: each side's lane) from the
        two sides' per-subpath state."""
