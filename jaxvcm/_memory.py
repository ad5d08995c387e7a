"""Passes in a memory budget: the chunk count (`Tuning.chunks`, `cfg.tuning.chunks`) that
keeps one pass's working memory under a budget.

A pass's working memory is, to a good approximation, a cost per path of one chunk (the
subpath records, the techniques' per-lane values, the hash grid) plus a fixed part (the
film and the other per-pass arrays). Neither is guessed: `memory_model` compiles the pass at
two probe chunk sizes and reads XLA's own memory analysis of each program
(`Compiled.memory_analysis`: temporaries, outputs, arguments), a straight line through the
two. `chunks_for_memory` then takes the fewest chunks that divide the pass's paths evenly
and fit. docs/benchmarks.md lists the per-path figures of the shipped scenes.

Without a budget, `auto_chunks` uses the device's: 80 % of what its runtime may allocate
(`Device.memory_stats()["bytes_limit"]`, reported by GPU and TPU runtimes, not by the CPU's),
and probes only when a rough upper bound (`ROUGH_BYTES`, per path and depth segment, above
what the probes find for PT and VCM) says a single chunk might not fit.
"""

from __future__ import annotations

import re

import jax

from ._config import RenderConfig
from ._integrator import integrate

PROBE_PATHS = 1024
DEVICE_SHARE = 0.8  # of a device's allocatable memory, for one pass
ROUGH_BYTES = {"camera": 700, "both": 2500}  # per path per depth segment: upper bounds of
# what `memory_model` finds for camera-only passes (PT) and bidirectional ones (VCM)
MIN_CHUNK = 256  # paths; smaller chunks are all overhead

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_bytes(text: str) -> int:
    """'512M', '4G', '1.5g', '1000000' (bytes; K/M/G/T are powers of 1024, 'B' optional)."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([kKmMgGtT]?)[bB]?\s*", str(text))
    if m is None:
        raise ValueError(f"memory: expected a size such as 512M or 4G, got {text!r}")
    v = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not 0 < v < 1 << 50:
        raise ValueError(f"memory: must lie in (0, 1P] bytes, got {text!r}")
    return int(v)


def _paths(scene, cfg: RenderConfig) -> int:
    return scene.camera.height * scene.camera.width * cfg.spp


def _probe_bytes(scene, cfg: RenderConfig, paths: int) -> int:
    """XLA's memory analysis (temporaries + outputs + arguments) of the pass compiled with
    chunks of `paths` paths."""
    c = cfg.tuned(chunks=_paths(scene, cfg) // paths)
    exe = jax.jit(integrate, static_argnums=2).lower(scene, jax.random.key(0), c, 0).compile()
    m = exe.memory_analysis()
    return int(m.temp_size_in_bytes + m.output_size_in_bytes + m.argument_size_in_bytes)


def memory_model(scene, cfg: RenderConfig) -> tuple[float, float]:
    """(fixed bytes, bytes per path of a chunk) of the pass: two probe compiles at chunks
    of about PROBE_PATHS and 2 PROBE_PATHS paths, a straight line through them (the film and
    the other per-pass arrays are the fixed part). A pass of at most PROBE_PATHS paths is
    probed once, whole, and charged entirely to its paths."""
    n = _paths(scene, cfg)
    p1 = max(d for d in range(1, min(n, PROBE_PATHS) + 1) if n % d == 0)
    p2 = max(d for d in range(1, min(n, 2 * PROBE_PATHS) + 1) if n % d == 0)
    m1 = _probe_bytes(scene, cfg, p1)
    if p2 == p1:
        return 0.0, m1 / p1
    m2 = _probe_bytes(scene, cfg, p2)
    per = max((m2 - m1) / (p2 - p1), 1.0)
    return max(m1 - per * p1, 0.0), per


def chunks_for_memory(scene, cfg: RenderConfig, budget: int,
                      model: tuple[float, float] | None = None) -> int:
    """The fewest chunks (dividing the pass's paths) whose pass fits `budget` bytes by
    `model` = (fixed, per path) (default: `memory_model`)."""
    n = _paths(scene, cfg)
    fixed, per_path = memory_model(scene, cfg) if model is None else model
    fit = int((budget - fixed) // per_path)
    smallest = min(MIN_CHUNK, n)
    if fit < smallest:
        raise ValueError(f"memory: {budget} bytes is too small for one chunk: "
                         f"{smallest} paths need about {int(fixed + per_path * smallest)} "
                         f"bytes ({fixed:.0f} fixed + {per_path:.0f} per path, "
                         f"{cfg.algorithm} at depth {cfg.max_depth})")
    for k in range(1, n + 1):
        if n % k == 0 and n // k <= fit:
            return k
    return n  # unreachable: k = n gives chunks of one path


def device_budget(device) -> int | None:
    """DEVICE_SHARE of the memory `device`'s runtime may allocate; None where it reports
    none (the CPU)."""
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 (a backend without memory statistics)
        return None
    if not stats or not stats.get("bytes_limit"):
        return None
    return int(DEVICE_SHARE * stats["bytes_limit"])


def auto_chunks(scene, cfg: RenderConfig, device) -> int:
    """`cfg.tuning.chunks`, or, when `device` reports its memory and a rough upper bound of the
    one-chunk pass exceeds its budget, `chunks_for_memory` of that budget (one probe
    compile)."""
    budget = device_budget(device)
    if budget is None or cfg.tuning.chunks != 1:
        return cfg.tuning.chunks
    kind = "both" if cfg.techniques.light_paths else "camera"
    if _paths(scene, cfg) * cfg.max_depth * ROUGH_BYTES[kind] <= budget:
        return 1
    return chunks_for_memory(scene, cfg, budget)
