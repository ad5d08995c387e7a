"""One pass of the bidirectional core: camera subpaths, light subpaths, and the techniques
the algorithm enables (`_config.TECHNIQUES`: pt s = 0, 1; lt t = 1; bdpt all connections;
ppm photon gathering at the first non-delta camera vertex; bpm merging at every camera
vertex plus emitter hits; vcm all connections and all merges), each weighted by MIS over
the techniques that algorithm has.

Stages, in a straight line:
    camera rays -> camera subpaths -> [s = 0] emitter hits -> [s = 1] next-event estimation
    light emission -> light subpaths -> [t = 1] light tracing splats -> [s, t >= 2] connections
    -> [merging] hash grid over light vertices, gather at camera vertices (ppm / bpm / vcm)
    -> film: every technique's image, summed with non-finite contributions counted
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from . import _camera as camera
from . import _connect as connect
from . import _lights as lights
from . import _merge as merge
from . import _path as path
from . import _subpath as subpath
from ._config import RenderConfig
from ._scene import Scene


class Technique(NamedTuple):
    """Label of one technique image.

    kind "connection": the (s, t) technique (s light vertices, t camera vertices;
         s = 0 emitter hits, s = 1 next-event estimation, t = 1 light tracing);
    kind "merge": vertex merging at camera vertex z_{t-1} (bpm, vcm), every path length
         (s = 0: any number of light vertices);
    kind "gather": ppm's photon gather (s = t = 0).
    """

    kind: str
    s: int
    t: int


class TechniqueImages(eqx.Module):
    """The weighted contribution of every technique of a pass, one [H, W, C] image each
    (leading batch axes allowed, e.g. under vmap over keys)."""

    labels: tuple[Technique, ...] = eqx.field(static=True)
    images: Float[Array, "*batch K H W C"]

    def __getitem__(self, label: Technique) -> Float[Array, "*batch H W C"]:
        return self.images[..., self.labels.index(label), :, :, :]

    def items(self):
        return [(lab, self.images[..., i, :, :, :]) for i, lab in enumerate(self.labels)]


class PassStats(eqx.Module):
    """What a pass counted, besides its image."""

    camera_vertices: Int[Array, ""]
    light_vertices: Int[Array, ""]
    merge_overflow: Bool[Array, ""]
    merge_candidates: Int[Array, ""]  # longest hash-grid candidate list of a gather point


def technique_images(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0
                     ) -> tuple[TechniqueImages, PassStats]:
    """Every technique's weighted image of one pass (`Technique` labels), and its stats.
    `pass_index` drives the merging radius schedule."""
    cam = scene.camera
    H, W, C = cam.height, cam.width, scene.channels
    P = H * W
    N = P * cfg.spp
    D = cfg.max_depth
    dt = cam.origin.dtype
    kc, kp, kn, ke, kl = jax.random.split(key, 5)
    tech = cfg.techniques
    out: dict = {}
    zero = jnp.zeros((), jnp.int32)
    camera_vertices, light_vertices, overflow, need = zero, zero, jnp.zeros((), bool), zero
    if tech.merging is not None:
        radius = merge.pass_radius(cfg, scene, pass_index)
    etas = merge.log_etas(radius, N, dt) if tech.merging == "all" else (0.0, 0.0)

    # ---- subpaths: camera and light starts, then one trace (both in one when both run) ----
    pixel = jnp.arange(N, dtype=jnp.int32) % P
    if tech.camera_paths:
        u_cam = jax.random.uniform(kc, (2, N), dt)
        o, d = jax.vmap(camera.generate_ray, in_axes=(None, 0, 0, 0))(cam, pixel, u_cam[0], u_cam[1])
        _, imp, _ = jax.vmap(lambda w: camera.camera_importance(scene, w))(d)
        c0 = jax.vmap(subpath.camera_start, in_axes=(None, 0, 0, 0))(scene, o, d, jax.lax.stop_gradient(imp))
        uc = jax.random.uniform(kp, (D, N, subpath.N_UNIFORMS), dt)
    if tech.light_paths:
        e = jax.vmap(lights.sample_emission, in_axes=(None, 0))(
            scene, jax.random.uniform(ke, (N, 5), dt))
        l0 = jax.vmap(subpath.light_start, in_axes=(None, 0))(scene, e)
        n_steps = max(D - 1, 1)
        ul = jax.random.uniform(kl, (n_steps, N, subpath.N_UNIFORMS), dt)
    if tech.camera_paths and tech.light_paths:
        cverts, (lverts, rev0) = subpath.trace_both(scene, cfg, c0, uc, D, l0, ul, n_steps)
    elif tech.camera_paths:
        cverts, _ = subpath.trace(scene, cfg, True, c0, uc, D)
    else:
        lverts, rev0 = subpath.trace(scene, cfg, False, l0, ul, n_steps)

    # ---- MIS partial sums of each subpath (O(D) per subpath, then O(1) per technique) ----
    joins = path.joins_partials(cfg)
    cparts = lparts = None
    log_n = path.log_n_light_tracing(cfg, N, dt)
    if tech.camera_paths:
        cends = subpath.camera_ends(scene, o, cverts, N)
    if tech.light_paths:
        lends = subpath.light_ends(scene, e, rev0, lverts, N)
    if joins and tech.camera_paths and tech.light_paths:
        lparts, cparts = path.both_partials(cfg, path.pdfs(lends), path.pdfs(cends), e.delta,
                                            log_n, etas)
    elif joins and tech.camera_paths:
        cparts = path.camera_partials(cfg, path.pdfs(cends), log_n, etas)
    elif joins:
        lparts = path.light_partials(cfg, path.pdfs(lends), e.delta, etas)
    parts = (lparts, cparts) if joins else None

    # ---- camera-side techniques ----
    if tech.camera_paths:
        if tech.emitter_hits and tech.merging != "first":  # ppm: in its gather
            out.update(connect.emitter_hits(scene, cfg, cends, cverts, etas, parts))
        if D >= 2 and tech.nee:
            u_nee = jax.random.uniform(kn, (D - 1, N, 3), dt)
            out.update(connect.next_event(scene, cfg, cends, u_nee, etas, parts))
        camera_vertices = jnp.sum(cverts.alive)
    # ---- light-side techniques ----
    if tech.light_paths:
        cam_o = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,)),
                             camera.generate_ray(cam, jnp.int32(0), jnp.zeros((), dt), jnp.zeros((), dt))[0])
        if tech.merging == "first":
            out[Technique("gather", 0, 0)], overflow, need = merge.photon_gather(
                scene, cfg, cends, cverts, lends, radius)
        if tech.light_tracing:
            out.update(connect.light_tracing(scene, cfg, lends, e, cam_o, etas, parts))
        if tech.connections:
            out.update(connect.connections(scene, cfg, lends, cends, e, etas, parts))
        if tech.merging == "all" and D >= 2:
            vm, overflow, need = merge.vertex_merging(scene, cfg, cends, lends, e, radius, parts)
            for j in range(vm.shape[0]):
                out[Technique("merge", 0, j + 2)] = vm[j]  # merging at camera vertex z_{j+1}
        light_vertices = jnp.sum(lverts.alive)
    # ---- film ----
    labels, images = [], []
    for label, val in out.items():
        if not isinstance(label, Technique):
            label = Technique("connection", *label)
        if isinstance(val, tuple):  # light-tracing splat (pixel, value): each of the N
            pix, v = val                 # light paths carries 1/N already, whatever spp is
            img = jnp.zeros((P, C), dt).at[pix].add(v).reshape(H, W, C)
        else:
            img = val.reshape(cfg.spp, H, W, C).mean(axis=0)
        labels.append(label)
        images.append(img)
    stats = PassStats(camera_vertices.astype(jnp.int32), light_vertices.astype(jnp.int32),
                      overflow, need)
    return TechniqueImages(tuple(labels), jnp.stack(images)), stats


def integrate(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0
              ) -> tuple[Float[Array, "H W C"], Int[Array, ""], PassStats]:
    """The pass's image (the sum of its technique images, non-finite contributions zeroed),
    the number of non-finite contributions, and its stats."""
    tech, stats = technique_images(scene, key, cfg, pass_index)
    cam = scene.camera
    img = jnp.zeros((cam.height, cam.width, scene.channels), cam.origin.dtype)
    bad = jnp.zeros((), jnp.int32)
    for _, v in tech.items():
        finite = jnp.isfinite(v)
        bad = bad + jnp.sum(~finite).astype(jnp.int32)
        img = img + jnp.where(finite, v, 0.0)
    return img, bad, stats
