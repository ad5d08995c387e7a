"""Passes in a memory budget: the chunk count (`Tuning.chunks`, `cfg.tuning.chunks`) that
keeps one pass's working memory under a budget.

A pass's working memory is, to a good approximation, a cost per path of one chunk (the
subpath records, the techniques' per-lane values, the hash grid) plus a fixed part (the
film and the other per-pass arrays). Neither is guessed: `memory_model` compiles the pass at
two probe chunk sizes and reads XLA's own memory analysis of each program
(`Compiled.memory_analysis`: temporaries, outputs, arguments), a straight line through the
two. `chunks_for_memory` then takes the fewest chunks that divide the pass's paths evenly,
fit, and keep each chunk's indices within int32 (`_integrator.max_chunk_paths`).
docs/benchmarks.md lists the per-path figures of the shipped scenes.

Without a budget, `auto_chunks` uses the device's: DEVICE_SHARE of what its runtime may
allocate (`Device.memory_stats()["bytes_limit"]`, reported by GPU and TPU runtimes), or on
the CPU, which reports none, of the host's available memory (`host_memory`) less the
host's own buffers of the image (`host_bytes`: the running sum and mean in float64, the
float32 image and its PNG), shared by the CPU devices that run passes at once. It probes
only when a rough upper bound (`ROUGH_BYTES`, per path and depth segment, above what the
probes find for PT and VCM) says a single chunk might not fit. An image whose host buffers
(`check_host`) or fixed part cannot fit however many chunks is refused before any pass
runs, in one line naming the image size and the memory.
"""

from __future__ import annotations

import os
import re

import jax

from ._config import RenderConfig
from ._integrator import fewest_chunks, integrate, max_chunk_paths, min_chunks

PROBE_PATHS = 1024
DEVICE_SHARE = 0.8  # of a device's allocatable memory (the CPU: of the host's available
# memory), for one pass
ROUGH_BYTES = {"camera": 700, "both": 2500}  # per path per depth segment: upper bounds of
# what `memory_model` finds for camera-only passes (PT) and bidirectional ones (VCM)
MIN_CHUNK = 256  # paths; smaller chunks are all overhead
HOST_BYTES = 24  # per pixel and channel: the host's buffers of an image being rendered (the
# float64 running sum and mean, the float32 image written, its 8-bit PNG, with room)

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


