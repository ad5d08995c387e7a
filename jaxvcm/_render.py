"""The pure render pass (`render_pass`, with its `Diagnostics`) and the one host-side
progressive driver (`progressive`: pass keys, merge-capacity re-runs, time budgets,
progress bar, atomic snapshots) used by RGB `render` and spectral `render_spectral`."""

from __future__ import annotations

import contextlib
import functools
from typing import Any, Callable
import hashlib
import os
import time as _time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from . import _devices, _hosts, _io, _memory, _signals, _warm
from . import _merge
from ._version import __version__
from ._config import RenderConfig
from ._integrator import Technique, TechniqueImages, integrate, technique_images
from ._scene import Scene


class Diagnostics(eqx.Module):
    """What a render pass reports besides its image: counts and flags.

    Errors are values under jit: a host driver reads these flags after the pass (a merging
    overflow re-runs it with more room, `with_retry`)."""

    nonfinite: Int[Array, ""]  # pixel-technique contributions that were NaN/Inf (zeroed; must be 0)
    camera_paths: Int[Array, ""]  # camera subpaths traced
    light_paths: Int[Array, ""]  # light subpaths traced
    camera_vertices: Int[Array, ""]  # camera subpath vertices that existed
    light_vertices: Int[Array, ""]  # light subpath vertices that existed
    merge_overflow: Array  # merging ran out of candidate or photon room (re-run!)
    merge_candidates: Array  # longest candidate list of a gather point: the room needed
    photon_overflow: Array  # more valid photons than the hash grid's photon room
    merge_photons: Array  # valid photons (of the largest chunk): the photon room needed
    merge_imprecise: Array  # the hash grid could not resolve the merging radius in the
    # scene's float dtype at the photons' coordinates (neighbours may have been missed: the
    # pass is wrong; the radius's floor, `_merge.pass_radius`, keeps it from happening
    # inside the scene's box)


def render_pass(scene: Scene, key: PRNGKeyArray, config: RenderConfig = RenderConfig(),
                pass_index=0) -> tuple[Float[Array, "H W C"], Diagnostics]:
    """One render pass: an unbiased per-pixel radiance estimate by `config.algorithm`.

    The algorithm's techniques run on the one bidirectional core, from `config.spp` camera
    subpaths per pixel and/or as many light subpaths. Pure and jit/vmap/grad-able (config
    is static). `pass_index` (0-based) drives the merging radius schedule of the merging
    algorithms (ppm, bpm, vcm). Returns (image [H, W, C], `Diagnostics`)."""
    cam = scene.camera
    N = cam.height * cam.width * config.spp
    img, bad, stats = integrate(scene, key, config, pass_index)
    tech = config.techniques
    diag = Diagnostics(
        nonfinite=bad,
        camera_paths=jnp.asarray(N if tech.camera_paths else 0, jnp.int32),
        light_paths=jnp.asarray(N if tech.light_paths else 0, jnp.int32),
        camera_vertices=stats.camera_vertices,
        light_vertices=stats.light_vertices,
        merge_overflow=stats.merge_overflow,
        merge_candidates=stats.merge_candidates,
        photon_overflow=stats.photon_overflow,
        merge_photons=stats.merge_photons,
        merge_imprecise=stats.merge_imprecise,
    )
    return img, diag


@functools.partial(jax.jit, static_argnums=(2,))
def _render_pass_jit(scene, key, config, pass_index=0):
    return render_pass(scene, key, config, pass_index)


