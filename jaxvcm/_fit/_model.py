"""The forward model of a fit: regions of rendered images, their mean colours, residuals.

A *region* is a pixel rectangle `rect = [x0, y0, x1, y1]` (half-open; x = column, y = row,
row 0 at the top of the image, as in the PNG/EXR the renderer writes) of one scene's camera
image, with a target colour and optional 1-sigma uncertainties.

`region_colours(...)` maps parameters theta to the mean colour of every region: every scene
is rendered with `passes` passes with the fixed keys `pass_key(seed, i)`, i < passes
(common random numbers: the same keys at every iterate, so the objective is a deterministic
function of theta; in spectral mode the keys fix the hero wavelengths too), the passes are
averaged and each region's pixels are averaged. Scenes with the same static structure
(shapes, kinds, image size, n_wavelengths) are stacked and rendered one after another by
one `lax.map`, so they share one compiled program. The same function serves RGB `Scene`s (theta = ln sigma_a,
ln sigma_s; linear sRGB film) and `SpectralScene`s (theta = WaterModel leaves; XYZ film):
only the map (theta, scene) -> rendered pass differs (`region_colours_fn`,
`spectral_region_colours_fn`).

`residuals(...)` is the fit's residual function: (colour in the target's space - target) /
uncertainty, per region and channel. Default uncertainties: 1 Delta E*ab unit in "lab",
1% of the target (plus 1e-4) in "srgb"/"xyz".
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .._config import RenderConfig
from .._integrator import max_chunk_paths
from .._memory import device_budget, gib
from .._render import pass_key, render_pass
from .._scene import Scene
from .._spectral import SpectralScene, render_pass_spectral
from ._colour import target_problem, to_space, xyz_to_space


@dataclasses.dataclass(frozen=True)
class Region:
    """One target: the mean colour of pixels [y0:y1, x0:x1] of scene `scene`'s image."""

    name: str
    scene: int | str  # index into the scenes, or a key of a scene dict
    rect: tuple[int, int, int, int]  # x0, y0, x1, y1 (half-open, row 0 at the top)
    target: tuple[float, float, float]  # in the fit's colour space
    uncertainty: tuple[float, float, float] | None = None  # 1 sigma, same space


# ------------------------------------------------------------------ scenes and regions
def _named(items, cls) -> tuple[list, list[str]]:
    """One item of type `cls`, a list, or a name -> item dict: (items, names)."""
    if isinstance(items, cls):
        items = [items]
    if isinstance(items, dict):
        names = list(items)
        return [items[k] for k in names], names
    items = list(items)
    return items, [str(i) for i in range(len(items))]


def _resolve(scenes, regions, space: str) -> tuple[list[Scene], list[Region], list[str]]:
    """Validate the regions against the scenes and their targets in `space`
    (`target_problem`) -> (scenes, regions with scene indices and integer rects, scene
    names)."""
    scenes, names = _named(scenes, Scene)
    if not scenes:
        raise ValueError("fit: no scenes")
    if not regions:
        raise ValueError("fit: no regions")
    C = scenes[0].channels
    out = []
    seen = set()
    for r in regions:
        if r.name in seen:
            raise ValueError(f"regions.{r.name}: duplicate region name")
        seen.add(r.name)
        if isinstance(r.scene, str) and not isinstance(r.scene, bool):
            if r.scene not in names:
                raise ValueError(f"regions.{r.name}.scene: unknown scene {r.scene!r} "
                                 f"(one of {', '.join(names)})")
            si = names.index(r.scene)
        else:
            si = int(r.scene)
            if not 0 <= si < len(scenes):
                raise ValueError(f"regions.{r.name}.scene: index {si} out of range")
        s = scenes[si]
        if not s.water.enabled:
            raise ValueError(f"regions.{r.name}.scene: scene {names[si]!r} has no water")
        if s.channels != C:
            raise ValueError(f"regions.{r.name}.scene: scenes differ in channel count")
        x0, y0, x1, y1 = (int(v) for v in r.rect)
        W, H = s.camera.width, s.camera.height
        if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
            raise ValueError(f"regions.{r.name}.rect: {list(r.rect)} is empty or outside the "
                             f"{W}x{H} image (need 0 <= x0 < x1 <= {W}, 0 <= y0 < y1 <= {H})")
        if len(r.target) != 3:
            raise ValueError(f"regions.{r.name}.target: expected 3 numbers")
        why = target_problem(r.target, space)
        if why:
            raise ValueError(f"regions.{r.name}.target: {why}")
        if r.uncertainty is not None and (len(r.uncertainty) != 3 or
                                          not all(u > 0 for u in r.uncertainty)):
            raise ValueError(f"regions.{r.name}.uncertainty: expected 3 numbers > 0")
        out.append(dataclasses.replace(r, scene=si, rect=(x0, y0, x1, y1)))
    return scenes, out, names


