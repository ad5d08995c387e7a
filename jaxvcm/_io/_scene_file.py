"""TOML scene files -> `Scene`, with one-line errors naming file, field and problem.

Schema (metres, y up; "spectrum" = a number or a list of C numbers):

  base = "FILE.toml" | ["A.toml", "B.toml"]        # optional: shared parts (below)
  name = "pool"                                    # optional
  [camera]  position, target, up = [0,1,0], fov (vertical, degrees), width, height
  [materials.NAME]  type = "diffuse" | "mirror", albedo = spectrum
                    type = "glossy", albedo (Lambertian k_d, default 0), glossy (Phong
                                     k_s, default 0.5), exponent (default 90); two-sided
                    type = "glass", ior      (smooth dielectric: inside is where the
                                              shape's normal points away from)
  [[shapes]] type = "rect":   center, normal, size = [w, h], up (tangent hint), material
  [[shapes]] type = "sphere": center, radius, material
  [[shapes]] type = "basin":  min = [x0, floor, z0], max = [x1, top, z1],
                              floor_material, wall_material,
                              wall_tops = [top at x0, at x1, at z0, at z1]   (optional)
             (an open box: floor + 4 inward-facing walls, expanded into 5 rectangles)
             every shape: two_sided = true (default: a diffuse or glossy shape scatters on
             both faces) | false (only on the side its normal faces, black from behind,
             like SmallVCM's and Mitsuba's diffuse; diffuse and glossy materials only)
  [water]   level, waves = [[A, kx, kz, phase], ...], sigma_a, sigma_s (1/m, spectra),
            phase = "isotropic" | "hg" | "water", g (hg), b = 0.835 (water), ior,
            footprint = [xmin, xmax, zmin, zmax], floor   (default: the basin's interior)
  [[lights]] type = "rect":   center, normal (the side it emits to), size, radiance, up
  [[lights]] type = "sphere": center, radius, radiance                (emits both ways)
  [[lights]] type = "sun":    direction (the way light travels), irradiance, aim
  [[lights]] type = "sky":    radiance, aim              (directions with y > 0 only)
             aim = 0 (default) .. < 1: the fraction of the light's photons aimed at the
             water's footprint (the caustic caster) instead of the scene's bounding disk;
             the rest still cover the scene, and every technique's MIS uses the mixture
             pdf (`_lights.aimed_pdf`), so images are unbiased either way (needs [water];
             an aimed sun must shine downwards)
  [[lights]] type = "point":  position, intensity (W/sr)  (isotropic, delta position)
  [[lights]] type = "background": radiance               (every direction; SmallVCM's
                                                          background; at most one of
                                                          sky and background)

Valid ranges (anything outside is a one-line error naming the field; the constants are in
`_toml.py` and `_scene_sections.py`). They keep every derived value finite in float32:

  coordinates (positions, centers, targets, basin min/max, footprint, level, floor,
      wave amplitude)                 |x| <= 1e6 m
  sizes, radii                        1e-6 m .. 1e6 m, and >= 1e-6 x the scene's extent
                                      (smaller shapes are not resolved in float32)
  directions (normal, up, direction)  not all zero; a rect's `up` not parallel to its normal
  camera.fov                          0.01 .. 179 degrees (vertical)
  camera.width, camera.height         1 .. 16384 (also --width / --height)
  albedo (materials and emitters)     0 .. 1 (glossy: albedo + glossy <= 1 per channel)
  exponent (glossy)                   1 .. 1e5
  radiance, irradiance                0 .. 1e15 (> 0 in some channel)
  sigma_a, sigma_s                    0 .. 1e6 1/m
  ior                                 1 .. 3 (1: an index-matched boundary, no refraction)
  wave numbers kx, kz                 |k| <= 1e4 rad/m; phase |p| <= 1e6 rad
  g (hg)                              -0.999 .. 0.999;  b (water phase 1 + b cos^2): 0 .. 10
  any other number                    |x| <= 1e6
Integers of any size and floats beyond float64 (inf, nan) are rejected the same way. The file
must be UTF-8 TOML; keys that are not bare are shown quoted in messages.

Variants share parts through `base`: the files it names (paths relative to this file, each
possibly with its own `base`; at most MAX_BASES in a chain, no cycles) are read first, in
order, and this file is laid over them: tables merge key by key, [[shapes]] and
[[lights]] entries are appended after the bases' ones, any other value replaces the
base's. A base need not be a whole scene (scenes/_base/ holds the Cornell box's parts).
Messages name the file that was loaded and the merged document's field (shapes[i] counts
the bases' shapes first).

The file is read and its values checked in `_toml.py` (`SceneError`, `_Ctx`); each section
is parsed in `_scene_sections.py`, and `scene_from_dict` below puts the parts together.
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from .._scene import (
    LIGHT_BACKGROUND, LIGHT_POINT, LIGHT_RECT, LIGHT_SPHERE, LIGHT_SUN, Camera, Lights, Materials, Rects, Scene, Spheres, Water,
)
from ._scene_sections import (
    _Parts, parse_camera, parse_lights, parse_materials, parse_shapes, parse_water,
)
from ._toml import REL_SIZE, SceneError, _Ctx, read_toml

__all__ = ["SceneError", "load_scene", "read_scene_doc", "scene_from_dict"]


def load_scene(path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
               dtype=jnp.float32) -> Scene:
    """Load and validate a TOML scene file; raises `SceneError` with a one-line message."""
    src = os.fspath(path)
    return scene_from_dict(read_scene_doc(src), src, width=width, height=height, dtype=dtype)


MAX_BASES = 8  # files in one chain of `base`s
_APPENDED = ("shapes", "lights")  # arrays of tables that a file adds to its bases'


def merge_docs(base: dict, over: dict) -> dict:
    """`over` laid over `base`: tables merged key by key, the [[shapes]] / [[lights]]
    arrays appended, any other value replaced."""
    out = dict(base)
    for k, v in over.items():
        b = out.get(k)
        if isinstance(v, dict) and isinstance(b, dict):
            out[k] = merge_docs(b, v)
        elif k in _APPENDED and isinstance(v, list) and isinstance(b, list):
            out[k] = b + v
        else:
            out[k] = v
    return out


def read_scene_doc(src: str, _chain: tuple = ()) -> dict:
    """The TOML document at `src` with its `base` files merged under it (`merge_docs`)."""
    doc = read_toml(src)
    if "base" not in doc:
        return doc
    ctx = _Ctx(src)
    bases = doc.pop("base")
    names = [bases] if isinstance(bases, str) else bases
    if not isinstance(names, list) or not names:
        ctx.fail("base", "expected a file name or a non-empty list of file names")
    chain = _chain + (os.path.realpath(src),)
    merged: dict = {}
    for i, name in enumerate(names):
        f = "base" if isinstance(bases, str) else f"base[{i}]"
        path = os.path.join(os.path.dirname(src), ctx.string(name, f))
        if os.path.realpath(path) in chain:
            ctx.fail(f, f"{name!r} is this file or one of its bases (a cycle)")
        if len(chain) >= MAX_BASES:
            ctx.fail(f, f"more than {MAX_BASES} files in a chain of bases")
        if not os.path.isfile(path):
            ctx.fail(f, f"file not found: {path}")
        merged = merge_docs(merged, read_scene_doc(path, chain))
    return merge_docs(merged, doc)


def scene_from_dict(doc: dict, src: str = "<scene>", *, width=None, height=None,
                    dtype=jnp.float32) -> Scene:
    """Validate a parsed scene document (the format above) and build the `Scene`;
    `width` / `height` override the camera's. Sections are checked in the order below."""
    ctx = _Ctx(src)
    ctx.table(doc, {"name", "camera", "materials", "shapes", "water", "lights"},
              {"camera", "lights"}, "")
    name = ctx.string(doc.get("name", os.path.splitext(os.path.basename(src))[0]), "name")
    # The ranges of `_toml` keep every value below finite; a floating-point exception here
    # is a gap in them, reported as one line rather than as a NumPy warning.
    with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
        try:
            cam = parse_camera(ctx, doc["camera"], width, height)
            parts = _Parts()
            parse_materials(ctx, doc.get("materials", {}), parts)
            parse_shapes(ctx, doc.get("shapes", []), parts)
            parse_lights(ctx, doc["lights"], parts)
            water = parse_water(ctx, doc.get("water"), parts)
            for field, a in parts.l_aim:
                if a > 0 and not water["enabled"]:
                    ctx.fail(field, "aims at the water's footprint: the scene has no [water]")
            bounds = _bounds(cam["pos"], parts, water)
            _check_sizes(ctx, parts, bounds)
            power = _light_power(parts, bounds)
        except FloatingPointError as e:  # pragma: no cover (no known case)
            ctx.fail("scene", f"a derived value is out of range ({e})")
    return _check_finite(ctx, _to_scene(cam, parts, water, bounds, power, name, dtype))


