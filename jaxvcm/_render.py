"""The pure render pass (`render_pass`, with its `Diagnostics`) and the one host-side
progressive driver (`progressive`: pass keys, merge-capacity re-runs, time budgets,
progress bar, atomic snapshots) used by RGB `render` and spectral `render_spectral`."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import time as _time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from . import _devices, _io, _warm
from ._version import __version__
from ._config import RenderConfig
from ._integrator import integrate
from ._scene import Scene


class Diagnostics(eqx.Module):
    """Per-pass result flags (errors are values under jit)."""

    nonfinite: Int[Array, ""]  # pixel-technique contributions that were NaN/Inf (zeroed; must be 0)
    camera_paths: Int[Array, ""]  # camera subpaths traced
    light_paths: Int[Array, ""]  # light subpaths traced
    camera_vertices: Int[Array, ""]  # camera subpath vertices that existed
    light_vertices: Int[Array, ""]  # light subpath vertices that existed
    merge_overflow: Array  # the hash-grid gather ran out of candidate capacity (re-run!)
    merge_candidates: Array  # longest candidate list of a gather point: the room needed


def render_pass(scene: Scene, key: PRNGKeyArray, config: RenderConfig = RenderConfig(),
                pass_index=0) -> tuple[Float[Array, "H W C"], Diagnostics]:
    """One independent pass of `config.algorithm` on the one bidirectional core: an unbiased
    per-pixel radiance estimate from `config.spp` camera subpaths per pixel and/or as many
    light subpaths. Pure and jit/vmap/grad-able (config is static). `pass_index` (0-based)
    drives the merging radius schedule of `ppm`."""
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
    )
    return img, diag


@functools.partial(jax.jit, static_argnums=(2,))
def _render_pass_jit(scene, key, config, pass_index=0):
    return render_pass(scene, key, config, pass_index)


def with_retry(jitted_pass, scene, key, config: RenderConfig, pass_index, overflow_of,
               need_of=None):
    """Host side: run `jitted_pass(scene, key, config, pass_index)`; if the merging gather
    overflowed its static capacity (`overflow_of(diagnostics)`), re-run the same pass (same
    key) with more room (jax-md's re-allocation pattern); never truncate. The room is the
    power of two that holds the longest candidate list the pass reported (`need_of`), at
    least twice the old one, so one re-run (one new compiled program) is enough. Returns
    (estimate, diagnostics, the config that had room)."""
    while True:
        est, diag = jitted_pass(scene, key, config, pass_index)
        if not bool(np.any(overflow_of(diag))):
            return est, diag, config
        cap = 2 * config.merge_capacity
        if need_of is not None:
            need = int(np.max(np.asarray(need_of(diag))))
            cap = max(cap, 1 << max(need - 1, 1).bit_length())
        config = dataclasses.replace(config, merge_capacity=cap)


def _host_pass(scene, key, config, pass_index=0):
    """`render_pass` jitted, or (warm starts on, `_warm`) its exported module."""
    if _warm.enabled():
        return _warm.exported_pass(render_pass, Diagnostics, scene, key, config, pass_index)
    return _render_pass_jit(scene, key, config, pass_index)


def render_pass_host(scene, key, config, pass_index=0):
    """`render_pass` (jitted, or exported for warm starts: `_warm`) with the
    merge-capacity re-run of `with_retry`."""
    return with_retry(_host_pass, scene, key, config, pass_index,
                      lambda d: d.merge_overflow, lambda d: d.merge_candidates)


def pass_key(seed: int, index: int) -> PRNGKeyArray:
    """Key of pass `index` of a render with `seed`: independent of how passes are batched,
    so resumed or sharded renders draw the same samples."""
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
                snapshot_every=None, progress=True, exposure=0.0):
    """Average independent passes until `passes` are done or `time` seconds have elapsed (at
    least one pass). `run_pass(i) -> (estimate ndarray, nonfinite count)`; `to_image(mean)`
    turns the running mean into the image written; `meta(passes, seconds, nonfinite,
    snapshot)` its JSON record, to which "warnings" (one line each) is added. With `out`,
    writes EXR + PNG + JSON at the end, and with `snapshot_every` (seconds) atomic snapshots
    along the way, so a killed render leaves its last snapshot intact. The first pass
    includes the compilation: the progress line says "compiling" until it is done, and the
    snapshot clock starts when it has finished. Before anything, `out`'s set is recovered
    from an earlier killed render (`_io.recover_outputs`). Returns (mean estimate float64,
    passes done, nonfinite)."""
    passes, time = check_budget(passes, time)
    if out:
        _io.prefetch_imports()
        _io.recover_outputs(out)
    acc = None
    nonfinite = 0
    t0 = _time.perf_counter()
    last_snap = None
    bar = _io.Progress(total=passes, time_budget=time, enabled=progress)
    bar.start()
    i = 0

    def record(n, seconds, image, snapshot):
        m = meta(n, seconds, nonfinite, snapshot)
        return {**m, "warnings": render_warnings(image, nonfinite)}

    try:
        while True:
            ests, bad = run_pass(i)  # one pass, or a list of passes i, i + 1, ... (devices)
            for est in (ests if isinstance(ests, list) else [ests]):
                est = np.asarray(est, dtype=np.float64)
                acc = est if acc is None else acc + est  # in pass order, in float64
                i += 1
            nonfinite += int(bad)
            now = _time.perf_counter()
            bar.update(i, now - t0)
            done = (passes is not None and i >= passes) or (time is not None and now - t0 >= time)
            last_snap = now if last_snap is None else last_snap
            if out and snapshot_every is not None and not done and now - last_snap >= snapshot_every:
                img = to_image(acc / i).astype(np.float32)
                _io.write_outputs(out, img, record(i, now - t0, img, True), exposure)
                last_snap = now
            if done:
                break
    finally:
        bar.close()
    mean = acc / i
    img = to_image(mean).astype(np.float32)
    if nonfinite:
        import warnings

        warnings.warn("; ".join(render_warnings(img, nonfinite)))
    if out:
        _io.write_outputs(out, img, record(i, _time.perf_counter() - t0, img, False), exposure)
    return mean, i, nonfinite


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
           exposure: float = 0.0, scene_path: str | None = None, devices=None) -> np.ndarray:
    """Progressive render (`progressive`) of `render_pass` with keys `pass_key(seed, i)`:
    the mean of the passes as float32 [H, W, C]; with `out`, EXR + PNG + JSON (and
    snapshots every `snapshot_every` seconds). `devices` (None: every local device; a
    count; or a list) run one pass each at once (`_devices`): the same passes and the same
    image as on one device. With `passes` not a multiple of the device count the last
    batch computes a whole batch and keeps only the passes asked for."""
    check_budget(passes, time)
    devs = _devices.resolve_devices(devices)
    config = config or RenderConfig(algorithm=algorithm)
    if config.algorithm != algorithm:
        raise ValueError(f"algorithm: {algorithm!r} disagrees with config.algorithm "
                         f"{config.algorithm!r}")
    state = {"config": config}

    def run_pass(i):
        if len(devs) == 1:
            img, diag, state["config"] = render_pass_host(scene, pass_key(seed, i),
                                                          state["config"], i)
            return img, diag.nonfinite
        D = len(devs)
        n = D if passes is None else min(D, passes - i)
        idx = np.arange(i, i + D)
        keys = jnp.stack([pass_key(seed, int(j)) for j in idx])
        imgs, diag, state["config"] = with_retry(
            lambda s, k, c, p: _devices.sharded_passes(render_pass, s, k, c, p, devs),
            scene, keys, state["config"], idx, lambda d: d.merge_overflow,
            lambda d: d.merge_candidates)
        return list(imgs[:n]), int(np.sum(np.asarray(diag.nonfinite)[:n]))

    def meta(n, seconds, nonfinite, snapshot):
        return {**_meta(scene, scene_path, state["config"], n, seconds, seed, nonfinite,
                        snapshot), "devices": len(devs)}

    mean, _, _ = progressive(run_pass, lambda m: m, meta, passes=passes, time=time, out=out,
                             snapshot_every=snapshot_every, progress=progress,
                             exposure=exposure)
    return mean.astype(np.float32)


def _meta(scene, scene_path, config, passes, seconds, seed, nonfinite, snapshot):
    h = None
    if scene_path is not None:
        with open(scene_path, "rb") as f:
            h = hashlib.sha256(f.read()).hexdigest()
    return {
        "scene": scene_path, "scene_sha256": h, "scene_name": scene.name,
        "algorithm": config.algorithm, "config": dataclasses.asdict(config),
        "passes": passes, "seconds": round(seconds, 3), "seed": seed,
        "nonfinite": nonfinite, "snapshot": snapshot, "version": __version__,
        "width": scene.camera.width, "height": scene.camera.height,
    }

