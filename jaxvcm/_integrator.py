"""One pass of the bidirectional core: camera subpaths, light subpaths, and the techniques
the algorithm enables (`_config.TECHNIQUES`: pt s = 0, 1; lt t = 1; bdpt all connections;
ppm photon gathering at the first non-delta camera vertex; bpm merging at every camera
vertex plus emitter hits; vcm all connections and all merges), each weighted by MIS over
the techniques that algorithm has.

The pass is a straight line of named stages `stage(scene, cfg, state) -> state` over a
`PassState` (`pass_stages(cfg)` lists the ones the algorithm runs):
    setup (keys, merging radius) -> camera rays -> light emission -> subpaths (one trace of
    both when both run) -> mis partials -> [s = 0] emitter hits -> vertex connection ([s =
    1] next-event estimation, [t = 1] light tracing splats, [s, t >= 2] connections: one
    work queue) -> [merging] hash grid over light vertices, gather at camera vertices
    (ppm / bpm / vcm) -> film: every technique's image
`technique_images` composes them inside the caller's jit; `profile_stages` jits and times
each on its own. A PT pass that wants only its image (`integrate`, explicit MIS form)
runs setup -> camera rays -> one trace that evaluates the emitter hits and next-event
estimation at each vertex as it is made (`_inline`; no records) -> film.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from . import _camera as camera
from . import _connect as connect
from . import _glints as glints
from . import _mnee as mnee
from . import _inline as inline
from . import _lights as lights
from . import _merge as merge
from . import _path as path
from . import _subpath as subpath
from ._config import RenderConfig
from ._lights import Emission
from ._merge import Merged, Radii
from ._mis import SubpathMIS, mis_form
from ._scene import Scene
from ._subpath import PathEnds, Vertex, WalkState
from ._uniforms import Uniforms
from ._vec import Vec3


class Technique(NamedTuple):
    """The label of one technique image: its kind and its (s, t).

    kind "connection": the (s, t) technique (s light vertices, t camera vertices;
         s = 0 emitter hits, s = 1 next-event estimation, t = 1 light tracing);
    kind "merge": vertex merging at camera vertex z_{t-1} (bpm, vcm), every path length
         (s = 0: any number of light vertices), or with `technique_images(merge_lengths=True)`
         of photon y_{s-1} only (s >= 2: a path of s + t - 2 segments);
    kind "gather": ppm's photon gather (s = t = 0);
    kind "sum": in a pass that wants only its image (`integrate`), vertex connection's
         techniques summed: next-event estimation and the connections (s, t >= 2) per
         camera path (s = 1, t = 0), light tracing's splats per pixel (s = 0, t = 1,
         a splat onto every pixel): its queue adds each item into its row, so none of its
         D^2 / 2 techniques writes an [N, C] buffer of its own (the emitter hits, D
         techniques, keep one value per technique); and PT's emitter hits and next-event
         estimation summed per path inside the camera trace (s = 0, t = 0;
         docs/design/pass.md, "PT's inline route").
    """

    kind: str
    s: int
    t: int


class TechniqueImages(eqx.Module):
    """The weighted contribution of every technique of a pass, one image each.

    `images` [..., K, H, W, C] in the order of `labels` (leading batch axes allowed, e.g.
    under vmap over keys); indexing with a `Technique` label reads one image, `items()`
    lists (label, image) pairs."""

    labels: tuple[Technique, ...] = eqx.field(static=True)
    images: Float[Array, "*batch K H W C"]

    def __getitem__(self, label: Technique) -> Float[Array, "*batch H W C"]:
        return self.images[..., self.labels.index(label), :, :, :]

    def items(self):
        return [(lab, self.images[..., i, :, :, :]) for i, lab in enumerate(self.labels)]


class PassStats(eqx.Module):
    """What a pass counted, besides its image (int32 counts; summed over chunks they
    saturate at 2^31 - 1)."""

    camera_vertices: Int[Array, ""]
    light_vertices: Int[Array, ""]
    merge_overflow: Bool[Array, ""]  # merging missed something (candidates or photons)
    merge_candidates: Int[Array, ""]  # longest hash-grid candidate list of a gather point
    photon_overflow: Bool[Array, ""]  # more valid photons than the grid's photon room
    merge_photons: Int[Array, ""]  # valid photons of the pass (largest chunk)
    merge_imprecise: Bool[Array, ""]  # the hash grid could not resolve the merging radius


Splat = tuple[Int[Array, " N"], Float[Array, "N C"]]  # light tracing: (pixel, value)


class PassState(eqx.Module):
    """What the stages of one pass have produced so far (None: not yet, or not run). A
    pytree: `profile_stages` hands it from one jitted stage to the next. N: the chunk's
    camera paths (and light paths), D: max_depth."""

    key: PRNGKeyArray
    pass_index: Int[Array, ""] | int
    chunk: Int[Array, ""] | int = 0  # which chunk of the pass's paths (`Tuning.chunks`)
    # ---- setup
    keys: PRNGKeyArray | None = None  # [5]: camera rays, camera paths, NEE, emission, light paths
    radius: Radii | None = None  # this pass's merging radii (merging algorithms)
    etas: tuple[Float[Array, ""], Float[Array, ""]] | None = None  # log eta_VCM (surface,
    # medium) when every camera vertex merges
    # ---- camera rays, light emission: the subpaths' starts (consumed by the trace)
    origins: Vec3 | None = None  # camera ray origins [N]
    cam_start: WalkState | None = None
    cam_u: Uniforms | None = None
    emission: Emission | None = None  # y_0 of every light subpath [N]
    light_start: WalkState | None = None
    light_u: Uniforms | None = None
    # ---- subpaths: their records [D, N] and the records with their start vertex
    cverts: Vertex | None = None
    lverts: Vertex | None = None  # [max(D - 1, 1), N]
    cends: PathEnds | None = None
    lends: PathEnds | None = None
    n_cverts: Int[Array, ""] | None = None  # live camera vertices, when no records are kept
    # ---- MIS: (light, camera) per-subpath state
    parts: tuple[SubpathMIS, SubpathMIS] | None = None
    # ---- glints: F_pixel of the glints' light points and of the emitter hits' paths
    glint_roots: glints.Found | None = None
    # ---- techniques: per label, [N, C] per camera path or a light-tracing splat
    merge_lengths: bool = eqx.field(static=True, default=False)  # merges split by photon
    labels: tuple[Technique, ...] = eqx.field(static=True, default=())
    values: tuple[Float[Array, "N C"] | Splat, ...] = ()
    bad: Int[Array, ""] | int = 0  # non-finite values of techniques summed per path
    merged: Merged | None = None  # merging's overflow flags, candidates and photons
    # ---- film
    images: TechniqueImages | None = None
    stats: PassStats | None = None

    @property
    def mis_etas(self):
        return (0.0, 0.0) if self.etas is None else self.etas


Stage = Callable[[Scene, RenderConfig, PassState], PassState]


def _dims(scene: Scene, cfg: RenderConfig):
    """(pixels P, paths N of one chunk, max depth D, dtype)."""
    cam = scene.camera
    P = cam.height * cam.width
    return P, P * cfg.spp // cfg.tuning.chunks, cfg.max_depth, cam.origin.dtype


# ---- int32 indices: the library runs with x64 off, so every index is an int32. Within a
# chunk of N paths the largest flat index space is `index_factor(cfg)` N items (a work
# queue over (technique, path) items, the hash grid's photon slots and table); keeping it
# at most INDEX_ITEMS leaves every index, padding and fill value included (a queue pads
# to less than twice its items, the table is the power of two above its photons), below
# 2^31. Across chunks only path numbers (pixel = path mod pixels) and counts remain, hence
# MAX_PASS_PATHS. Chunks are chosen so that both hold (`min_chunks`); `check_chunks`
# refuses a configuration that breaks them before anything is traced.
INDEX_ITEMS = 1 << 30
MAX_PASS_PATHS = (1 << 31) - 1


def index_factor(cfg: RenderConfig) -> int:
    """Flat items per path of the largest index space of a chunk: the D + 1 vertex rows of a
    subpath (emitter hits, manifold NEE, photons and gather points queue at most D items
    per path), the trace's two lanes per path, vertex connection's techniques (next-event
    estimation D - 1, light tracing D, the connections' (D - 1) (D - 2) / 2 (s, t) pairs,
    one queue), the glints' light samples per path times the roots kept per sample."""
    D = cfg.max_depth
    f = max(2, D + 1, connect.queue_rows(cfg))
    if cfg.glints:
        f = max(f, glints.SAMPLES * (1 + glints.EXTRA))
    return f


