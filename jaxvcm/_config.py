"""Static render configuration. Hashable: passed to `jax.jit` as a static argument."""

from __future__ import annotations

import dataclasses

ALGORITHMS = ("pt", "lt", "bdpt")  # later: ppm, bpm, vcm as flags of the same core
MIS_HEURISTICS = ("balance", "power")


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Everything that changes the compiled program.

    algorithm:   which techniques of the one core are enabled ("pt" for now).
    max_depth:   maximum number of path segments from the camera to the light
                 (1 = emitters seen directly; a furnace of albedo a converges to
                 Le (1 - a^max_depth) / (1 - a)).
    rr_depth:    Russian roulette starts after this many segments (>= max_depth: off).
    mis:         "power" (beta = 2) or "balance" heuristic for NEE vs BSDF sampling.
    march_steps: uniform bracketing segments of the heightfield intersector.
    spp:         camera paths per pixel per pass.
    """

    algorithm: str = "pt"
    max_depth: int = 8
    rr_depth: int = 4
    mis: str = "power"
    march_steps: int = 16
    spp: int = 1

    def __post_init__(self):
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"config.algorithm: unknown {self.algorithm!r}; "
                             f"one of {', '.join(ALGORITHMS)}")
        if self.mis not in MIS_HEURISTICS:
            raise ValueError(f"config.mis: unknown {self.mis!r}; one of {MIS_HEURISTICS}")
        for name in ("max_depth", "march_steps", "spp"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"config.{name}: must be a positive integer, got {v!r}")
        if not isinstance(self.rr_depth, int) or self.rr_depth < 1:
            raise ValueError(f"config.rr_depth: must be a positive integer, got {self.rr_depth!r}")
