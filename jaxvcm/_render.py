"""Pure-JAX render pass and the host-side progressive driver."""

from __future__ import annotations

import functools
import time as _time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ._bidir import render_pass_bidir, uses_camera_paths, uses_light_paths
from ._config import RenderConfig
from ._scene import Scene


class Diagnostics(eqx.Module):
    """Per-pass result flags (errors are values under jit)."""

    nonfinite: Int[Array, ""]  # pixel-technique contributions that were NaN/Inf (zeroed; must be 0)
    camera_paths: Int[Array, ""]  # camera subpaths traced
    light_paths: Int[Array, ""]  # light subpaths traced
    camera_vertices: Int[Array, ""]  # camera subpath vertices that existed
    light_vertices: Int[Array, ""]  # light subpath vertices that existed
    merge_overflow: Array  # the hash-grid gather ran out of candidate capacity (re-run!)


def render_pass(scene: Scene, key: PRNGKeyArray, config: RenderConfig = RenderConfig(),
                pass_index=0) -> tuple[Float[Array, "H W C"], Diagnostics]:
    """One independent pass of `config.algorithm` on the one bidirectional core: an unbiased
    per-pixel radiance estimate from `config.spp` camera subpaths per pixel and/or as many
    light subpaths. Pure and jit/vmap/grad-able (config is static). `pass_index` (0-based)
    drives the merging radius schedule of `ppm`."""
    cam = scene.camera
    N = cam.height * cam.width * config.spp
    img, bad, stats = render_pass_bidir(scene, key, config, pass_index)
    zero = jnp.zeros((), jnp.int32)
    diag = Diagnostics(
        nonfinite=bad,
        camera_paths=jnp.asarray(N if uses_camera_paths(config.algorithm) else 0, jnp.int32),
        light_paths=jnp.asarray(N if uses_light_paths(config.algorithm) else 0, jnp.int32),
        camera_vertices=stats.get("camera_vertices", zero).astype(jnp.int32),
        light_vertices=stats.get("light_vertices", zero).astype(jnp.int32),
        merge_overflow=stats.get("merge_overflow", jnp.zeros((), bool)),
    )
    return img, diag


@functools.partial(jax.jit, static_argnums=(2,))
def _render_pass_jit(scene, key, config, pass_index=0):
    return render_pass(scene, key, config, pass_index)


def render_pass_host(scene, key, config, pass_index=0):
    """Host-side pass: if the merging gather overflowed its static capacity, re-run the same
    pass (same key) with twice the room (jax-md's re-allocation pattern); never truncate."""
    import dataclasses

    while True:
        img, diag = _render_pass_jit(scene, key, config, pass_index)
        if not bool(diag.merge_overflow):
            return img, diag, config
        config = dataclasses.replace(config, merge_capacity=2 * config.merge_capacity)


def pass_key(seed: int, index: int) -> PRNGKeyArray:
    """Key of pass `index` of a render with `seed`: independent of how passes are batched,
    so resumed or sharded renders draw the same samples."""
    return jax.random.fold_in(jax.random.key(seed), index)


def render(scene: Scene, algorithm: str = "pt", passes: int | None = None,
           time: float | None = None, seed: int = 0, snapshot_every: float | None = None,
           out: str | None = None, config: RenderConfig | None = None, progress: bool = True,
           exposure: float = 0.0, scene_path: str | None = None) -> np.ndarray:
    """Progressive render: average independent passes until `passes` are done or `time`
    seconds have elapsed (at least one pass). With `out`, writes EXR + PNG + JSON, and with
    `snapshot_every` (seconds) writes atomic snapshots along the way, so a killed render
    leaves its last snapshot intact."""
    from . import _io as _film

    if passes is None and time is None:
        passes = 16
    if passes is not None and passes < 1:
        raise ValueError(f"passes: must be >= 1, got {passes}")
    if time is not None and not time > 0:
        raise ValueError(f"time: must be > 0 seconds, got {time}")
    config = config or RenderConfig(algorithm=algorithm)
    if config.algorithm != algorithm:
        raise ValueError(f"algorithm: {algorithm!r} disagrees with config.algorithm "
                         f"{config.algorithm!r}")
    acc = None
    nonfinite = 0
    t0 = _time.perf_counter()
    last_snap = t0
    bar = _film.Progress(total=passes, time_budget=time, enabled=progress)
    i = 0
    try:
        while True:
            img, diag, config = render_pass_host(scene, pass_key(seed, i), config, i)
            img = np.asarray(img, dtype=np.float64)
            nonfinite += int(diag.nonfinite)
            acc = img if acc is None else acc + img
            i += 1
            now = _time.perf_counter()
            bar.update(i, now - t0)
            done = (passes is not None and i >= passes) or (time is not None and now - t0 >= time)
            if out and snapshot_every is not None and not done and now - last_snap >= snapshot_every:
                _film.write_outputs(out, (acc / i).astype(np.float32), _meta(
                    scene, scene_path, config, i, now - t0, seed, nonfinite, snapshot=True),
                    exposure)
                last_snap = now
            if done:
                break
    finally:
        bar.close()
    image = (acc / i).astype(np.float32)
    if nonfinite:
        import warnings

        warnings.warn(f"render: {nonfinite} non-finite path contributions were zeroed")
    if out:
        _film.write_outputs(out, image, _meta(scene, scene_path, config, i,
                                              _time.perf_counter() - t0, seed, nonfinite,
                                              snapshot=False), exposure)
    return image


def _meta(scene, scene_path, config, passes, seconds, seed, nonfinite, snapshot):
    import dataclasses
    import hashlib

    from . import __version__

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
