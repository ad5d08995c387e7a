"""Static render configuration: the estimator (`RenderConfig`), the techniques of each
algorithm (`TECHNIQUES`) and how a pass lays out its work (`Tuning`). Hashable: passed to
`jax.jit` as a static argument."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

ALGORITHMS = ("pt", "lt", "bdpt", "ppm", "bpm", "vcm")  # flags of the one core
"""The algorithm names `RenderConfig.algorithm` accepts: each is a set of techniques of the
one bidirectional core (`TECHNIQUES`)."""


@dataclasses.dataclass(frozen=True)
class Techniques:
    """The techniques an algorithm enables on the one bidirectional core.

    `TECHNIQUES` is the only algorithm -> technique table: the integrator runs these
    stages, and both MIS forms weight over these techniques.

    emitter_hits:  s = 0, the camera subpath hits an emitter or escapes to the sky;
    nee:           s = 1 with t >= 2, next-event estimation;
    light_tracing: t = 1, light vertex -> pinhole;
    connections:   s, t >= 2;
    merging:       None, "first" (ppm: photons gathered at the first non-delta camera
                   vertex only, and emitter hits only through a purely delta camera
                   prefix) or "all" (bpm, vcm: merging at every non-delta camera vertex).
    """

    emitter_hits: bool
    nee: bool
    light_tracing: bool
    connections: bool
    merging: str | None = None

    @property
    def camera_paths(self) -> bool:
        return self.emitter_hits or self.nee or self.connections or self.merging is not None

    @property
    def weighted(self) -> bool:
        """The techniques carry MIS weights: every algorithm but ppm, whose gather (at the
        first non-delta camera vertex) and emission along the delta prefix take weight 1."""
        return self.merging != "first"

    @property
    def light_paths(self) -> bool:
        return self.light_tracing or self.connections or self.merging is not None

    def connection_mask(self, j, k):
        """Connection technique j (j light vertices) of a path with k segments enabled
        (before delta vertices and zero pdfs are considered). j == k is light tracing
        (also for k = 1), j == 1 < k next-event estimation."""
        on = jnp.where(j == 0, self.emitter_hits,
                       jnp.where(j == k, self.light_tracing,
                                 jnp.where(j == 1, self.nee, self.connections)))
        return on & (j <= k)


TECHNIQUES = {
    "pt": Techniques(emitter_hits=True, nee=True, light_tracing=False, connections=False),
    "lt": Techniques(emitter_hits=False, nee=False, light_tracing=True, connections=False),
    "bdpt": Techniques(emitter_hits=True, nee=True, light_tracing=True, connections=True),
    "ppm": Techniques(emitter_hits=True, nee=False, light_tracing=False, connections=False,
                      merging="first"),
    "bpm": Techniques(emitter_hits=True, nee=False, light_tracing=False, connections=False,
                      merging="all"),
    "vcm": Techniques(emitter_hits=True, nee=True, light_tracing=True, connections=True,
                      merging="all"),
}
"""The techniques each algorithm enables (`Techniques`), by algorithm name."""
MIS_HEURISTICS = ("balance", "power")
MIS_FORMS = ("explicit", "recursive")
MAX_DEPTH = 64  # path segments; subpaths are [depth, paths] arrays, so memory grows with it
# the largest first merging radius, as a fraction of the view radius: a blur up to 100x the
# size of what the camera sees (a close-up of a small patch may still blur over centimetres)
MAX_RADIUS = 100.0


def _positive_int(name: str, v) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        raise ValueError(f"config.{name}: must be a positive integer, got {v!r}")


@dataclasses.dataclass(frozen=True)
class Tuning:
    """How a pass does its work: none of these changes what the estimator is, only how
    its work is laid out and how much room it has (the host driver sets them; the tests
    check that each leaves the image unchanged, up to float32 round-off where the
    summation order moves). Private: reached through `RenderConfig.tuning` and set with
    `RenderConfig.tuned`.

    trace_split:     the subpath tracer advances 1/trace_split of the lanes (at least
                     `_queue.MIN_ROUND`) per round, only lanes still alive
                     (`_subpath.trace`); 1 = every lane every round.
    trace_tail:      rounds of a single-direction trace (PT, light tracing) with at most
                     1/trace_tail of a round's lanes alive run a step that narrow
                     (`_subpath.tail_width`); 1 = off; 0 = auto (8 from max_depth >=
                     3 rr_depth on, else off).
    chunks:          a pass's camera and light paths are traced in this many chunks, one
                     after the other (`lax.scan`), so its memory is that of 1/chunks of
                     its paths (`_memory.chunks_for_memory`), and so are its int32
                     indices (`_integrator.min_chunks`: a chunk's are below 2^31).
                     Chunk c holds the paths c N/chunks .. (c + 1) N/chunks - 1 and as
                     many light paths; its camera vertices merge with its own photons
                     (eta = pi r^2 N/chunks) while every chunk's light paths splat onto
                     the whole film with 1/N: an unbiased pass whose MIS counts are
                     what each technique sees. With chunks > 1 the samples differ from
                     one chunk's (so does the image, within noise).
    merge_capacity:  static bound on hash-grid candidates per gather point; overflow is
                     flagged in the diagnostics and the host re-runs the pass with more room.
    photon_capacity: photons (valid light vertices) the hash grid holds per chunk; 0 = half
                     the light-vertex slots, at least 4096 (`_merge.photon_room`); overflow
                     is flagged like merge_capacity's.
    """

    trace_split: int = 8
    trace_tail: int = 0
    chunks: int = 1
    merge_capacity: int = 512
    photon_capacity: int = 0

    def __post_init__(self):
        for name in ("trace_split", "chunks", "merge_capacity"):
            _positive_int(name, getattr(self, name))
        for name, what in (("trace_tail", "0: auto"), ("photon_capacity", "0: the default")):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"config.{name}: must be a non-negative integer ({what}), "
                                 f"got {v!r}")


TUNING_FIELDS = tuple(f.name for f in dataclasses.fields(Tuning))


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """The estimator: every setting that changes what a pass computes.

    Hashable: passed to `jax.jit` as a static argument.

    algorithm:   which techniques of the one core are enabled (`TECHNIQUES`).
    max_depth:   maximum number of path segments from the camera to the light
                 (1 = emitters seen directly; a furnace of albedo a converges to
                 Le (1 - a^max_depth) / (1 - a)).
    rr_depth:    Russian roulette starts after this many segments (>= max_depth: off).
    mis:         "power" (beta = 2) or "balance" heuristic.
    march_steps: uniform bracketing segments of the heightfield intersector.
    spp:         camera paths per pixel per pass; a pass's width x height x spp paths are at
                 most 2^31 - 1 (int32 path numbers: 7 spp at 16384 x 16384; more samples
                 come from more passes), refused before tracing otherwise.
    radius:      merging radius of the first pass, as a fraction of the scene's view
                 radius (`Scene.view_radius`: half the diagonal of the box of the surfaces
                 the camera sees); pass i uses r_1 i^((alpha - 1) / 2) (progressive
                 photon mapping).
    alpha:       radius reduction exponent (0 < alpha < 1).
    mis_form:    "explicit" (log-space sums over all techniques, evaluated at each join
                 from per-subpath partial sums) or "recursive" (the tech report's
                 dVCM/dVC/dVM recursion in linear space, carried along the subpaths as
                 they are traced): the same weights, two implementations of one
                 interface (docs/design/mis.md).
    glints:      add the glint technique: per camera path, a point on a light and the
                 water surface's point that reflects it (refracts it, for a camera
                 under the water) into the path's pixel, found by Newton, weighted by
                 MIS against the emitter hits that make the same paths
                 (docs/design/manifold.md). For the algorithms with emitter hits and
                 MIS weights: pt, bdpt, bpm, vcm.
    manifold_nee: add manifold next-event estimation: from every camera vertex under the
                 water, a point on a light above it and the surface point that refracts
                 its light there, found by Newton, one more technique of the explicit MIS
                 sums (docs/design/manifold.md). For pt, bdpt, bpm and vcm with the
                 explicit MIS form.
    tuning:      how the work is laid out (`Tuning`: trace rounds, chunks, capacities),
                 not what is estimated; set by the host driver, or with `tuned(...)`.
    """

    algorithm: str = "pt"
    max_depth: int = 8  # <= MAX_DEPTH
    rr_depth: int = 4
    mis: str = "power"
    march_steps: int = 16
    spp: int = 1
    radius: float = 0.005
    alpha: float = 0.75
    mis_form: str = "explicit"
    glints: bool = False
    manifold_nee: bool = False
    tuning: Tuning = Tuning()

    @property
    def techniques(self) -> Techniques:
        return TECHNIQUES[self.algorithm]

    def tuned(self, **changes) -> "RenderConfig":
        """This configuration with some `Tuning` fields changed (`trace_split`,
        `trace_tail`, `chunks`, `merge_capacity`, `photon_capacity`)."""
        return dataclasses.replace(self, tuning=dataclasses.replace(self.tuning, **changes))

    def record(self) -> dict:
        """The settings as one flat dict (the estimator's fields, then the tuning's): what
        run records (EXR header, JSON) store."""
        est = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name != "tuning"}
        return est | dataclasses.asdict(self.tuning)

    def __post_init__(self):
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"config.algorithm: unknown {self.algorithm!r}; "
                             f"one of {', '.join(ALGORITHMS)}")
        if self.mis not in MIS_HEURISTICS:
            raise ValueError(f"config.mis: unknown {self.mis!r}; one of {MIS_HEURISTICS}")
        if self.mis_form not in MIS_FORMS:
            raise ValueError(f"config.mis_form: unknown {self.mis_form!r}; one of {MIS_FORMS}")
        for name in ("max_depth", "march_steps", "spp", "rr_depth"):
            _positive_int(name, getattr(self, name))
        if self.max_depth > MAX_DEPTH:
            raise ValueError(f"config.max_depth: must be <= {MAX_DEPTH} (subpaths are stored "
                             f"as [depth, paths] arrays), got {self.max_depth!r}")
        if not (isinstance(self.radius, (int, float)) and 0 < self.radius <= MAX_RADIUS):
            raise ValueError(f"config.radius: must lie in (0, {MAX_RADIUS:g}] (a fraction of "
                             f"the scene's view radius), got {self.radius!r}")
        if not (isinstance(self.alpha, (int, float)) and 0 < self.alpha < 1):
            raise ValueError(f"config.alpha: must lie in (0, 1), got {self.alpha!r}")
        if not isinstance(self.glints, bool):
            raise ValueError(f"config.glints: must be true or false, got {self.glints!r}")
        if self.glints and not (self.techniques.emitter_hits and self.techniques.weighted):
            raise ValueError(f"config.glints: the glint technique shares its paths with the "
                             f"emitter hits by MIS; {self.algorithm} has no weighted emitter "
                             f"hits (use pt, bdpt, bpm or vcm)")
        if not isinstance(self.manifold_nee, bool):
            raise ValueError(f"config.manifold_nee: must be true or false, "
                             f"got {self.manifold_nee!r}")
        if self.manifold_nee and not (self.techniques.camera_paths and self.techniques.weighted):
            raise ValueError(f"config.manifold_nee: a technique of the MIS sums from camera "
                             f"vertices; {self.algorithm} has no weighted camera techniques "
                             f"(use pt, bdpt, bpm or vcm)")
        if self.manifold_nee and self.mis_form != "explicit":
            raise ValueError("config.manifold_nee: its weights are terms of the explicit "
                             "sums; use mis_form 'explicit'")
        if not isinstance(self.tuning, Tuning):
            raise ValueError(f"config.tuning: must be a Tuning record (set it with "
                             f"RenderConfig.tuned), got {type(self.tuning).__name__}")