def with_retry(jitted_pass, scene, key, config: RenderConfig, pass_index,
               core: Callable[[Any], Diagnostics], geometry: Scene, valid=None):
    """Host side: run `jitted_pass(scene, key, config, pass_index)`; if merging overflowed a
    static capacity, re-run the same pass (same key) with more room (jax-md's
    re-allocation pattern); never truncate. `core(diagnostics)` is the pass's core
    `Diagnostics` (leading batch axes allowed; `valid`: which batch entries count);
    `geometry` is the scene whose box bounds the photons. The candidate room is the power of
    two that holds the longest candidate list the pass reported, at least twice the old
    one; the photon room at least doubles and holds the photons with a margin
    (`_merge.more_room`), so one re-run (one new compiled program) is enough. Returns
    (estimate, diagnostics, the config that had room). The merging radius never goes below
    what the hash grid resolves at the scene's scale (`_merge.pass_radius`), so the grid's
    `precise` flag can trip only for photons outside the scene's box: an error, never a
    silent miss."""
    while True:
        est, diag = jitted_pass(scene, key, config, pass_index)
        d = core(diag)
        if bool(np.any(d.merge_imprecise)):  # the grid's own flag: the radius's floor
            # holds for the scene's box, so the photons were outside it
            raise ValueError(f"config.radius: the hash grid could not resolve pass "
                             f"{int(np.max(np.asarray(pass_index))) + 1}'s merging radius at "
                             f"the photons' coordinates (photons outside the scene's box); "
                             f"use a larger radius or a float64 scene")
        counts = (lambda x: x) if valid is None else (lambda x: x & valid)  # noqa: E731
        if not bool(np.any(counts(d.merge_overflow))):
            return est, diag, config
        config = _merge.more_room(config, int(np.max(np.asarray(d.merge_candidates))),
                                  bool(np.any(counts(d.photon_overflow))),
                                  int(np.max(np.asarray(d.merge_photons))))


def _host_pass(scene, key, config, pass_index=0):
    """`render_pass` jitted, or (warm starts on, `_warm`) its exported module."""
    if _warm.enabled():
        return _warm.exported_pass(render_pass, Diagnostics, scene, key, config, pass_index)
    return _render_pass_jit(scene, key, config, pass_index)


def render_pass_host(scene, key, config, pass_index=0):
    """One render pass run from the host, re-run with more room if merging overflows.

    `render_pass` jitted (or exported for warm starts: `_warm`), with the merge-capacity
    re-run of `with_retry`. Returns (image, `Diagnostics`, the config that had room)."""
    return with_retry(_host_pass, scene, key, config, pass_index, lambda d: d, scene)


def pass_key(seed: int, index: int) -> PRNGKeyArray:
    """The random key of pass `index` of a render with `seed`.

    Independent of how passes are batched, so resumed or sharded renders draw the same
    samples."""
    return jax.random.fold_in(jax.random.key(seed), index)


def check_budget(passes, time):
    """The pass count / time budget of a progressive render (default 16 passes)."""
    if passes is None and time is None:
        passes = 16
    if passes is not None and passes < 1:
        raise ValueError(f"passes: must be >= 1, got {passes}")
    if time is not None and not time > 0:
        raise ValueError(f"time: must be > 0 seconds, got {time}")
    return passes, time


def progressive(run_pass, to_image, meta, *, passes=None, time=None, out=None,
                snapshot_every=None, progress=True, exposure=0.0, total=None, start=None,
                to_layers=None):
    """Average independent passes until `passes` are done or `time` seconds of rendering
    have elapsed after the first pass (at least one pass). The first pass of a run includes
    the compilation (seconds to a minute from an empty cache), so the time budget starts
    when it is done: a short budget renders for its time, not one pass. The record's
    "first_pass_seconds" is that pass's wall time (compilation included) and "seconds" the
    whole run's. `run_pass(i) -> (estimates, nonfinite count)`: the estimate ndarray of
    pass i, a list of them (passes i, i + 1, ...), or the count of passes it added to sums
    kept on the devices, whose float64 total `total()` returns (`_devices.DeviceSum`).
    `start = (passes done, their float64 sum)` resumes an earlier render. `to_image(mean)`
    turns the running mean into the image written; `meta(passes, seconds, nonfinite,
    snapshot)` its JSON record, to which "warnings" (one line each) is added;
    `to_layers(mean)` (optional) the EXR's extra layers {name: image}. With `out`,
    writes EXR + PNG + JSON at the end, and with `snapshot_every` (seconds) atomic snapshots
    along the way, so a killed render leaves its last snapshot intact. An interrupted one
    (SIGINT, SIGTERM, KeyboardInterrupt: `_signals`) finishes its pass in flight, writes the
    set of the passes it has (its record says "interrupted") and re-raises, with the pass
    count as the exception's `passes`. The output set is held for the render
    (`_io.output_lock`): a second render to the same `out` is refused. The first pass
    includes the compilation: the progress line says "compiling" until it is done, and the
    snapshot clock starts when it has finished. Before anything, `out`'s set is recovered
    from an earlier killed render (`_io.recover_outputs`). On many processes (`_hosts`) every
    process runs this loop; process 0 prints and writes, and its clock decides when to stop
    and when to snapshot (`_hosts.agree`). Returns (mean estimate float64, passes done,
    nonfinite)."""
    passes, time = check_budget(passes, time)
    lead = _hosts.is_lead()
    out = out if lead else None
    with _io.output_lock(out) if out else contextlib.nullcontext():
        return _progressive(run_pass, to_image, meta, passes, time, out, snapshot_every,
                            progress, exposure, total, start, to_layers)