def gib(n: float) -> str:
    """Bytes as GiB for messages ('3.2 GiB')."""
    return f"{n / (1 << 30):.3g} GiB"


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
                      model: tuple[float, float] | None = None, what: str | None = None) -> int:
    """The fewest chunks (dividing the pass's paths) whose pass fits `budget` bytes by
    `model` = (fixed, per path) (default: `memory_model`) and whose indices fit int32.
    `what`: the budget in words (`auto_chunks`); None: the caller's `memory`."""
    n = _paths(scene, cfg)
    fixed, per_path = memory_model(scene, cfg) if model is None else model
    fit = int((budget - fixed) // per_path)
    smallest = min(MIN_CHUNK, n)
    if fit < smallest:
        need = f"{fixed:.0f} fixed + {per_path:.0f} per path, {cfg.algorithm} at depth " \
               f"{cfg.max_depth}"
        if what is None:
            raise ValueError(f"memory: {budget} bytes is too small for one chunk: "
                             f"{smallest} paths need about {int(fixed + per_path * smallest)} "
                             f"bytes ({need})")
        raise too_big(scene, f"a pass in chunks of {smallest} paths needs about "
                             f"{gib(fixed + per_path * smallest)} ({need} bytes)", what)
    return fewest_chunks(n, min(fit, max_chunk_paths(cfg)))


def too_big(scene, need: str, what: str) -> ValueError:
    """The one-line refusal of an image whose pass or buffers cannot fit the memory."""
    cam = scene.camera
    return ValueError(f"camera.width, camera.height: a {cam.width} x {cam.height} image is too "
                      f"large for this memory: {need}, more than {what}; render a smaller image")


def host_memory() -> int | None:
    """Bytes the host can still give this process: Linux's MemAvailable (/proc/meminfo),
    capped by a cgroup v2 limit (memory.max less memory.current), else the free pages
    (`os.sysconf`); None where none of these is known."""
    avail = None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
        except (AttributeError, ValueError, OSError):
            return None
    try:
        with open("/sys/fs/cgroup/memory.max", encoding="ascii") as f:
            limit = f.read().strip()
        with open("/sys/fs/cgroup/memory.current", encoding="ascii") as f:
            used = int(f.read().strip())
        if limit != "max":
            avail = min(avail, max(int(limit) - used, 0))
    except (OSError, ValueError):
        pass
    return avail if avail and avail > 0 else None


def host_bytes(scene) -> int:
    """The host's own buffers of an image being rendered (HOST_BYTES per pixel and channel),
    beside its passes."""
    cam = scene.camera
    return HOST_BYTES * cam.height * cam.width * scene.channels


def check_host(scene) -> None:
    """Refuse (one line) an image whose host buffers (`host_bytes`) exceed DEVICE_SHARE of
    the host's available memory, before anything is compiled or rendered."""
    avail = host_memory()
    if avail is not None and host_bytes(scene) > DEVICE_SHARE * avail:
        raise too_big(scene, f"its running sum, mean and outputs need about "
                             f"{gib(host_bytes(scene))} of host memory ({HOST_BYTES} bytes per "
                             f"pixel and channel)", f"the {gib(DEVICE_SHARE * avail)} there "
                             f"is for them ({DEVICE_SHARE:.0%} of the host's {gib(avail)} "
                             f"available)")


def device_budget(device) -> int | None:
    """DEVICE_SHARE of the memory `device`'s runtime may allocate, or for the CPU, whose
    runtime reports none, of the host's available memory (`host_memory`); None where
    neither is known."""
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 (a backend without memory statistics)
        stats = None
    if stats and stats.get("bytes_limit"):
        return int(DEVICE_SHARE * stats["bytes_limit"])
    if getattr(device, "platform", None) == "cpu":
        avail = host_memory()
        return None if avail is None else int(DEVICE_SHARE * avail)
    return None


def pass_budget(scene, device, devices: int = 1) -> tuple[int, str] | None:
    """(bytes, the same in words) one pass on `device` may use: `device_budget`; on the
    CPU less the host's buffers of the image (`host_bytes`) and shared by the `devices`
    CPU devices that run passes at once. None where the device's memory is not known."""
    budget = device_budget(device)
    if budget is None:
        return None
    if getattr(device, "platform", None) != "cpu":
        return budget, f"the {gib(budget)} this device has for a pass ({DEVICE_SHARE:.0%})"
    rest = max(budget - host_bytes(scene), 0) // max(devices, 1)
    share = f", shared by {devices} devices" if devices > 1 else ""
    return rest, (f"the {gib(rest)} a pass may have on this host ({DEVICE_SHARE:.0%} of its "
                  f"available memory, less {gib(host_bytes(scene))} for the image{share})")


def auto_chunks(scene, cfg: RenderConfig, device, devices: int = 1) -> int:
    """`cfg.tuning.chunks`, or the fewest chunks for `device`'s memory (`pass_budget`): those
    whose indices fit int32 (`_integrator.min_chunks`) when a rough upper bound of the
    one-chunk pass fits the budget (no probe), else `chunks_for_memory` of the budget (one
    or two probe compiles). An image whose film alone exceeds the budget is refused without
    a probe. `devices`: the devices running passes at once (they share the CPU's memory)."""
    if cfg.tuning.chunks != 1:
        return cfg.tuning.chunks
    floor = min_chunks(scene, cfg)
    got = pass_budget(scene, device, devices)
    if got is None:
        return floor
    budget, what = got
    cam = scene.camera
    film = cam.height * cam.width * scene.channels * cam.origin.dtype.itemsize
    if film > budget:
        raise too_big(scene, f"its film alone needs {gib(film)}", what)
    kind = "both" if cfg.techniques.light_paths else "camera"
    if _paths(scene, cfg) * cfg.max_depth * ROUGH_BYTES[kind] + film <= budget:
        return floor
    return chunks_for_memory(scene, cfg, budget, what=what)