def size_checks(scenes: Sequence[Scene], config: RenderConfig):
    """A fit's image size, checked before and after its solver compiles: each pass of a fit
    runs in one chunk, so every scene's paths must fit int32 indices
    (`_integrator.max_chunk_paths`, refused here, before any work); the returned callable
    refuses, once XLA has compiled the solver (`levenberg_marquardt`'s `memory`), a program
    larger than the device's memory budget (`_memory.device_budget`: the CPU's from the
    host's available memory). Both name the fit config's `render.width, render.height`."""
    big = max(scenes, key=lambda sc: sc.camera.width * sc.camera.height)
    cam = big.camera
    size = f"{cam.width} x {cam.height}"
    most = max_chunk_paths(config)
    if cam.width * cam.height * config.spp > most:
        raise ValueError(f"render.width, render.height: a fit renders each pass in one "
                         f"chunk, and {size} x {config.spp} spp paths are more than the "
                         f"{most} whose indices fit int32 ({config.algorithm} at depth "
                         f"{config.max_depth}); fit a smaller image")

    def memory(nbytes: int) -> None:
        budget = device_budget(jax.devices()[0])
        if budget is not None and nbytes > budget:
            raise ValueError(f"render.width, render.height: the fit's compiled solver at "
                             f"{size} needs about {gib(nbytes)}, more than the "
                             f"{gib(budget)} there is for it; fit a smaller image")

    return memory


def default_uncertainty(target, space: str) -> np.ndarray:
    t = np.asarray(target, np.float64)
    if space == "lab":
        return np.ones(3)
    return 0.01 * np.abs(t) + 1e-4


# ------------------------------------------------------------------ region colours
def _groups(scenes: Sequence, anonymous: Callable) -> list[tuple[list[int], object]]:
    """Scenes with equal static structure -> (indices, stacked scene with a leading axis).
    `anonymous(scene)` clears the (static) name, which must not split groups."""
    groups: list[tuple[list[int], list]] = []
    for i, s in enumerate(scenes):
        s = anonymous(s)
        st = jax.tree.structure(s)
        shapes = [(a.shape, a.dtype) for a in jax.tree.leaves(s)]
        for idx, members in groups:
            m0 = members[0]
            if jax.tree.structure(m0) == st and shapes == [(a.shape, a.dtype) for a in
                                                          jax.tree.leaves(m0)]:
                idx.append(i)
                members.append(s)
                break
        else:
            groups.append(([i], [s]))
    return [(idx, jax.tree.map(lambda *a: jnp.stack(a), *members)) for idx, members in groups]


def _pass_devices(passes: int, devices) -> int:
    """How many of `devices` the passes are spread over: the largest number that divides
    `passes`."""
    return max(d for d in range(1, len(devices) + 1) if passes % d == 0)


def _mean_over_passes(render_pass_of, ctx, keys, idx, devices):
    """The mean of `render_pass_of(ctx, key, i) -> (image, overflow)` over the passes
    `keys` [P], `idx` [P], and whether any pass overflowed. The passes run one after another
    (`lax.scan`), not under `vmap`: the pass is traced once, unbatched, so its run-time
    branches (the work queues' `lax.cond`s) stay branches. On n > 1 devices each device
    loops over P / n of the passes (`shard_map` over a 1-D mesh; `ctx`, the parameters and
    the scene, replicated) and the sum is a `psum`."""
    P_ = keys.shape[0]
    n = _pass_devices(P_, devices)

    def passes_sum(ctx, key_data, idx):  # -> the images' sum, any overflow (int32)
        keys = jax.random.wrap_key_data(key_data)
        imgs, ovs = jax.lax.scan(lambda c, ki: (c, render_pass_of(ctx, *ki)), None,
                                 (keys, idx))[1]
        return jnp.sum(imgs, axis=0), jnp.any(ovs).astype(jnp.int32)

    key_data = jax.random.key_data(keys)
    if n == 1:
        total, ov = passes_sum(ctx, key_data, idx)
    else:
        def body(ctx, key_data, idx):
            return jax.tree.map(lambda x: jax.lax.psum(x, "passes"),
                                passes_sum(ctx, key_data, idx))

        spec = PartitionSpec("passes")
        total, ov = jax.shard_map(body, mesh=Mesh(np.array(devices[:n]), ("passes",)),
                                  in_specs=(PartitionSpec(), spec, spec),
                                  out_specs=(PartitionSpec(), PartitionSpec()),
                                  check_vma=False)(ctx, key_data, idx)
    return total / P_, ov > 0


