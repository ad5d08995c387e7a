"""TOML scene files -> `Scene`, with one-line errors naming file, field and problem.

The format (sections, fields, kinds, units, valid ranges, defaults) is the schema in
`_schema.py`, which the validation reads and docs/scene-format.md is generated from. A
file is read and its values checked in `_toml.py` (`SceneError`, `_Ctx`), its `base` files
merged under it here (`read_scene_doc`), each section parsed in `_scene_sections.py`, and
`scene_from_dict` below puts the parts together.
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
from ._schema import DOCUMENT, MAX_BASES, REL_SIZE
from ._toml import SceneError, _Ctx, read_toml
from ._view import view_radius

__all__ = ["SceneError", "load_scene", "read_scene_doc", "scene_from_dict"]


def load_scene(path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
               dtype=jnp.float32) -> Scene:
    """Load and validate a TOML scene file; raises `SceneError` with a one-line message."""
    src = os.fspath(path)
    return scene_from_dict(read_scene_doc(src), src, width=width, height=height, dtype=dtype)


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
        if os.path.isdir(path):
            ctx.fail(f, f"is a directory, not a TOML file: {path}")
        if not os.path.exists(path):
            ctx.fail(f, f"file not found: {path}")
        merged = merge_docs(merged, read_scene_doc(path, chain))
    return merge_docs(merged, doc)


def scene_from_dict(doc: dict, src: str = "<scene>", *, width=None, height=None,
                    dtype=jnp.float32) -> Scene:
    """Validate a parsed scene document (the schema's format) and build the `Scene`;
    `width` / `height` override the camera's. Sections are checked in the order below."""
    ctx = _Ctx(src)
    # `base` is not among the keys: `read_scene_doc` merged the bases and removed it
    ctx.table(doc, DOCUMENT.keys(), DOCUMENT.required(), "")
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
            groups = _bound_points(cam["pos"], parts, water)
            _check_sizes(ctx, parts, _box(groups), groups)
            bounds = _box(_geometry(groups))
            power = _light_power(parts, bounds)
            view = view_radius(cam, parts, water, bounds)
        except FloatingPointError as e:  # pragma: no cover (no known case)
            ctx.fail("scene", f"a derived value is out of range ({e})")
    return _check_finite(ctx, _to_scene(cam, parts, water, bounds, view, power, name,
                                          dtype))


def _check_sizes(ctx: _Ctx, parts: _Parts, bounds: np.ndarray, groups) -> None:
    """Every shape at least REL_SIZE x the scene's extent: smaller ones are not resolved by
    float32 positions at that scale (a 1e-308 m light would have area 0 and no normal). The
    message names what set the extent when one field alone did (a water level of 1e6 m
    makes every light too small)."""
    extent = float(np.linalg.norm(bounds[1] - bounds[0]))
    for field, size in parts.sizes:
        if size < REL_SIZE * extent:
            by = ""
            for name, _ in groups:  # the field whose removal shrinks the extent 10x
                rest = _box([g for g in groups if g[0] != name])
                if float(np.linalg.norm(rest[1] - rest[0])) < 0.1 * extent:
                    by = f", set by {name}"
                    break
            ctx.fail(field, f"{size:g} m is below {REL_SIZE:g} x the scene's extent "
                            f"({extent:g} m{by}): too small to resolve in float32")


def _check_finite(ctx: _Ctx, scene: Scene) -> Scene:
    """Every array of the scene finite (float32 overflow would show here), else one line
    naming the array."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(scene)[0]:
        # NumPy on the host copy: a jnp check would compile a small program per shape
        if not np.all(np.isfinite(np.asarray(leaf))):  # pragma: no cover (no known case)
            ctx.fail("scene" + jax.tree_util.keystr(path), "not finite in float32")
    return scene


def _bound_points(pos: np.ndarray, parts: _Parts, water: dict) -> list:
    """The points the scene's box holds, as (the field that places them, [n, 3] points):
    the camera, the point lights, every shape, the water volume's top and bottom."""
    groups = [("camera.position", pos[None])]
    for i, (k, q) in enumerate(zip(parts.l_kind, parts.l_pos)):
        if k == LIGHT_POINT:
            groups.append((f"lights[{i}].position", np.asarray(q, float)[None]))
    for p0, e1, e2 in zip(parts.rect_p0, parts.rect_e1, parts.rect_e2):
        groups.append(("shapes", np.array([p0, p0 + e1, p0 + e2, p0 + e1 + e2])))
    for cc, r in zip(parts.sph_c, parts.sph_r):
        groups.append(("shapes", np.array([cc - r, cc + r])))
    if water["enabled"]:
        fp = water["fp"]
        a = np.abs(water["waves"][:, 0]).sum()
        groups.append(("water.floor", np.array([[fp[0], water["floor"], fp[2]],
                                                [fp[1], water["floor"], fp[3]]])))
        groups.append(("water.level", np.array([[fp[0], water["level"] + a, fp[2]],
                                                [fp[1], water["level"] + a, fp[3]]])))
    return groups


def _geometry(groups) -> list:
    """The groups of `_bound_points` that are surfaces light can reach (shapes, the water),
    without the camera and the point lights: the scene's `bounds`. The sun's, the sky's and
    the background's photons start on the disk of this box's bounding sphere, so their
    density does not depend on where the camera stands (a camera further back would thin
    the photons); the merging radius's length is the view's (`_view`). Unbiased:
    every line that meets a surface passes through the sphere around all surfaces, so the
    disk covers every photon that can land anywhere; light that meets no surface reaches
    no camera vertex and no camera (the sun and point lights cannot be hit, and an escaped
    camera ray's sky or background is found by its emitter hit, which no disk bounds). A
    scene without surfaces keeps the camera's point (radius 0: no photon lands)."""
    geo = [g for g in groups if g[0] == "shapes" or g[0].startswith("water.")]
    return geo or groups


def _box(groups) -> np.ndarray:
    """[2, 3] box around the points of `_bound_points`' groups."""
    pts = np.concatenate([p for _, p in groups])
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


def _to_scene(cam: dict, p: _Parts, water: dict, bounds, view, power, name: str,
              dtype) -> Scene:
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
    return Scene(camera, materials, rects, spheres, wat, lights, A(bounds), A(view), name)