def _progressive(run_pass, to_image, meta, passes, time, out, snapshot_every, progress,
                 exposure, total, start, to_layers):
    lead = _hosts.is_lead()
    if out:
        _io.prefetch_imports()
        _io.recover_outputs(out)
    i, acc = (0, None) if start is None else start
    nonfinite = 0
    t0 = _time.perf_counter()
    last_snap = None
    bar = _io.Progress(total=passes, time_budget=time, enabled=progress and lead)
    bar.start()

    first = None  # wall time of this run's first pass (compilation included)

    def record(n, seconds, image, snapshot):
        m = dict(meta(n, seconds, nonfinite, snapshot))
        if first is not None:
            m["first_pass_seconds"] = round(first, 3)
        return {**m, "warnings": render_warnings(image, nonfinite) + m.pop("warnings", [])}

    def mean():
        s = acc
        if total is not None:
            s = total() if s is None else s + total()
        return s / i

    interrupted = None
    try:
        while True:
            _signals.defer(i > 0)  # a signal now ends the render after this pass
            ests, bad = run_pass(i)
            if isinstance(ests, (int, np.integer)):
                i += int(ests)  # added on the devices
            else:
                for est in (ests if isinstance(ests, list) else [ests]):
                    if acc is None:  # in pass order, in float64, in place (a large
                        acc = np.array(est, dtype=np.float64)  # image's sum is one buffer)
                    else:
                        acc += np.asarray(est, dtype=np.float64)
                    i += 1
                ests = est = None  # no second copy of a pass held while the next runs
            nonfinite += int(bad)
            now = _time.perf_counter()
            if first is None:
                first = now - t0
                if time is not None:  # the ETA of the budget, which starts now
                    bar.time_budget = time + first
            bar.update(i, now - t0)
            done = (passes is not None and i >= passes) or (
                time is not None and now - t0 - first >= time)
            last_snap = now if last_snap is None else last_snap
            snap = (bool(out) and snapshot_every is not None and not done
                    and now - last_snap >= snapshot_every)
            done, snap = (bool(x) for x in _hosts.agree((done, snap)))
            if snap:
                m = mean()  # a collective: every process
                img = to_image(m).astype(np.float32)
                if out:
                    _io.write_outputs(out, img, record(i, now - t0, img, True), exposure,
                                      None if to_layers is None else to_layers(m))
                last_snap = now
            if done:
                break
            _signals.check()
    except KeyboardInterrupt as e:  # SIGINT / SIGTERM (`_signals`): keep the passes done
        interrupted = e
    finally:
        _signals.defer(False)
        bar.close()
    if interrupted is not None:
        if i > 0 and out and _hosts.count() == 1:  # several processes: the last snapshot
            m = mean()
            img = to_image(m).astype(np.float32)
            rec = record(i, _time.perf_counter() - t0, img, False)
            rec["interrupted"] = str(interrupted) or "SIGINT"
            _io.write_outputs(out, img, rec, exposure,
                              None if to_layers is None else to_layers(m))
        interrupted.passes = i
        raise interrupted
    m = mean()
    img = to_image(m).astype(np.float32)
    if nonfinite and lead:
        import warnings

        warnings.warn("; ".join(render_warnings(img, nonfinite)))
    if out:
        _io.write_outputs(out, img, record(i, _time.perf_counter() - t0, img, False), exposure,
                          None if to_layers is None else to_layers(m))
    return m, i, nonfinite