def region_colours(scenes: Sequence, regions: Sequence[Region], passes: int, seed: int,
                   anonymous: Callable, params: Callable, render: Callable, devices=None):
    """The forward model shared by both fits -> fn(theta, keys, indices) = (region colours
    [R, C] in the film's space, merge overflow flag): pure, jit- and jacfwd-able.

    params(theta) -> p (once per call); render(scene, p, key, i) -> (image, overflow) of one
    pass of one (unstacked) scene. Default keys: pass_key(seed, i), i < passes; other keys
    [P] with pass indices [P] render other passes with the same program. The passes (and so
    the fit's Jacobian, scenes x regions x keys) are spread over `devices` (default: every
    local device; `_mean_over_passes`); the values do not depend on how many, to float32
    rounding of the mean."""
    devs = jax.local_devices() if devices is None else list(devices)
    groups = _groups(scenes, anonymous)
    keys = jnp.stack([pass_key(seed, i) for i in range(passes)])
    idx = jnp.arange(passes, dtype=jnp.int32)
    where = {}  # scene index -> (group, position)
    for g, (members, _) in enumerate(groups):
        for p, i in enumerate(members):
            where[i] = (g, p)

    def fn(theta, keys=keys, idx=idx):
        p = params(theta)
        images = []
        overflow = jnp.zeros((), bool)
        for _, stacked in groups:
            def passes_of(scene):
                return _mean_over_passes(lambda c, key, i: render(c[0], c[1], key, i),
                                         (scene, p), keys, idx, devs)

            # one scene of the group after another: the pass is traced once, unbatched
            imgs, ov = jax.lax.map(passes_of, stacked)
            images.append(imgs)
            overflow = overflow | jnp.any(ov)
        cols = []
        for r in regions:
            g, q = where[r.scene]
            x0, y0, x1, y1 = r.rect
            cols.append(jnp.mean(images[g][q, y0:y1, x0:x1], axis=(0, 1)))
        return jnp.stack(cols), overflow

    return fn


def _with_water(scene: Scene, sigma_a, sigma_s) -> Scene:
    return eqx.tree_at(lambda s: (s.water.sigma_a, s.water.sigma_s), scene, (sigma_a, sigma_s))


def region_colours_fn(scenes: Sequence[Scene], regions: Sequence[Region], config: RenderConfig,
                      passes: int, seed: int, devices=None):
    """The forward model of an RGB fit: water coefficients -> the regions' mean colours.

    fn(theta, keys, indices): theta [2C] = (ln sigma_a, ln sigma_s) -> (region colours
    [R, C] linear sRGB, merge overflow flag); see `region_colours`."""
    C = scenes[0].channels
    dtype = scenes[0].water.sigma_a.dtype

    def params(theta):
        return jnp.exp(theta[:C]).astype(dtype), jnp.exp(theta[C:]).astype(dtype)

    def render(scene, p, key, i):
        img, diag = render_pass(_with_water(scene, *p), key, config, i)
        return img, diag.merge_overflow

    return region_colours(scenes, regions, passes, seed,
                          lambda s: dataclasses.replace(s, name="fit"), params, render, devices)


def _to_values(theta, names, linear):
    """theta [n] -> parameter values [n]: exp for log-space names, identity for linear."""
    lin = jnp.asarray([n in linear for n in names])
    return jnp.where(lin, theta, jnp.exp(jnp.where(lin, 0.0, theta)))


def spectral_region_colours_fn(spectral: Sequence[SpectralScene], regions: Sequence[Region],
                               names: Sequence[str], config: RenderConfig, passes: int,
                               seed: int, linear: Sequence[str] = (), devices=None):
    """The forward model of a spectral fit: water-model parameters -> the regions' XYZ.

    fn(theta, keys, indices): theta [n] -> (region XYZ [R, 3], merge overflow flag),
    theta_j = ln p_j of the WaterModel leaf `names[j]`, or p_j itself for names in
    `linear`; see `region_colours`."""
    names = list(names)
    linear = tuple(linear)

    def render(sp, vals, key, i):
        dt = sp.scene.bounds.dtype
        water = dataclasses.replace(sp.water,
                                    **{n: vals[j].astype(dt) for j, n in enumerate(names)})
        xyz, diag = render_pass_spectral(dataclasses.replace(sp, water=water), key, config, i)
        return xyz, diag.core.merge_overflow

    def anonymous(sp):
        return dataclasses.replace(sp, scene=dataclasses.replace(sp.scene, name="fit"))

    return region_colours(spectral, regions, passes, seed, anonymous,
                          lambda theta: _to_values(theta, names, linear), render, devices)


# ------------------------------------------------------------------ residuals
def residuals(colours: Callable, regions: Sequence[Region], space: str, film: str,
              embed: Callable, dtype):
    """The residual function of a fit -> (residual_fn(y, args) = (r [R * 3] in the solver's
    dtype, overflow), targets [R, 3], uncertainties [R, 3]).

    r = (colour in `space` - target) / uncertainty with colour = colours(embed(y))[0] in the
    film's space `film` ("srgb" for RGB scenes, "xyz" for spectral ones); `dtype`: the
    renderer's. The solver's dtype is the default float type (optimistix builds its damping
    terms in it: float64 under jax_enable_x64)."""
    pdtype = jnp.result_type(float)
    targets = np.array([r.target for r in regions], np.float64)
    unc = np.array([default_uncertainty(r.target, space) if r.uncertainty is None
                    else r.uncertainty for r in regions], np.float64)
    tgt = jnp.asarray(targets, dtype)
    inv_unc = jnp.asarray(1.0 / unc, dtype)
    convert = (lambda c: to_space(c, space)) if film == "srgb" else \
        (lambda c: xyz_to_space(c, space))

    def residual_fn(y, args):
        c, overflow = colours(embed(y))
        return ((convert(c) - tgt) * inv_unc).reshape(-1).astype(pdtype), overflow

    return residual_fn, targets, unc