def _check_sizes(ctx: _Ctx, parts: _Parts, bounds: np.ndarray) -> None:
    """Every shape at least REL_SIZE x the scene's extent: smaller ones are not resolved by
    float32 positions at that scale (a 1e-308 m light would have area 0 and no normal)."""
    extent = float(np.linalg.norm(bounds[1] - bounds[0]))
    for field, size in parts.sizes:
        if size < REL_SIZE * extent:
            ctx.fail(field, f"{size:g} m is below {REL_SIZE:g} x the scene's extent "
                            f"({extent:g} m): too small to resolve in float32")


def _check_finite(ctx: _Ctx, scene: Scene) -> Scene:
    """Every array of the scene finite (float32 overflow would show here), else one line
    naming the array."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(scene)[0]:
        # NumPy on the host copy: a jnp check would compile a small program per shape
        if not np.all(np.isfinite(np.asarray(leaf))):  # pragma: no cover (no known case)
            ctx.fail("scene" + jax.tree_util.keystr(path), "not finite in float32")
    return scene


def _bounds(pos: np.ndarray, parts: _Parts, water: dict) -> np.ndarray:
    """[2, 3] box around the camera, every shape, the point lights and the water volume."""
    pts = [pos[None]]
    for k, q in zip(parts.l_kind, parts.l_pos):
        if k == LIGHT_POINT:
            pts.append(np.asarray(q, float)[None])
    for p0, e1, e2 in zip(parts.rect_p0, parts.rect_e1, parts.rect_e2):
        pts.append(np.array([p0, p0 + e1, p0 + e2, p0 + e1 + e2]))
    for cc, r in zip(parts.sph_c, parts.sph_r):
        pts.append(np.array([cc - r, cc + r]))
    if water["enabled"]:
        fp = water["fp"]
        a = np.abs(water["waves"][:, 0]).sum()
        pts.append(np.array([[fp[0], water["floor"], fp[2]],
                             [fp[1], water["level"] + a, fp[3]]]))
    pts = np.concatenate(pts)
    return np.stack([pts.min(0), pts.max(0)])


def _light_power(parts: _Parts, bounds: np.ndarray) -> list:
    """Emitted power of each light (sun, sky, background: into the scene's bounding
    sphere: the sun's irradiance and the sky's pi L through its disk, the background's pi L
    through its whole surface)."""
    rb = 0.5 * np.linalg.norm(bounds[1] - bounds[0])
    power = []
    for k, sh, rad in zip(parts.l_kind, parts.l_shape, parts.l_rad):
        if k == LIGHT_RECT:
            area = np.linalg.norm(np.cross(parts.rect_e1[sh], parts.rect_e2[sh]))
            power.append(rad.mean() * math.pi * area)
        elif k == LIGHT_SPHERE:
            power.append(rad.mean() * math.pi * 4 * math.pi * parts.sph_r[sh] ** 2)
        elif k == LIGHT_SUN:
            power.append(rad.mean() * math.pi * rb * rb)
        elif k == LIGHT_BACKGROUND:
            power.append(rad.mean() * math.pi * 4 * math.pi * rb * rb)
        elif k == LIGHT_POINT:
            power.append(rad.mean() * 4 * math.pi)
        else:
            power.append(rad.mean() * math.pi * math.pi * rb * rb)
    return power


def _to_scene(cam: dict, p: _Parts, water: dict, bounds, power, name: str, dtype) -> Scene:
    """The NumPy float64 parts as the `Scene` pytree (floats in `dtype`, indices int32)."""
    # converted in NumPy and transferred with device_put: jnp.asarray compiles a small
    # copy/conversion program per shape (20-40 ms each, in every process)
    A = lambda x: jax.device_put(np.asarray(x, dtype=np.float64).astype(np.dtype(dtype)))  # noqa: E731
    I = lambda x: jax.device_put(np.asarray(x, dtype=np.int32))  # noqa: E731

    def arr3(lst):
        return A(np.array(lst).reshape(-1, 3))

    camera = Camera(A(cam["pos"]), A(cam["fwd"]), A(cam["right"]), A(cam["up"]),
                    A(cam["tan_half_fov"]), cam["width"], cam["height"])
    one_sided = tuple(p.mat_one_sided) if any(p.mat_one_sided) else ()
    materials = Materials(tuple(p.mat_kind), A(np.array(p.mat_albedo)), A(p.mat_ior),
                          A(np.array(p.mat_glossy)), A(p.mat_exponent), one_sided)
    rects = Rects(arr3(p.rect_p0), arr3(p.rect_e1), arr3(p.rect_e2), I(p.rect_mat),
                  I(p.rect_light))
    spheres = Spheres(arr3(p.sph_c), A(p.sph_r), I(p.sph_mat), I(p.sph_light))
    w, wv = water, water["waves"]
    wat = Water(w["enabled"], w["phase"], A(w["level"]), A(wv[:, 0]), A(wv[:, 1]), A(wv[:, 2]),
                A(wv[:, 3]), A(w["fp"]), A(w["floor"]), A(w["sig_a"]), A(w["sig_s"]), A(w["g"]),
                A(w["b"]), A(w["ior"]), w["mat"])
    aim = tuple(a for _, a in p.l_aim)
    aimed = any(a > 0 for a in aim)
    lights = Lights(tuple(p.l_kind), tuple(p.l_shape), A(np.array(p.l_rad)), arr3(p.l_dir),
                    A(power), arr3(p.l_pos), aim if aimed else (),
                    A(np.ones((1, 1))) if aimed else None, A(w["fp"]) if aimed else None)
    return Scene(camera, materials, rects, spheres, wat, lights, A(bounds), name)