ALL_NONFINITE = "every path contribution was non-finite"


def render_warnings(image, nonfinite: int) -> list[str]:
    """The one-line warnings of a finished render: contributions zeroed because they were
    not finite (NaN/Inf, e.g. a scene at the edge of float32), and an image that is black
    for that reason (`ALL_NONFINITE`; the CLI exits 3 on it) or entirely zero."""
    out = []
    black = not np.any(np.asarray(image) != 0)
    if nonfinite:
        out.append(f"{nonfinite} non-finite path contributions were zeroed")
    if black and nonfinite:
        out.append(f"the image is black: {ALL_NONFINITE}")
    elif black:
        out.append("the image is black: no path contribution reached the film")
    return out


def render(scene: Scene, algorithm: str = "pt", passes: int | None = None,
           time: float | None = None, seed: int = 0, snapshot_every: float | None = None,
           out: str | None = None, config: RenderConfig | None = None, progress: bool = True,
           exposure: float = 0.0, scene_path: str | None = None, devices=None,
           resume: bool = False, memory: int | str | None = None,
           techniques: bool = False) -> np.ndarray:
    """Render a scene progressively: the mean of independent passes, to a count or a time.

    `progressive` over `render_pass` with keys `pass_key(seed, i)`: returns the mean of
    the passes as float32 [H, W, C]; with `out`, writes EXR + PNG + JSON (and
    snapshots every `snapshot_every` seconds). `devices` (None: every local device; a
    count; or a list) run one pass each at once (`_devices`; on a multi-process launch,
    `_hosts`, that many on every process): the same passes as on one device, summed on the
    devices, so the image equals the one-device image to float32 rounding of the sums. With
    `passes` not a multiple of the device count the last batch masks the passes not asked
    for. `resume` with `out`: continue the render whose set `out` holds (same scene, seed,
    algorithm and config) from its pass count up to `passes` (a total) or for `time` more
    seconds; the passes are those an uninterrupted render draws, so the result equals it to
    float32 rounding of the stored mean. `memory` (bytes, or '4G'): trace each pass in as
    many chunks as keep its working memory under it (`_memory.chunks_for_memory`, which
    sets `config.tuning.chunks`); None: the device's memory, or on the CPU the host's
    available memory (`_memory.auto_chunks`). Either way the chunks keep every index within
    int32, and an image whose buffers cannot fit the memory however many chunks is refused
    before any pass, in one line (`_memory.check_host`, `auto_chunks`). `techniques`:
    `out`'s EXR also holds every technique's image as a layer (`technique_layer` names
    them; their sum is the image), from `technique_images(merge_lengths=True)` on one
    device in one chunk."""
    check_budget(passes, time)
    local = _devices.resolve_devices(devices)
    devs = _devices.mesh_devices(local)
    config = config or RenderConfig(algorithm=algorithm)
    if config.algorithm != algorithm:
        raise ValueError(f"algorithm: {algorithm!r} disagrees with config.algorithm "
                         f"{config.algorithm!r}")
    _memory.check_host(scene)  # the image's host buffers: refused before anything runs
    if techniques:
        return _render_techniques(scene, config, passes, time, seed, snapshot_every, out,
                                  progress, exposure, scene_path, devices, resume, memory)
    if memory is not None:
        budget = _memory.parse_bytes(memory) if isinstance(memory, str) else int(memory)
        config = config.tuned(chunks=_memory.chunks_for_memory(scene, config, budget))
    else:  # the device's own memory (GPUs), or the host's (the CPU)
        config = config.tuned(chunks=_memory.auto_chunks(scene, config, local[0],
                                                         len(local)))
    state = {"config": config}
    start = None
    if resume:
        start = _resume_start(out, scene, scene_path, config, seed)
        if start is not None and passes is not None and start[0] >= passes:
            return (start[1] / start[0]).astype(np.float32)
    G = len(devs)
    cam = scene.camera
    dsum = (None if G == 1 else
            _devices.DeviceSum(render_pass, scene, devs, (cam.height, cam.width, scene.channels)))

    def run_pass(i):
        if G == 1:
            img, diag, state["config"] = render_pass_host(scene, pass_key(seed, i),
                                                          state["config"], i)
            return img, diag.nonfinite
        n = G if passes is None else min(G, passes - i)
        idx = np.arange(i, i + G)
        keys = jnp.stack([pass_key(seed, int(j)) for j in idx])
        valid = np.arange(G) < n
        sums, diag, state["config"] = with_retry(
            lambda s, k, c, p: dsum.run(k, p, valid, c), scene, keys, state["config"], idx,
            lambda d: d, scene, valid)
        dsum.add(sums)
        return n, int(np.sum(np.asarray(diag.nonfinite)[valid]))

    def meta(n, seconds, nonfinite, snapshot):
        note = _merge.radius_floor_note(scene, state["config"], n)
        return {**_meta(scene, scene_path, state["config"], n, seconds, seed, nonfinite,
                        snapshot), "devices": G, "processes": _hosts.count(),
                "warnings": [note] if note else []}

    mean, _, _ = progressive(run_pass, lambda m: m, meta, passes=passes, time=time, out=out,
                             snapshot_every=snapshot_every, progress=progress,
                             exposure=exposure, total=None if dsum is None else dsum.total,
                             start=start)
    return mean.astype(np.float32)


