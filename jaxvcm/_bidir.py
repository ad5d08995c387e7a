"""A pass of the bidirectional core: camera subpaths, light subpaths, and the techniques
the algorithm enables (pt: s = 0, 1; lt: t = 1; bdpt: all connections; ppm: photon
gathering at the first non-delta camera vertex; bpm: merging at every camera vertex (+
emitter hits); vcm: all connections and all merges), each weighted by explicit-sum MIS
over the techniques that algorithm has.

Stages, in a straight line:
    camera rays -> camera subpaths -> [s = 0] emitter hits -> [s = 1] next-event estimation
    light emission -> light subpaths -> [t = 1] light tracing splats -> [s, t >= 2] connections
    -> [merging] hash grid over light vertices, gather at camera vertices (ppm / bpm / vcm)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, PRNGKeyArray

from . import _camera
from . import _connect as CN
from . import _lights as Lt
from . import _subpath as SP
from ._config import RenderConfig
from ._scene import Scene


def uses_camera_paths(algorithm: str) -> bool:
    return algorithm in ("pt", "bdpt", "ppm", "bpm", "vcm")


def uses_light_paths(algorithm: str) -> bool:
    return algorithm in ("lt", "bdpt", "ppm", "bpm", "vcm")


def technique_images(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0
                     ) -> tuple[dict[tuple[int, int], Array], dict]:
    """Weighted contribution of every (s, t) technique as its own [H, W, C] image; merging
    at camera vertex z_j under the key (-1, j) (bpm, vcm), and `ppm`'s gather under "ppm".
    `pass_index` drives the merging radius."""
    cam = scene.camera
    H, W, C = cam.height, cam.width, scene.channels
    P = H * W
    N = P * cfg.spp
    D = cfg.max_depth
    dt = cam.origin.dtype
    kc, kp, kn, ke, kl = jax.random.split(key, 5)
    out: dict = {}
    stats = {}
    merging = cfg.algorithm in ("bpm", "vcm")
    if merging:
        from ._merge import pass_radius

        radius = pass_radius(cfg, scene, pass_index)
        etas = CN.log_etas(radius, N, dt)
    else:
        etas = (0.0, 0.0)

    # ---- camera subpaths ----
    pixel = jnp.arange(N, dtype=jnp.int32) % P
    if uses_camera_paths(cfg.algorithm):
        u_cam = jax.random.uniform(kc, (2, N), dt)
        o, d = jax.vmap(_camera.generate_ray, in_axes=(None, 0, 0, 0))(cam, pixel, u_cam[0], u_cam[1])
        _, imp, _ = jax.vmap(lambda w: CN.camera_importance(scene, w))(d)
        s0 = jax.vmap(SP.camera_start, in_axes=(None, 0, 0, 0))(scene, o, d, jax.lax.stop_gradient(imp))
        u = jax.random.uniform(kp, (D, N, SP.N_UNIFORMS), dt)
        cverts, _ = SP.trace(scene, cfg, True, s0, u, D)
        cends = CN.camera_ends(scene, o, cverts, N)
        if cfg.algorithm != "ppm":
            out.update(CN.emitter_hits(scene, cfg, cends, cverts, etas))
        if D >= 2 and cfg.algorithm in ("pt", "bdpt", "vcm"):
            u_nee = jax.random.uniform(kn, (D - 1, N, 3), dt)
            out.update(CN.next_event(scene, cfg, cends, u_nee, etas))
        stats["camera_vertices"] = jnp.sum(cverts.alive)
    # ---- light subpaths ----
    if uses_light_paths(cfg.algorithm):
        e = jax.vmap(Lt.sample_emission, in_axes=(None, 0))(
            scene, jax.random.uniform(ke, (N, 5), dt))
        s0 = jax.vmap(SP.light_start, in_axes=(None, 0))(scene, e)
        n_steps = max(D - 1, 1)
        u = jax.random.uniform(kl, (n_steps, N, SP.N_UNIFORMS), dt)
        lverts, rev0 = SP.trace(scene, cfg, False, s0, u, n_steps)
        lends = CN.light_ends(scene, e, rev0, lverts, N)
        cam_o = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,)),
                             _camera.generate_ray(cam, jnp.int32(0), jnp.zeros((), dt), jnp.zeros((), dt))[0])
        if cfg.algorithm == "ppm":
            from ._merge import pass_radius, photon_gather

            r = pass_radius(cfg, scene, pass_index)
            out["ppm"], stats["merge_overflow"] = photon_gather(scene, cfg, cends, cverts, lends, r)
        elif cfg.algorithm in ("lt", "bdpt", "vcm"):
            out.update(CN.light_tracing(scene, cfg, lends, e, cam_o, etas))
        if cfg.algorithm in ("bdpt", "vcm"):
            out.update(CN.connections(scene, cfg, lends, cends, e, etas))
        if merging and D >= 2:
            from ._merge import vertex_merging

            vm, stats["merge_overflow"] = vertex_merging(scene, cfg, cends, lends, e, radius)
            for j in range(vm.shape[0]):
                out[(-1, j + 1)] = vm[j]  # key (-1, j): merging at camera vertex z_j
        stats["light_vertices"] = jnp.sum(lverts.alive)
    # ---- film ----
    images = {}
    for key_st, val in out.items():
        if isinstance(val, tuple):  # light-tracing splat (pixel, value): each of the N
            pix, v = val                 # light paths carries 1/N already, whatever spp is
            img = jnp.zeros((P, C), dt).at[pix].add(v)
            images[key_st] = img.reshape(H, W, C)
        else:
            images[key_st] = val.reshape(cfg.spp, H, W, C).mean(axis=0)
    return images, stats


def render_pass_bidir(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0):
    images, stats = technique_images(scene, key, cfg, pass_index)
    cam = scene.camera
    img = jnp.zeros((cam.height, cam.width, scene.channels), cam.origin.dtype)
    bad = jnp.zeros((), jnp.int32)
    for v in images.values():
        finite = jnp.isfinite(v)
        bad = bad + jnp.sum(~finite).astype(jnp.int32)
        img = img + jnp.where(finite, v, 0.0)
    return img, bad, stats