def max_chunk_paths(cfg: RenderConfig) -> int:
    """The most paths one chunk may hold so that its indices fit int32 (INDEX_ITEMS)."""
    return INDEX_ITEMS // index_factor(cfg)


def fewest_chunks(n: int, most: int) -> int:
    """The fewest chunks k dividing n paths with n / k <= most (k = n at worst)."""
    if n <= most:
        return 1
    want = -(-n // max(most, 1))
    best = n
    d = 1
    while d * d <= n:  # the divisors of n in pairs (d, n / d)
        if n % d == 0:
            for k in (d, n // d):
                if want <= k < best:
                    best = k
        d += 1
    return best


def min_chunks(scene: Scene, cfg: RenderConfig) -> int:
    """The fewest chunks whose indices fit int32 (`max_chunk_paths`)."""
    cam = scene.camera
    return fewest_chunks(cam.height * cam.width * cfg.spp, max_chunk_paths(cfg))


def check_chunks(scene: Scene, cfg: RenderConfig) -> None:
    """The pass's paths must fit int32 (MAX_PASS_PATHS), the chunks must split them evenly,
    and each chunk's indices must fit int32 (`max_chunk_paths`)."""
    cam = scene.camera
    n = cam.height * cam.width * cfg.spp
    k = cfg.tuning.chunks
    size = f"{cam.width} x {cam.height} x {cfg.spp} spp"
    if n > MAX_PASS_PATHS:
        raise ValueError(f"config.spp: a pass of {size} = {n} paths is more than "
                         f"{MAX_PASS_PATHS} (int32 path numbers); use fewer spp per pass "
                         f"and more passes")
    if n % k:
        raise ValueError(f"config.tuning.chunks: {k} does not divide the pass's "
                         f"{n} paths ({size})")
    if n // k > max_chunk_paths(cfg):
        raise ValueError(f"config.tuning.chunks: chunks of {n // k} paths ({size} in {k}) "
                         f"are more than the {max_chunk_paths(cfg)} whose indices fit int32 "
                         f"({cfg.algorithm} at depth {cfg.max_depth}: {index_factor(cfg)} "
                         f"items per path); use at least {min_chunks(scene, cfg)} chunks")


def _path_pixels(scene: Scene, cfg: RenderConfig, st) -> Int[Array, " N"]:
    """The pixel of each camera path of chunk `st.chunk`."""
    P, N, _, _ = _dims(scene, cfg)
    return ((st.chunk * N + jnp.arange(N, dtype=jnp.int32)) % P).astype(jnp.int32)


def _light_steps(cfg: RenderConfig) -> int:
    return max(cfg.max_depth - 1, 1)


def _add(st: PassState, out: dict) -> PassState:
    """`st` with the technique images of `out` added (dict update: a label already there
    keeps its place and takes the new value)."""
    labels, values = list(st.labels), list(st.values)
    for label, val in out.items():
        if not isinstance(label, Technique):
            label = Technique("connection", *label)
        if label in labels:
            values[labels.index(label)] = val
        else:
            labels.append(label)
            values.append(val)
    return dataclasses.replace(st, labels=tuple(labels), values=tuple(values))


# ---- setup: the pass's random keys and merging radius
def setup(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    _, N, _, dt = _dims(scene, cfg)
    tech = cfg.techniques
    radius = etas = None
    if tech.merging is not None:
        radius = merge.pass_radius(cfg, scene, st.pass_index)
    if tech.merging == "all":
        etas = merge.log_etas(radius, N, dt)
    zero, no = jnp.zeros((), jnp.int32), jnp.zeros((), bool)
    return dataclasses.replace(st, keys=jax.random.split(st.key, 5), radius=radius,
                               etas=etas, merged=merge.Merged(no, zero, zero, no, no))


# ---- camera rays: one per path through its pixel, and the camera subpaths' uniforms
def camera_rays(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    cam = scene.camera
    P, N, D, dt = _dims(scene, cfg)
    pixel = _path_pixels(scene, cfg, st)
    u_cam = Uniforms.draw(st.keys[0], (1, 2, N), dt).dense()[0]
    o, d = jax.vmap(camera.generate_ray, in_axes=(None, 0, 0, 0))(cam, pixel, u_cam[0], u_cam[1])
    _, imp, _ = jax.vmap(lambda w: camera.camera_importance(scene, w))(d)
    c0 = jax.vmap(subpath.camera_start, in_axes=(None, 0, 0, 0))(
        scene, o, d, jax.lax.stop_gradient(imp))
    c0 = c0._replace(carry=mis_form(cfg).camera_carry(cfg, N, st.mis_etas, dt))
    uc = Uniforms.draw(st.keys[1], (D, N, subpath.N_UNIFORMS), dt)  # hashed where used
    return dataclasses.replace(st, origins=o, cam_start=c0, cam_u=uc)


# ---- light emission: y_0 and the first ray of every light subpath, and their uniforms
def light_emission(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    _, N, _, dt = _dims(scene, cfg)
    e = jax.vmap(lights.sample_emission, in_axes=(None, 0))(
        scene, Uniforms.draw(st.keys[3], (1, N, 5), dt).dense()[0])
    l0 = jax.vmap(subpath.light_start, in_axes=(None, 0))(scene, e)
    l0 = l0._replace(carry=mis_form(cfg).light_carry(cfg, e, st.mis_etas, dt))
    ul = Uniforms.draw(st.keys[4], (_light_steps(cfg), N, subpath.N_UNIFORMS), dt)
    return dataclasses.replace(st, emission=e, light_start=l0, light_u=ul)


# ---- subpaths: one trace (camera and light lanes together when both run), then the
#      records with their start vertices
def subpaths(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    _, N, D, dt = _dims(scene, cfg)
    tech = cfg.techniques
    n_steps = _light_steps(cfg)
    cverts = lverts = cends = lends = None
    ctx = mis_form(cfg).trace_context(cfg, st.mis_etas, path.log_n_light_tracing(cfg, N, dt),
                                      dt)
    cm0 = None if st.cam_start is None else st.cam_start.carry
    lm0 = None if st.light_start is None else st.light_start.carry
    # the records come back with the start vertices z_0 / y_0 as row 0 (`subpath.trace`'s
    # v0), so that they are the `PathEnds` as they are
    c0 = l0 = None
    if tech.camera_paths:
        c0 = subpath.camera_start_record(scene, st.origins, N, cm0)
    if tech.light_paths:
        l0 = subpath.light_start_record(scene, st.emission, lm0)
    # (and packed per dtype as the trace keeps them: `VertexTable`, read by the joins)
    if tech.camera_paths and tech.light_paths:
        (cfull, ctab), (lfull, ltab) = subpath.trace_both(
            scene, cfg, st.cam_start, st.cam_u, D, st.light_start, st.light_u, n_steps, ctx,
            (c0, l0))
    elif tech.camera_paths:
        cfull, ctab = subpath.trace(scene, cfg, True, st.cam_start, st.cam_u, D, mis_ctx=ctx,
                                    v0=c0)
        ctab = None if ctab is None else subpath.VertexTable(*ctab, 0, False)
    else:
        lfull, ltab = subpath.trace(scene, cfg, False, st.light_start, st.light_u, n_steps,
                                    mis_ctx=ctx, v0=l0)
        ltab = None if ltab is None else subpath.VertexTable(*ltab, 0, True)
    tail = lambda v: jax.tree.map(lambda a: a[1:], v)  # noqa: E731 (the records alone)
    if tech.camera_paths:
        cends, cverts = subpath.ends(cfull, False, ctab), tail(cfull)
    if tech.light_paths:
        lends, lverts = subpath.ends(lfull, True, ltab), tail(lfull)
    return dataclasses.replace(st, cverts=cverts, lverts=lverts, cends=cends, lends=lends,
                               cam_start=None, cam_u=None, light_start=None, light_u=None)


# ---- PT, image only: camera subpaths with the emitter hits and next-event estimation
#      evaluated at each vertex inside the trace (`_inline`): no records, no MIS tables
def camera_paths_inline(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    _, N, D, dt = _dims(scene, cfg)
    # the light samples' uniforms: the table `next_event` draws, row j - 1 for z_j
    u_nee = Uniforms.draw(st.keys[2], (D - 1, N, 3), dt) if D >= 2 else None
    est = functools.partial(inline.estimate, scene, cfg, inline.uniforms(u_nee))
    val, bad, n_v = subpath.trace(scene, cfg, True, inline.start(st.cam_start), st.cam_u, D,
                                  estimate=est)
    st = _add(st, {Technique("sum", 0, 0): val})
    return dataclasses.replace(st, bad=st.bad + bad, n_cverts=n_v, cam_start=None,
                               cam_u=None)


# ---- per-subpath MIS state (O(D) per subpath, then O(1) per technique at its join)
def mis_partials(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    _, N, _, dt = _dims(scene, cfg)
    delta_light = None if st.emission is None else st.emission.delta
    light_mnee = None
    if _mnee_on(scene, cfg) and st.lends is not None:
        light_mnee = mnee.light_factors(scene, cfg, st.lends, st.emission)
    parts = mis_form(cfg).subpaths(cfg, st.lends, st.cends, delta_light,
                                   path.log_n_light_tracing(cfg, N, dt), st.mis_etas,
                                   light_mnee=light_mnee)
    return dataclasses.replace(st, parts=parts)


# ---- [s = 0] emitter hits of the camera subpaths (ppm: in its gather)
def emitter_hits(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    share = st.glint_roots.share if st.glint_roots is not None else None
    return _add(st, connect.emitter_hits(scene, cfg, st.cends, st.cverts, st.mis_etas, st.parts,
                                         share, _mnee_on(scene, cfg)))


# ---- manifold next-event estimation: from camera vertices under the water through the
#      water surface to a light (`_mnee`)
def _mnee_on(scene: Scene, cfg: RenderConfig) -> bool:
    return cfg.manifold_nee and mnee.applies(scene)


def manifold_next_event(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    if not mnee.applies(scene):  # no water, a dispersive one, or no light with a point
        return st
    key = jax.random.fold_in(jax.random.fold_in(st.key, mnee.STREAM), st.chunk)
    val = mnee.manifold_nee(scene, cfg, st.cends, st.parts, st.mis_etas, key)
    return _add(st, {Technique("manifold", s, t): v for (s, t), v in val.items()})


# ---- glints: a light point seen in the water surface, per camera path (`_glints`)
def _glints_on(scene: Scene, cfg: RenderConfig) -> bool:
    return cfg.glints and glints.applies(scene)


def _glint_key(st: PassState):
    return jax.random.fold_in(jax.random.fold_in(st.key, glints.STREAM), st.chunk)


def glint_roots(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    """F_pixel of the glints' light points and of the emitter hits that take a share of
    them, in one search (`_glints.search`): one copy of the solves in the pass."""
    if not _glints_on(scene, cfg):
        return st
    return dataclasses.replace(st, glint_roots=glints.search(
        scene, _path_pixels(scene, cfg, st), _glint_key(st), st.cends, st.cverts))


def glint_connections(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    if not glints.applies(scene):  # no water, or no light a glint can show
        return st
    val, bad = glints.glints(scene, cfg, _path_pixels(scene, cfg, st), _glint_key(st),
                             found=st.glint_roots)
    st = _add(st, {Technique("glint", 1, 1): val})
    return dataclasses.replace(st, bad=st.bad + bad)


# ---- vertex connection: [s = 1] next-event estimation at camera vertices, [t = 1] light
#      tracing (light vertices splatted onto the film through the pinhole), [s, t >= 2]
#      connections of camera and light vertices, as one work queue (`_connect`)
def _connection_inputs(scene: Scene, cfg: RenderConfig, st: PassState):
    _, N, D, dt = _dims(scene, cfg)
    fams = connect.families(cfg)
    u_nee = cam_o = None
    if connect.NEE in fams:
        u_nee = Uniforms.draw(st.keys[2], (D - 1, N, 3), dt)  # hashed where used
    if connect.LT in fams:
        o, _ = camera.generate_ray(scene.camera, jnp.int32(0), jnp.zeros((), dt),
                                   jnp.zeros((), dt))
        cam_o = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,)), o)
    return (scene, cfg, st.lends, st.cends, st.emission, u_nee, cam_o, st.mis_etas, st.parts,
            fams)


def vertex_connection(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    """One image per technique."""
    return _add(st, connect.vertex_connection(*_connection_inputs(scene, cfg, st)))


def vertex_connection_summed(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    """(image only) Summed per camera path and per pixel."""
    out = connect.vertex_connection(*_connection_inputs(scene, cfg, st), summed=True)
    if out is None:
        return st
    cam, splat, bad = out
    if connect.NEE in connect.families(cfg) or connect.CONN in connect.families(cfg):
        st = _add(st, {Technique("sum", 1, 0): cam})
    if splat is not None:
        P = splat.shape[0]
        st = _add(st, {Technique("sum", 0, 1): (jnp.arange(P, dtype=jnp.int32), splat)})
    return dataclasses.replace(st, bad=st.bad + bad)


# ---- merging: hash grid over the light vertices, gather at camera vertices
def photon_gather(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    """ppm: at the first non-delta camera vertex."""
    img, merged = merge.photon_gather(scene, cfg, st.cends, st.cverts, st.lends, st.radius)
    st = _add(st, {Technique("gather", 0, 0): img})
    return dataclasses.replace(st, merged=merged)


def vertex_merging(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    """bpm, vcm: at every camera vertex."""
    vm, merged = merge.vertex_merging(scene, cfg, st.cends, st.lends, st.emission,
                                              st.radius, st.parts, st.merge_lengths)
    if st.merge_lengths:  # photon y_{i+1} (s = i + 2 light vertices) at z_{j+1} (t = j + 2)
        st = _add(st, {Technique("merge", i + 2, j + 2): vm[j, :, i]
                       for j in range(vm.shape[0]) for i in range(vm.shape[2])
                       if i + j + 2 <= cfg.max_depth})
    else:
        st = _add(st, {Technique("merge", 0, j + 2): vm[j]  # merging at camera vertex z_{j+1}
                       for j in range(vm.shape[0])})
    return dataclasses.replace(st, merged=merged)


def _merge_stats(st: PassState):
    """PassStats' merging fields (overflow, candidates, photon overflow, photons,
    imprecise grid)."""
    m = st.merged
    return m.overflow, m.need, m.photon_overflow, m.photons, m.imprecise


# ---- film: every technique's image, and the pass's counts
def film(scene: Scene, cfg: RenderConfig, st: PassState) -> PassState:
    cam = scene.camera
    H, W, C = cam.height, cam.width, scene.channels
    P, _, _, dt = _dims(scene, cfg)
    images = []
    for val in st.values:
        if isinstance(val, tuple):  # light-tracing splat (pixel, value): each of the N
            pix, v = val                 # light paths carries 1/N already, whatever spp is
            img = jnp.zeros((P, C), dt).at[pix].add(v).reshape(H, W, C)
        else:
            img = val.reshape(cfg.spp, H, W, C).mean(axis=0)
        images.append(img)
    zero = jnp.zeros((), jnp.int32)
    camera_vertices = (jnp.sum(st.cverts.alive) if st.cverts is not None
                       else zero if st.n_cverts is None else st.n_cverts)
    light_vertices = zero if st.lverts is None else jnp.sum(st.lverts.alive)
    stats = PassStats(camera_vertices.astype(jnp.int32), light_vertices.astype(jnp.int32),
                      *_merge_stats(st))
    return dataclasses.replace(st, images=TechniqueImages(st.labels, jnp.stack(images)),
                               stats=stats)


def pass_stages(cfg: RenderConfig, image_only: bool = False) -> list[tuple[str, Stage]]:
    """The named stages of `cfg`'s pass, in the order they run: the one place that chooses
    a pass's route. The techniques' order is the film's (and `integrate`'s summation)
    order, so ppm's gather comes before the light-side techniques and bpm / vcm's merging
    after them. `image_only`: the pass wants only its image (`integrate`), not one image
    per technique: the connections come summed per path, and PT evaluates its techniques
    inside the camera trace (`_inline`: one stage for the subpaths, emitter hits and
    next-event estimation, no records)."""
    tech = cfg.techniques
    D = cfg.max_depth
    cam, light = tech.camera_paths, tech.light_paths
    stages: list[tuple[str, Stage]] = [("setup", setup)]
    if image_only and inline.enabled(cfg):
        return stages + [("camera rays", camera_rays),
                         ("subpaths, emitter hits, next-event estimation",
                          camera_paths_inline), ("film", film)]
    if cam:
        stages.append(("camera rays", camera_rays))
    if light:
        stages.append(("light emission", light_emission))
    stages.append(("subpaths", subpaths))
    if tech.weighted:
        stages.append(("mis partials", mis_partials))
    if cam and tech.emitter_hits and cfg.glints:
        stages.append(("glint roots", glint_roots))
    if cam and tech.emitter_hits and tech.merging != "first":
        stages.append(("emitter hits", emitter_hits))
    if cam and tech.emitter_hits and cfg.glints:
        stages.append(("glints", glint_connections))
    if light and tech.merging == "first":
        stages.append(("merging", photon_gather))
    if connect.families(cfg):
        stages.append(("vertex connection",
                       vertex_connection_summed if image_only else vertex_connection))
    if cam and D >= 3 and cfg.manifold_nee:
        stages.append(("manifold next-event estimation", manifold_next_event))
    if light and tech.merging == "all" and D >= 2:
        stages.append(("merging", vertex_merging))
    stages.append(("film", film))
    return stages


def technique_images(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0,
                     merge_lengths: bool = False) -> tuple[TechniqueImages, PassStats]:
    """Every technique's weighted image of one pass (`Technique` labels), and its stats.
    `pass_index` drives the merging radius schedule. `merge_lengths` (static): bpm / vcm's
    merges split by path length as well (label ("merge", s, t): photon y_{s-1} merged at
    z_{t-1}, a path of s + t - 2 segments) instead of one image per camera vertex (s = 0);
    the gather's sums are then max_depth - 1 times as wide."""
    if cfg.tuning.chunks != 1:
        raise ValueError(f"config.tuning.chunks: technique images need one chunk, got "
                         f"{cfg.tuning.chunks}")
    check_chunks(scene, cfg)
    st = PassState(key=key, pass_index=pass_index, merge_lengths=merge_lengths)
    for _, stage in pass_stages(cfg):
        st = stage(scene, cfg, st)
    return st.images, st.stats


def integrate(scene: Scene, key: PRNGKeyArray, cfg: RenderConfig, pass_index=0
              ) -> tuple[Float[Array, "H W C"], Int[Array, ""], PassStats]:
    """The pass's image (the sum of its technique images, non-finite contributions zeroed),
    the number of non-finite contributions, and its stats. With `cfg.tuning.chunks` > 1 the
    chunks run one after the other in a `lax.scan` (keys `fold_in(key, chunk)`), each
    adding its techniques straight into the image (`_chunk_film`), so no [techniques, H, W]
    stack or whole-pass subpath record is ever held."""
    check_chunks(scene, cfg)
    if cfg.tuning.chunks > 1:
        return _integrate_chunks(scene, key, cfg, pass_index)
    st = PassState(key=key, pass_index=pass_index)
    for name, stage in pass_stages(cfg, image_only=True):
        if name != "film":  # the techniques go straight into one image, not one each
            st = stage(scene, cfg, st)
    img, bad, stats = _chunk_film(scene, cfg, st)
    cam = scene.camera
    return img.reshape(cam.height, cam.width, scene.channels), bad, stats


def _chunk_film(scene: Scene, cfg: RenderConfig, st: PassState):
    """A chunk's techniques added into one [P, C] image (non-finite values zeroed and
    counted): camera-path values at their pixels (1/spp), light-tracing splats where they
    land (each carries 1/N of the pass already).

    Written for the compiler: the camera values are one elementwise chain (their sum and
    a per-element count of non-finite values; one reduction at the end), and the splats
    one concatenated scatter, rather than a reduction per technique, which the CPU
    backend would run as separate kernels for each technique."""
    P, N, _, dt = _dims(scene, cfg)
    C = scene.channels
    cams = [v for v in st.values if not isinstance(v, tuple)]
    pix = [v[0].reshape(-1) for v in st.values if isinstance(v, tuple)]
    spl = [v[1].reshape(-1, C) for v in st.values if isinstance(v, tuple)]
    if cams:  # stacked first, so each value is computed once (else the two elementwise
        # chains below, sum and count, would each fuse in every technique's producer)
        vals = jnp.stack(cams)
        bad = jnp.sum(~jnp.isfinite(vals), dtype=jnp.int32)
        cam_sum = jnp.zeros((N, C), dt)
        for i in range(len(cams)):  # in technique order (elementwise: not a reduction
            v = vals[i]             # over the stack's first axis, a kernel of its own)
            cam_sum = cam_sum + jnp.where(jnp.isfinite(v), v, 0.0)
    else:
        cam_sum, bad = jnp.zeros((N, C), dt), jnp.zeros((), jnp.int32)
    cam_sum = cam_sum / cfg.spp
    if cfg.tuning.chunks == 1:  # path n is pixel n % P: a reshape, no scatter
        img = cam_sum.reshape(cfg.spp, P, C).sum(axis=0)
    else:
        img = jnp.zeros((P, C), dt).at[_path_pixels(scene, cfg, st)].add(cam_sum)
    if pix:
        v = jnp.concatenate(spl)
        finite = jnp.isfinite(v)
        bad = bad + jnp.sum(~finite, dtype=jnp.int32)
        img = img.at[jnp.concatenate(pix)].add(jnp.where(finite, v, 0.0))
    bad = bad + st.bad  # the summed families' non-finite values (`_queue.masked_map`)
    zero = jnp.zeros((), jnp.int32)
    cv = (jnp.sum(st.cverts.alive).astype(jnp.int32) if st.cverts is not None
          else zero if st.n_cverts is None else st.n_cverts)
    lv = zero if st.lverts is None else jnp.sum(st.lverts.alive).astype(jnp.int32)
    return img, bad, PassStats(cv, lv, *_merge_stats(st))


def _count_add(a, b):
    """a + b of two non-negative int32 counts, saturating at 2^31 - 1 (the counts of a pass
    of many chunks may outgrow int32; its indices do not, `check_chunks`)."""
    return a + jnp.minimum(b, jnp.iinfo(jnp.int32).max - a)


def _integrate_chunks(scene, key, cfg, pass_index):
    cam = scene.camera
    H, W, C = cam.height, cam.width, scene.channels
    stages = [f for name, f in pass_stages(cfg, image_only=True) if name != "film"]

    def body(carry, c):
        img, bad, stats = carry
        st = PassState(key=jax.random.fold_in(key, c), pass_index=pass_index, chunk=c)
        for stage in stages:
            st = stage(scene, cfg, st)
        i2, b2, s2 = _chunk_film(scene, cfg, st)
        stats = PassStats(_count_add(stats.camera_vertices, s2.camera_vertices),
                          _count_add(stats.light_vertices, s2.light_vertices),
                          stats.merge_overflow | s2.merge_overflow,
                          jnp.maximum(stats.merge_candidates, s2.merge_candidates),
                          stats.photon_overflow | s2.photon_overflow,
                          jnp.maximum(stats.merge_photons, s2.merge_photons),
                          stats.merge_imprecise | s2.merge_imprecise)
        return (img + i2, _count_add(bad, b2), stats), None

    zero = jnp.zeros((), jnp.int32)
    init = (jnp.zeros((H * W, C), cam.origin.dtype), zero,
            PassStats(zero, zero, jnp.zeros((), bool), zero, jnp.zeros((), bool), zero,
                      jnp.zeros((), bool)))
    (img, bad, stats), _ = jax.lax.scan(body, init, jnp.arange(cfg.tuning.chunks, dtype=jnp.int32))
    return img.reshape(H, W, C), bad, stats


# ---- profiling: each stage jitted and timed on its own
@functools.partial(jax.jit, static_argnums=2)
def _whole_pass(scene, key, cfg, pass_index):
    return integrate(scene, key, cfg, pass_index)


def _with_room(scene: Scene, cfg: RenderConfig, keys) -> RenderConfig:
    """`cfg` with a merge capacity that none of the passes `keys` overflows (the host
    re-run rule of `_render.with_retry`), each pass run (and compiled) once."""
    while True:
        stats = [_whole_pass(scene, k, cfg, i)[2] for i, k in enumerate(keys)]
        if not any(bool(s.merge_overflow) for s in stats):
            return cfg
        cfg = merge.more_room(cfg, max(int(s.merge_candidates) for s in stats),
                              any(bool(s.photon_overflow) for s in stats),
                              max(int(s.merge_photons) for s in stats))


def _stage_program(stage: Stage, cfg: RenderConfig):
    """`stage` jitted on its own, returning only the arrays it makes: the state's other
    leaves are handed on from its input on the host (a jitted program copies the inputs it
    returns, which would charge every stage for the whole state)."""
    where: dict = {}

    def fresh(scene, st):
        ins = {id(x): j for j, x in enumerate(jax.tree.leaves(st))}
        leaves, where["tree"] = jax.tree.flatten(stage(scene, cfg, st))
        where["src"] = [ins.get(id(x)) for x in leaves]
        return [x for x in leaves if id(x) not in ins]

    jitted = jax.jit(fresh)

    def run(scene, st):
        new = iter(jitted(scene, st))
        old = jax.tree.leaves(st)
        return jax.tree.unflatten(where["tree"], [next(new) if j is None else old[j]
                                                  for j in where["src"]])

    return run


def profile_stages(scene: Scene, cfg: RenderConfig, passes: int = 3, seed: int = 0
                   ) -> dict[str, float]:
    """Time each stage of a pass on its own: median wall seconds per stage.

    Stages of `cfg`'s pass (`pass_stages` names, in order, plus "whole pass": the usual
    single-jit pass), over `passes` passes with keys `pass_key(seed, i)`. Each stage is
    jitted on its own, its inputs computed by the earlier stages and waited for before its
    clock starts; every program is compiled and run once (pass 0) before timing. The merge
    capacity is raised first if a pass would overflow it, as the host driver does.
    Separate programs cannot fuse across stages, so the stages' sum is usually somewhat
    more than the whole pass."""
    if passes < 1:
        raise ValueError(f"passes: must be >= 1, got {passes}")
    keys = [jax.random.fold_in(jax.random.key(seed), i) for i in range(passes)]  # pass_key
    cfg = _with_room(scene, cfg, keys)
    stages = [(name, _stage_program(fn, cfg)) for name, fn in pass_stages(cfg, image_only=True)]

    def one_pass(i, times):
        st = jax.block_until_ready(PassState(key=keys[i], pass_index=i))
        for name, fn in stages:
            t0 = time.perf_counter()
            st = jax.block_until_ready(fn(scene, st))
            if times is not None:
                times.setdefault(name, []).append(time.perf_counter() - t0)

    one_pass(0, None)  # compile every stage
    times: dict[str, list[float]] = {}
    for i in range(passes):
        one_pass(i, times)
        t0 = time.perf_counter()
        jax.block_until_ready(_whole_pass(scene, keys[i], cfg, i))
        times.setdefault("whole pass", []).append(time.perf_counter() - t0)
    return {name: float(np.median(t)) for name, t in times.items()}