def technique_layer(label: Technique) -> str:
    """The EXR layer of a technique, keyed by path length k (segments) and technique:
    "k3_s1_t3" the connection of s light and t camera vertices (k = s + t - 1; s = 0 emitter
    hits, s = 1 next-event estimation, t = 1 light tracing), "k3_merge_s2_t3" photon
    y_{s-1} merged at z_{t-1} (k = s + t - 2), "merge_t3" every merge at z_{t-1} (s = 0),
    "gather" ppm's photon gather, "k2_glint" the glints (pinhole -> water surface -> light),
    "k4_manifold_t3" manifold next-event estimation from z_{t-1} through the water surface
    (k = t + 1)."""
    kind, s, t = label
    if kind == "glint":
        return "k2_glint"
    if kind == "manifold":
        return f"k{s + t - 1}_manifold_t{t}"
    if kind == "connection":
        return f"k{s + t - 1}_s{s}_t{t}"
    if kind == "merge":
        return f"k{s + t - 2}_merge_s{s}_t{t}" if s else f"merge_t{t}"
    return kind


@functools.partial(jax.jit, static_argnums=(2,))
def _technique_pass(scene, key, config, pass_index=0):
    """Every technique's image of one pass (merges split by path length), non-finite
    values zeroed and counted."""
    tech, stats = technique_images(scene, key, config, pass_index, merge_lengths=True)
    finite = jnp.isfinite(tech.images)
    return (TechniqueImages(tech.labels, jnp.where(finite, tech.images, 0.0)),
            (jnp.sum(~finite).astype(jnp.int32), stats))


