"""Photons where the camera looks: a pilot of camera paths before the render gives the
aimed lights' footprint map and a merge radius from the pixel footprint.

`[[lights]] aim = P` (`_lights.aimed_pdf`) sends a fraction P of a sun's or sky's photons
through the water's footprint, uniformly by default. In a large pool seen through a narrow
view most of the footprint casts no caustic the camera sees. `aim_at_view` traces one
pilot pass of camera subpaths (its own key, before any measured pass, so the map is
independent of every pass's samples and each pass stays unbiased) and bins the first
non-delta vertex of each path that lies under the water (the floor or walls seen through
the surface, or a medium vertex) by its (x, z). The surface above such a point casts its
caustic (`_casters`): for a sun, the point its refracted ray (flat surface) comes down
from, widened by what the waves' slopes can tilt it; for the sky, the vertical projection
widened by depth x tan(critical angle); both by a pixel's footprint and the first pass's merge
radius (a gather point reaches photons that far beyond what it sees). `Lights.aim_rect`
becomes the casters' widened box (clipped to the footprint) and `Lights.aim_map` the
[G, G] cells of it within reach of a caster (plus one cell); the disk part of the mixture
(1 - P) still covers every line, so light that starts elsewhere (reflected off a wall,
multiple bounces, wave slopes beyond the widening) is still emitted and the estimators
stay unbiased.

The merge radius of the first pass follows the pixel footprint at the same vertices:
r_1 = `radius_pixels` x the median over paths of (distance from the pinhole along the
path) x (one pixel's angle, 2 tan(fov / 2) / H), returned as the fraction of the scene's
view radius (`Scene.view_radius`) that `RenderConfig.radius` takes (the progressive
schedule is unchanged), but not below what the hash grid resolves in the scene's float
dtype at the scene's extent for `horizon` (10^4) passes of the schedule
(`_merge.precise_radius`: a 120 m pool in float32 takes 4.7 cm instead of its 1.8 cm
footprint; a float64 scene takes the footprint).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _integrator as integ
from . import _merge as merge
from . import _subpath as subpath
from ._config import MAX_RADIUS, RenderConfig
from ._scene import LIGHT_SKY, LIGHT_SUN, Scene

DEFAULT_GRID = 64
DEFAULT_RADIUS_PIXELS = 1.0
DEFAULT_HORIZON = 10_000  # passes the footprint radius must stay resolvable for


class ViewGuide(NamedTuple):
    """What the pilot pass of `view_guide` found: the aimed lights' map and a merge radius.

    With the figures they come from: the median pixel footprint and the path counts."""

    aim_map: np.ndarray  # [G, G] weights of the rectangle's cells (rows z, columns x)
    aim_rect: np.ndarray  # [4] x0, x1, z0, z1 of the water's plane the map covers
    radius: float  # first-pass merge radius, as a fraction of the view radius
    footprint: float  # median pixel footprint (m) at the first non-delta camera vertex
    under_water: int  # pilot paths whose first non-delta vertex lies under the footprint
    paths: int  # pilot paths


@functools.partial(jax.jit, static_argnums=(2,))
def _pilot(scene: Scene, key, cfg: RenderConfig):
    """First non-delta vertex of each camera subpath of one pass: (position [N, 3], path
    length from the pinhole [N], found [N])."""
    st = integ.PassState(key=key, pass_index=0)
    st = integ.setup(scene, cfg, st)
    st = integ.camera_rays(scene, cfg, st)
    v, _ = subpath.trace(scene, cfg, True, st.cam_start, st.cam_u, cfg.max_depth)
    ok = v.alive & ~v.delta & ~v.escaped & (v.kind != subpath.KIND_NONE)  # [D, N]
    first = jnp.argmax(ok, axis=0)
    found = jnp.any(ok, axis=0)
    lane = jnp.arange(ok.shape[1])
    p = jnp.stack([c[first, lane] for c in v.p], -1)
    # path length: the segments up to the first non-delta vertex
    o = st.origins
    pts = jnp.stack(list(v.p), -1)  # [D, N, 3]
    prev = jnp.concatenate([jnp.stack(list(o), -1)[None], pts[:-1]], 0)
    seg = jnp.linalg.norm(pts - prev, axis=-1)
    seg = jnp.where(jnp.arange(ok.shape[0])[:, None] <= first[None], seg, 0.0)
    return p, jnp.sum(seg, axis=0), found


def _casters(scene: Scene, q: np.ndarray, level: float):
    """For points q [M, 3] under the water: per aimed light, (caster points on the plane
    [M, 2] (x, z), reach (m) to widen them by). A sun's refracted ray (flat surface)
    reaches q from the point q - (level - q_y) t_h / |t_y| of the plane, t its refracted
    direction: the exact caster, widened by what the waves' slopes (bound sum |A| |k|) can
    tilt it; the sky's light arrives from every refracted direction up to the critical
    angle: the vertical projection, widened by (level - floor) tan(theta_c)."""
    ior = float(scene.water.ior)
    amp = np.abs(np.asarray(scene.water.amp, np.float64))
    k = np.hypot(np.asarray(scene.water.kx, np.float64), np.asarray(scene.water.kz, np.float64))
    slope = float((amp * k).sum())
    depth = level - float(scene.water.floor)
    out = []
    for i, kind in enumerate(scene.lights.kind):
        if i >= len(scene.lights.aim) or scene.lights.aim[i] <= 0:
            continue
        if kind == LIGHT_SUN:
            d = np.asarray(scene.lights.direction[i], np.float64)
            s_i = math.sqrt(max(0.0, 1.0 - d[1] ** 2))
            s_t = s_i / ior
            c_t = math.sqrt(1.0 - s_t * s_t)
            h = d[[0, 2]] / max(s_i, 1e-12) * s_t  # horizontal part of the refracted ray
            dz = (level - q[:, 1])[:, None]
            out.append((q[:, [0, 2]] - dz * h / c_t, depth * (slope + 0.05 * s_t / c_t)))
        elif kind == LIGHT_SKY:
            s_c = 1.0 / ior
            out.append((q[:, [0, 2]], depth * s_c / math.sqrt(1.0 - s_c * s_c)))
    return out


def view_guide(scene: Scene, key=None, *, spp: int = 4, max_depth: int = 8,
               grid: int = DEFAULT_GRID, radius_pixels: float = DEFAULT_RADIUS_PIXELS,
               alpha: float = RenderConfig.alpha, horizon: int = DEFAULT_HORIZON) -> ViewGuide:
    """Trace a pilot pass of camera paths: the aimed lights' footprint map and a merge radius.

    The pilot's camera subpaths (its own key, so the map is independent of every render
    pass's samples) find the first non-delta vertex of each path that lies under the
    water; the surface points that cast caustics there, widened by what the waves' slopes,
    a pixel's footprint and the merge radius reach, give the map's rectangle and its
    cells. The radius follows the median pixel footprint at those vertices
    (`radius_pixels` pixels), as a fraction of the scene's view radius, and is at
    least what the hash grid resolves in the scene's float dtype for `horizon` passes of
    the schedule with `alpha`. `key`: the pilot's key (default: a fixed key no pass
    uses)."""
    if not scene.water.enabled:
        raise ValueError("aim_at_view: the scene has no [water] footprint to aim at")
    if key is None:
        key = jax.random.fold_in(jax.random.key(0), 0x61696D)  # "aim"
    cfg = RenderConfig(algorithm="pt", max_depth=max_depth, spp=spp)
    p, dist, found = (np.asarray(a) for a in _pilot(scene, key, cfg))
    p = p.astype(np.float64)
    fx0, fx1, fz0, fz1 = (float(a) for a in np.asarray(scene.water.footprint))
    level = float(scene.water.level) + float(np.abs(np.asarray(scene.water.amp)).sum())
    under = (found & (p[:, 1] < level) & (p[:, 0] >= fx0) & (p[:, 0] < fx1)
             & (p[:, 2] >= fz0) & (p[:, 2] < fz1))
    G = int(grid)
    cam = scene.camera
    pixel = 2.0 * float(cam.tan_half_fov) / cam.height
    fp = float(np.median(dist[found])) * pixel if found.any() else float("nan")
    rb = float(scene.view_radius)  # the reference length of `RenderConfig.radius`
    r = radius_pixels * fp / rb if math.isfinite(fp) else RenderConfig.radius
    # not below what the hash grid resolves at the scene's extent for `horizon` passes of
    # the progressive schedule (`_merge.pass_radius`'s floor; the grid's radius shrinks as
    # i^((alpha - 1) / 3)): in float32 a 120 m pool resolves >= 2.2 cm
    r_min, _ = merge.precise_radius(scene)
    floor = r_min * 1.01 * horizon ** ((1.0 - alpha) / 3.0) / rb
    r = min(max(r, floor, 1e-6), MAX_RADIUS)
    if not under.any():
        rect, aim_map = (fx0, fx1, fz0, fz1), np.ones((G, G))
    else:
        # the casters' box on the plane, widened by their reach, clipped to the footprint;
        # the map over it: the cells within reach (plus one) of a caster
        cast = _casters(scene, p[under], level)
        # a pixel's footprint there, plus the first pass's merge radius: gather points
        # reach photons that far beyond what they see
        pix = pixel * float(np.median(dist[under])) + r * rb
        x0 = max(fx0, min(c[:, 0].min() - w - pix for c, w in cast))
        x1 = min(fx1, max(c[:, 0].max() + w + pix for c, w in cast))
        z0 = max(fz0, min(c[:, 1].min() - w - pix for c, w in cast))
        z1 = min(fz1, max(c[:, 1].max() + w + pix for c, w in cast))
        x1, z1 = max(x1, x0 + 1e-3 * (fx1 - fx0)), max(z1, z0 + 1e-3 * (fz1 - fz0))
        rect = (x0, x1, z0, z1)
        aim_map = np.zeros((G, G))
        for c, w in cast:
            i = np.clip(((c[:, 1] - z0) / (z1 - z0) * G).astype(int), 0, G - 1)
            j = np.clip(((c[:, 0] - x0) / (x1 - x0) * G).astype(int), 0, G - 1)
            seen = np.zeros((G, G), bool)
            seen[i, j] = True
            rx = min(G, int(math.ceil((w + pix) / ((x1 - x0) / G))) + 1)
            rz = min(G, int(math.ceil((w + pix) / ((z1 - z0) / G))) + 1)
            pad = np.pad(seen, ((rz, rz), (rx, rx)))
            for di in range(-rz, rz + 1):  # aimed: a caster lies within reach
                for dj in range(-rx, rx + 1):
                    aim_map = np.maximum(aim_map,
                                         pad[rz + di:rz + di + G, rx + dj:rx + dj + G])
    return ViewGuide(aim_map, np.asarray(rect), r, fp, int(under.sum()), int(p.shape[0]))


def aim_at_view(scene: Scene, config: RenderConfig | None = None, key=None, **kw
                ) -> tuple[Scene, RenderConfig, ViewGuide]:
    """Aim a scene's photons where the camera looks, and size the merge radius to match.

    Returns (`scene` with its aimed lights' map from `view_guide`, `config` (default
    RenderConfig()) with the footprint radius, the `ViewGuide`). The scene must have an
    aimed light (`[[lights]] aim > 0`)."""
    if not any(a > 0 for a in scene.lights.aim):
        raise ValueError("aim_at_view: the scene has no aimed light (set [[lights]] aim)")
    config = config or RenderConfig()
    g = view_guide(scene, key, alpha=config.alpha, **kw)
    dt = scene.lights.aim_map.dtype
    scene = eqx.tree_at(lambda s: (s.lights.aim_map, s.lights.aim_rect), scene,
                        (jnp.asarray(g.aim_map, dt), jnp.asarray(g.aim_rect, dt)))
    config = dataclasses.replace(config, radius=g.radius)
    return scene, config, g