def _render_techniques(scene, config, passes, time, seed, snapshot_every, out, progress,
                       exposure, scene_path, devices, resume, memory):
    """`render(techniques=True)`: `progressive` over the stacked technique images."""
    if devices is not None and len(_devices.resolve_devices(devices)) > 1:
        raise ValueError("techniques: per-technique images run on one device (devices=1)")
    if _hosts.count() > 1:
        raise ValueError("techniques: per-technique images run in one process")
    if memory is not None:
        raise ValueError("memory: not with techniques (per-technique images need one chunk)")
    if resume:
        raise ValueError("resume: not with techniques")
    state = {"config": config.tuned(chunks=1), "labels": ()}

    def run_pass(i):
        tech, (bad, _), state["config"] = with_retry(
            _technique_pass, scene, pass_key(seed, i), state["config"], i,
            lambda d: d[1], scene)
        state["labels"] = tech.labels
        return tech.images, bad

    def to_layers(m):
        return {technique_layer(lab): m[k] for k, lab in enumerate(state["labels"])}

    def meta(n, seconds, nonfinite, snapshot):
        return {**_meta(scene, scene_path, state["config"], n, seconds, seed, nonfinite,
                        snapshot), "devices": 1, "processes": 1,
                "techniques": [technique_layer(lab) for lab in state["labels"]]}

    mean, _, _ = progressive(run_pass, lambda m: m.sum(axis=0), meta, passes=passes,
                             time=time, out=out, snapshot_every=snapshot_every,
                             progress=progress, exposure=exposure, to_layers=to_layers)
    return mean.sum(axis=0).astype(np.float32)


RESUME_KEYS = ("algorithm", "seed", "width", "height", "scene_name")


def _resume_start(out, scene, scene_path, config, seed):
    """(passes done, their float64 sum) of the render in `out`'s set, checked against this
    render; None if there is no `out` yet. Process 0 reads it and broadcasts it."""
    if not out:
        raise ValueError("resume: needs out (the render to continue)")
    err, start = None, None
    if _hosts.is_lead():
        try:
            start = _read_resume(out, scene, scene_path, config, seed)
        except ValueError as e:
            err = e
    if _hosts.count() > 1:
        code = -1 if err is not None else (0 if start is None else start[0])
        (code,) = _hosts.agree((code,))
        if code < 0:
            raise err or ValueError("resume: refused by process 0 (see its message)")
        if code == 0:
            return None
        shape = (scene.camera.height, scene.camera.width, scene.channels)
        m = start[1] if start is not None else np.zeros(shape, np.float32)
        start = int(code), _hosts.broadcast(m)
    elif err is not None:
        raise err
    # the sum of the passes done, from the stored float32 mean (every process alike)
    return None if start is None else (start[0], start[1].astype(np.float64) * start[0])


def _read_resume(out, scene, scene_path, config, seed):
    if not os.path.exists(out):
        return None
    _io.recover_outputs(out)
    meta = _io.read_record(out)
    if meta is None or "passes" not in meta:
        raise ValueError(f"resume: {out}: not a jaxvcm render (no record in the EXR)")
    want = _meta(scene, scene_path, config, 0, 0.0, seed, 0, False)
    for k in RESUME_KEYS + (("scene_sha256",) if scene_path is not None else ()):
        if meta.get(k) != want[k]:
            raise ValueError(f"resume: {out} was rendered with {k} = {meta.get(k)!r}, "
                             f"this render has {want[k]!r}")
    room = ("merge_capacity", "photon_capacity")  # grown by re-runs: not the samples
    had = {k: v for k, v in meta["config"].items() if k not in room}
    now = {k: v for k, v in want["config"].items() if k not in room}
    if had != now:
        diff = sorted(k for k in set(had) | set(now) if had.get(k) != now.get(k))
        raise ValueError(f"resume: {out} was rendered with another config ({', '.join(diff)})")
    return int(meta["passes"]), _io.read_exr(out)


def _meta(scene, scene_path, config, passes, seconds, seed, nonfinite, snapshot):
    h = None
    if scene_path is not None:
        with open(scene_path, "rb") as f:
            h = hashlib.sha256(f.read()).hexdigest()
    return {
        "scene": scene_path, "scene_sha256": h, "scene_name": scene.name,
        "algorithm": config.algorithm, "config": config.record(),
        "passes": passes, "seconds": round(seconds, 3), "seed": seed,
        "nonfinite": nonfinite, "snapshot": snapshot, "version": __version__,
        "width": scene.camera.width, "height": scene.camera.height,
    }

