"""One parser per section of a scene file; the format is the schema of `_schema.py`.

Each parser validates its section through a `_Ctx` (one-line errors naming the field) and
returns NumPy float64 values. The keys each table accepts and requires, the ranges, the
defaults and the enum choices all come from the schema (`_read` reads a field as its kind
says); the parsers add the order of the checks and the rules that relate fields.
`_Parts` collects what several sections add to (materials, rectangles, spheres, lights),
in file order: named materials, [[shapes]], [[lights]] (each emitter adds an internal
material and a rectangle or sphere), then the water surface's dielectric material.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np

from .._scene import (
    LIGHT_BACKGROUND, LIGHT_POINT, LIGHT_RECT, LIGHT_SKY, LIGHT_SPHERE, LIGHT_SUN, MAT_DIELECTRIC, MAT_DIFFUSE,
    MAT_GLOSSY, MAT_MIRROR,
    PHASE_HG, PHASE_ISOTROPIC, PHASE_WATER,
)
from ._schema import (
    ANY, CAMERA, CHANNELS, COORD, LIGHTS, MATERIALS, PARALLEL, SHAPES, WATER, Derived, Field,
)
# re-exported: the fit config's spectral.ior and the command line's --width / --height
from ._schema import IOR as IOR
from ._schema import MAX_PIXELS as MAX_PIXELS
from ._toml import _Ctx, key_path

_GIVEN = object()


def _read(ctx: _Ctx, d: dict, spec: Field, f: str, v: Any = _GIVEN):
    """The field `spec` of the table `d` at path `f` (or the value `v`), its default when
    absent, read as its kind says with the schema's range, choices and length."""
    if v is _GIVEN:
        v = d[spec.name] if spec.required else d.get(spec.name, spec.default)
    assert not isinstance(v, Derived), spec.name  # the parser computes those
    path = f"{f}.{spec.name}"
    k, rng = spec.kind, spec.range
    if k == "number":
        return ctx.number(v, path, rng)
    if k == "integer":
        return ctx.integer(v, path, int(rng.lo), int(rng.hi))
    if k == "vector":
        return ctx.vec(v, path, spec.n, rng=rng)
    if k == "direction":
        return ctx.unit(v, path, rng)
    if k == "spectrum":
        return ctx.spectrum(v, path, rng, positive=spec.nonzero)
    if k == "enum":
        return ctx.string(v, path, spec.choices)
    if k == "boolean":
        return ctx.boolean(v, path)
    return ctx.string(v, path)  # string, material


def _check_table(ctx: _Ctx, d, spec, f: str) -> None:
    """`d` a table with only the keys `spec` (a `Table` or a `Variant`) accepts, and every
    key it requires."""
    ctx.table(d, spec.keys(), spec.required(), f)


def _frame(normal: np.ndarray, hint: np.ndarray | None):
    if hint is None:
        hint = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([0.0, 0.0, -1.0])
    t1 = np.cross(hint, normal)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    return t1, t2


@dataclasses.dataclass
class _Parts:
    """Materials, rectangles, spheres and lights gathered over the sections."""

    named: dict = dataclasses.field(default_factory=dict)  # the [materials] table
    mat_names: list = dataclasses.field(default_factory=list)
    mat_kind: list = dataclasses.field(default_factory=list)
    mat_albedo: list = dataclasses.field(default_factory=list)
    mat_ior: list = dataclasses.field(default_factory=list)
    mat_glossy: list = dataclasses.field(default_factory=list)
    mat_exponent: list = dataclasses.field(default_factory=list)
    mat_one_sided: list = dataclasses.field(default_factory=list)
    rect_p0: list = dataclasses.field(default_factory=list)
    rect_e1: list = dataclasses.field(default_factory=list)
    rect_e2: list = dataclasses.field(default_factory=list)
    rect_mat: list = dataclasses.field(default_factory=list)
    rect_light: list = dataclasses.field(default_factory=list)
    sph_c: list = dataclasses.field(default_factory=list)
    sph_r: list = dataclasses.field(default_factory=list)
    sph_mat: list = dataclasses.field(default_factory=list)
    sph_light: list = dataclasses.field(default_factory=list)
    l_kind: list = dataclasses.field(default_factory=list)
    l_shape: list = dataclasses.field(default_factory=list)
    l_rad: list = dataclasses.field(default_factory=list)
    l_dir: list = dataclasses.field(default_factory=list)
    l_pos: list = dataclasses.field(default_factory=list)
    l_aim: list = dataclasses.field(default_factory=list)  # (field, fraction) per light
    basin: tuple | None = None  # (min, max) of the last basin
    sizes: list = dataclasses.field(default_factory=list)  # (field, smallest side or radius)

    def add_material(self, kind, albedo, ior=1.0, glossy=0.0, exponent=1.0, name=None) -> int:
        self.mat_kind.append(kind)
        self.mat_albedo.append(np.asarray(albedo, float) * np.ones(CHANNELS))
        self.mat_ior.append(ior)
        self.mat_glossy.append(np.asarray(glossy, float) * np.ones(CHANNELS))
        self.mat_exponent.append(float(exponent))
        self.mat_one_sided.append(False)
        self.mat_names.append(name or f"<internal {len(self.mat_kind)}>")
        return len(self.mat_kind) - 1

    def sided(self, ctx: _Ctx, s: dict, f: str, mat: int) -> int:
        """The material of a shape with `two_sided` (default true: both faces scatter, as
        always here); false: a one-sided copy of `mat` (black from behind), diffuse and
        glossy only."""
        if _read(ctx, s, SHAPES["two_sided"], f):
            return mat
        if self.mat_kind[mat] not in (MAT_DIFFUSE, MAT_GLOSSY):
            ctx.fail(f + ".two_sided", f"only diffuse and glossy surfaces can be one-sided "
                                      f"(material {self.mat_names[mat]!r} is not)")
        name = f"{self.mat_names[mat]} (one-sided)"
        if name in self.mat_names:
            return self.mat_names.index(name)
        k = self.add_material(self.mat_kind[mat], self.mat_albedo[mat], self.mat_ior[mat],
                              self.mat_glossy[mat], self.mat_exponent[mat], name=name)
        self.mat_one_sided[k] = True
        return k

    def mat_ref(self, ctx: _Ctx, v, field: str) -> int:
        s = ctx.string(v, field)
        if s not in self.named:
            ctx.fail(field, f"unknown material {s!r}")
        return self.mat_names.index(s)

    def add_rect(self, center, normal, size, hint, mat, light=-1) -> None:
        t1, t2 = _frame(normal, hint)
        e1, e2 = t1 * size[0], t2 * size[1]
        self.add_rect_corners(center - 0.5 * e1 - 0.5 * e2, e1, e2, mat, light)

    def add_rect_corners(self, p0, e1, e2, mat, light=-1) -> None:
        self.rect_p0.append(np.asarray(p0, float))
        self.rect_e1.append(np.asarray(e1, float))
        self.rect_e2.append(np.asarray(e2, float))
        self.rect_mat.append(mat)
        self.rect_light.append(light)

    def add_sphere(self, center, radius, mat, light=-1) -> None:
        self.sph_c.append(center)
        self.sph_r.append(radius)
        self.sph_mat.append(mat)
        self.sph_light.append(light)


# ---------------------------------------------------------------- [camera]
def parse_camera(ctx: _Ctx, c, width=None, height=None) -> dict:
    """[camera] -> origin, orthonormal (forward, right, up), tan(fov / 2), width, height."""
    _check_table(ctx, c, CAMERA, "camera")
    pos = _read(ctx, c, CAMERA["position"], "camera")
    tgt = _read(ctx, c, CAMERA["target"], "camera")
    up = _read(ctx, c, CAMERA["up"], "camera")
    fov = _read(ctx, c, CAMERA["fov"], "camera")
    W = _read(ctx, c, CAMERA["width"], "camera", c["width"] if width is None else width)
    H = _read(ctx, c, CAMERA["height"], "camera", c["height"] if height is None else height)
    # The frame in float64 NumPy: jaxvcm._camera.camera_frame computes in JAX (float32
    # unless x64 is on) and does not give bit-identical frames.
    fwd = tgt - pos
    if np.linalg.norm(fwd) < 1e-6 * max(1.0, np.abs(pos).max()):
        ctx.fail("camera.target", "must differ from camera.position (by more than float32 "
                                  "resolves)")
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-6:
        ctx.fail("camera.up", "must not be parallel to the view direction")
    right /= np.linalg.norm(right)
    cup = np.cross(right, fwd)
    return dict(pos=pos, fwd=fwd, right=right, up=cup,
                tan_half_fov=math.tan(math.radians(fov) / 2), width=W, height=H)


# ---------------------------------------------------------------- [materials.NAME]
def _albedo(ctx: _Ctx, d: dict, spec: Field, f: str) -> np.ndarray:
    """One rule for every albedo, of materials and of emitters: within the schema's range
    (0 <= albedo <= 1), the upper bound reported as energy conservation."""
    v = d.get(spec.name, spec.default)
    field = f"{f}.{spec.name}"
    a = ctx.spectrum(v, field)
    for i, x in enumerate(a):
        if x > spec.range.hi:
            ctx.fail(field if not isinstance(v, list) else f"{field}[{i}]",
                     f"must be <= {spec.range.hi:g} (energy conservation), got {x:g}")
    return a


_MAT_KINDS = {"diffuse": MAT_DIFFUSE, "mirror": MAT_MIRROR}


def parse_materials(ctx: _Ctx, mats, parts: _Parts) -> None:
    if not isinstance(mats, dict):
        ctx.fail("materials", "expected a table of named materials")
    parts.named = mats
    for mname, m in mats.items():
        f = key_path("materials", mname)
        _check_table(ctx, m, MATERIALS, f)
        kind = _read(ctx, m, MATERIALS["type"], f)
        spec = MATERIALS.variant(kind)
        _check_table(ctx, m, spec, f)
        if kind == "glass":  # a smooth dielectric: exact Fresnel, lossless
            parts.add_material(MAT_DIELECTRIC, 1.0, _read(ctx, m, spec["ior"], f), name=mname)
        elif kind == "glossy":  # Lambertian k_d + normalised Phong k_s (SmallVCM's model)
            kd = _albedo(ctx, m, spec["albedo"], f)
            ks = _albedo(ctx, m, spec["glossy"], f)
            for i, x in enumerate(kd + ks):
                if x > spec["glossy"].range.hi:
                    ctx.fail(f + ".glossy", f"albedo + glossy must be <= 1 (energy "
                                            f"conservation), got {x:g} in channel {i}")
            n = _read(ctx, m, spec["exponent"], f)
            parts.add_material(MAT_GLOSSY, kd, 1.0, ks, n, name=mname)
        else:
            parts.add_material(_MAT_KINDS[kind], _albedo(ctx, m, spec["albedo"], f), name=mname)


# ---------------------------------------------------------------- [[shapes]]
def _rect_size(ctx: _Ctx, s: dict, f: str, spec: Field) -> np.ndarray:
    """Two sides: numbers within the coordinates' range, then > 0, then in the size range
    (so a negative side is reported as a zero-size shape)."""
    size = ctx.vec(s[spec.name], f + ".size", spec.n, rng=COORD)
    if np.any(size <= 0):
        ctx.fail(f + ".size", "zero-size shape: both sides must be > 0")
    for i, x in enumerate(size):
        ctx.number(x, f"{f}.size[{i}]", spec.range)
    return size


def _radius(ctx: _Ctx, s: dict, f: str, spec: Field) -> float:
    r = ctx.number(s[spec.name], f + ".radius", COORD)
    if r <= 0:
        ctx.fail(f + ".radius", "zero-size shape: must be > 0")
    return ctx.number(r, f + ".radius", spec.range)


def _rect(ctx: _Ctx, s: dict, f: str, spec, parts: _Parts, mat: int, light: int = -1) -> None:
    """A rectangle of a [[shapes]] or [[lights]] entry: center, normal, size, `up` hint."""
    size = _rect_size(ctx, s, f, spec["size"])
    normal = _read(ctx, s, spec["normal"], f)
    hint = None
    if "up" in s:
        hint = _read(ctx, s, spec["up"], f)
        if abs(np.dot(hint, normal)) > PARALLEL:
            ctx.fail(f + ".up", f"must not be parallel to {f}.normal (it orients the "
                                "rectangle's sides)")
    parts.add_rect(_read(ctx, s, spec["center"], f), normal, size, hint, mat, light)
    parts.sizes.append((f + ".size", float(size.min())))


def _material(ctx: _Ctx, s: dict, f: str, parts: _Parts, spec: Field) -> int:
    """The material a shape names in `spec`, one-sided if the shape says so."""
    return parts.sided(ctx, s, f, parts.mat_ref(ctx, s[spec.name], f"{f}.{spec.name}"))


def _rect_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    spec = SHAPES.variant("rect")
    _check_table(ctx, s, spec, f)
    _rect(ctx, s, f, spec, parts, _material(ctx, s, f, parts, spec["material"]))


def _sphere_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    spec = SHAPES.variant("sphere")
    _check_table(ctx, s, spec, f)
    r = _radius(ctx, s, f, spec["radius"])
    center = _read(ctx, s, spec["center"], f)
    parts.add_sphere(center, r, _material(ctx, s, f, parts, spec["material"]))
    parts.sizes.append((f + ".radius", r))


def _basin_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    """An open box: the floor and 4 inward-facing walls, as 5 rectangles."""
    spec = SHAPES.variant("basin")
    _check_table(ctx, s, spec, f)
    lo = _read(ctx, s, spec["min"], f)
    hi = _read(ctx, s, spec["max"], f)
    if np.any(hi <= lo):
        ctx.fail(f + ".max", "zero-size shape: max must exceed min on every axis")
    tops = (_read(ctx, s, spec["wall_tops"], f, s["wall_tops"]) if "wall_tops" in s
            else np.full(4, hi[1]))
    if np.any(tops <= lo[1]):
        ctx.fail(f + ".wall_tops", "every wall top must be above the floor")
    parts.sizes.append((f + ".max", float(min((hi - lo).min(), (tops - lo[1]).min()))))
    fm = _material(ctx, s, f, parts, spec["floor_material"])
    wm = _material(ctx, s, f, parts, spec["wall_material"])
    x0, y0, z0 = lo
    x1, _, z1 = hi
    dx, dz = x1 - x0, z1 - z0
    add = parts.add_rect_corners  # e1 x e2 must point into the pool
    add([x0, y0, z0], [0, 0, dz], [dx, 0, 0], fm)  # floor, +y
    add([x0, y0, z0], [0, tops[0] - y0, 0], [0, 0, dz], wm)  # x0 wall, +x
    add([x1, y0, z0], [0, 0, dz], [0, tops[1] - y0, 0], wm)  # x1 wall, -x
    add([x0, y0, z0], [dx, 0, 0], [0, tops[2] - y0, 0], wm)  # z0 wall, +z
    add([x0, y0, z1], [0, tops[3] - y0, 0], [dx, 0, 0], wm)  # z1 wall, -z
    parts.basin = (lo, hi)


_SHAPES = {"rect": _rect_shape, "sphere": _sphere_shape, "basin": _basin_shape}
assert tuple(_SHAPES) == SHAPES.types()


def parse_shapes(ctx: _Ctx, shapes, parts: _Parts) -> None:
    if not isinstance(shapes, list):
        ctx.fail("shapes", "expected an array of tables ([[shapes]])")
    for i, s in enumerate(shapes):
        f = f"shapes[{i}]"
        if not isinstance(s, dict) or "type" not in s:
            ctx.fail(f + ".type", "missing required field")
        kind = _read(ctx, s, SHAPES["type"], f)
        _SHAPES[kind](ctx, s, f, parts)


# ---------------------------------------------------------------- [[lights]]
def _emitter_material(ctx: _Ctx, l: dict, f: str, parts: _Parts, spec) -> int:
    return parts.add_material(MAT_DIFFUSE, _albedo(ctx, l, spec["albedo"], f))


def _rect_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    spec = LIGHTS.variant("rect")
    _check_table(ctx, l, spec, f)
    rad = _read(ctx, l, spec["radiance"], f)
    m = _emitter_material(ctx, l, f, parts, spec)
    _rect(ctx, l, f, spec, parts, m, len(parts.l_kind))
    return LIGHT_RECT, len(parts.rect_p0) - 1, rad, np.zeros(3)


def _sphere_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    spec = LIGHTS.variant("sphere")
    _check_table(ctx, l, spec, f)
    r = _radius(ctx, l, f, spec["radius"])
    rad = _read(ctx, l, spec["radiance"], f)
    m = _emitter_material(ctx, l, f, parts, spec)
    parts.add_sphere(_read(ctx, l, spec["center"], f), r, m, len(parts.l_kind))
    parts.sizes.append((f + ".radius", r))
    return LIGHT_SPHERE, len(parts.sph_c) - 1, rad, np.zeros(3)


def _aim(ctx: _Ctx, l: dict, f: str, spec: Field) -> float:
    """`aim`: the fraction of the light's photons aimed at the water's footprint, in the
    schema's [0, 1) (the rest start on the scene's bounding disk, so light that never meets
    the water is still emitted)."""
    a = ctx.number(l.get(spec.name, spec.default), f + ".aim", ANY, nonneg=True)
    if a >= spec.range.hi:
        ctx.fail(f + ".aim", "must be below 1 (the rest of the photons cover the scene)")
    return a


def _sun_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    spec = LIGHTS.variant("sun")
    _check_table(ctx, l, spec, f)
    dvec = _read(ctx, l, spec["direction"], f)
    rad = _read(ctx, l, spec["irradiance"], f)
    aim = _aim(ctx, l, f, spec["aim"])
    if aim > 0 and dvec[1] >= 0:
        ctx.fail(f + ".aim", "an aimed sun must shine downwards (direction y < 0)")
    parts.l_aim.append((f + ".aim", aim))
    return LIGHT_SUN, -1, rad, dvec


def _constant_light(kind: int, ctx: _Ctx, l: dict, f: str, parts: _Parts):
    """Sky (upper hemisphere) and background (every direction): a constant radiance."""
    spec = LIGHTS.variant("sky" if kind == LIGHT_SKY else "background")
    _check_table(ctx, l, spec, f)
    if kind == LIGHT_SKY:
        parts.l_aim.append((f + ".aim", _aim(ctx, l, f, spec["aim"])))
    rad = _read(ctx, l, spec["radiance"], f)
    return kind, -1, rad, np.zeros(3)


def _point_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    spec = LIGHTS.variant("point")
    _check_table(ctx, l, spec, f)
    pos = _read(ctx, l, spec["position"], f)
    rad = _read(ctx, l, spec["intensity"], f)
    return LIGHT_POINT, -1, rad, pos


_LIGHTS = {"rect": _rect_light, "sphere": _sphere_light, "sun": _sun_light,
           "sky": functools.partial(_constant_light, LIGHT_SKY),
           "background": functools.partial(_constant_light, LIGHT_BACKGROUND),
           "point": _point_light}
assert tuple(_LIGHTS) == LIGHTS.types()


def parse_lights(ctx: _Ctx, lights, parts: _Parts) -> None:
    if not isinstance(lights, list) or not lights:
        ctx.fail("lights", "the scene has no light (add a [[lights]] table)")
    for i, l in enumerate(lights):
        f = f"lights[{i}]"
        if not isinstance(l, dict) or "type" not in l:
            ctx.fail(f + ".type", "missing required field")
        kind = _read(ctx, l, LIGHTS["type"], f)
        if kind in ("sky", "background") and any(k in (LIGHT_SKY, LIGHT_BACKGROUND)
                                                  for k in parts.l_kind):
            ctx.fail(f + ".type", "at most one sky or background light per scene")
        n_aim = len(parts.l_aim)
        k, shape, rad, dvec = _LIGHTS[kind](ctx, l, f, parts)
        if len(parts.l_aim) == n_aim:
            parts.l_aim.append((f + ".aim", 0.0))
        parts.l_kind.append(k)
        parts.l_shape.append(shape)
        parts.l_rad.append(rad)
        point = k == LIGHT_POINT  # its vector is the position, not a direction
        parts.l_dir.append(np.zeros(3) if point else dvec)
        parts.l_pos.append(dvec if point else np.zeros(3))


# ---------------------------------------------------------------- [water]
def _wave(ctx: _Ctx, w, f: str, spec: Field) -> np.ndarray:
    """[A, kx, kz, phase]: amplitude in metres, wave numbers in rad/m, phase in rad."""
    if not isinstance(w, list) or len(w) != len(spec.items):
        ctx.fail(f, "expected a list of 4 numbers [A, kx, kz, phase]")
    return np.array([ctx.number(x, f"{f}[{i}]", c.range)
                     for i, (x, c) in enumerate(zip(w, spec.items))])


_PHASES = dict(isotropic=PHASE_ISOTROPIC, hg=PHASE_HG, water=PHASE_WATER)
assert tuple(_PHASES) == WATER["phase"].choices


def _no_water() -> dict:
    return dict(enabled=False, phase=PHASE_ISOTROPIC, level=0.0, waves=np.zeros((0, 4)),
                fp=np.zeros(4), floor=0.0, sig_a=np.zeros(CHANNELS), sig_s=np.zeros(CHANNELS),
                g=0.0, b=WATER["b"].default, ior=1.0, mat=0)


def parse_water(ctx: _Ctx, wdoc, parts: _Parts) -> dict:
    """[water] (optional) -> the surface, footprint, floor and medium; adds the surface's
    dielectric material last."""
    if wdoc is None:
        return _no_water()
    W, f = WATER, "water"
    _check_table(ctx, wdoc, W, f)
    level = _read(ctx, wdoc, W["level"], f)
    waves = wdoc.get("waves", W["waves"].default)
    if not isinstance(waves, list):
        ctx.fail("water.waves", "expected a list of [A, kx, kz, phase]")
    wv = np.array([_wave(ctx, w, f"water.waves[{j}]", W["waves"]) for j, w in enumerate(waves)]
                  ).reshape(-1, 4)
    sig_a = _read(ctx, wdoc, W["sigma_a"], f)
    sig_s = _read(ctx, wdoc, W["sigma_s"], f)
    phase = _read(ctx, wdoc, W["phase"], f)
    g = _read(ctx, wdoc, W["g"], f)
    b = _read(ctx, wdoc, W["b"], f)
    ior = _read(ctx, wdoc, W["ior"], f)
    basin = parts.basin
    if "footprint" in wdoc:
        fp = _read(ctx, wdoc, W["footprint"], f, wdoc["footprint"])
    elif basin is not None:
        fp = np.array([basin[0][0], basin[1][0], basin[0][2], basin[1][2]])
    else:
        ctx.fail("water.footprint", "missing required field (no basin to take it from)")
    if fp[1] <= fp[0] or fp[3] <= fp[2]:
        ctx.fail("water.footprint", "zero-size shape: need xmin < xmax and zmin < zmax")
    if "floor" in wdoc:
        wfloor = _read(ctx, wdoc, W["floor"], f, wdoc["floor"])
    elif basin is not None:
        wfloor = basin[0][1]
    else:
        ctx.fail("water.floor", "missing required field (no basin to take it from)")
    if wfloor >= level - np.abs(wv[:, 0]).sum():
        ctx.fail("water.floor", "must lie below the lowest point of the water surface")
    wmat = parts.add_material(MAT_DIELECTRIC, 1.0, ior)
    return dict(enabled=True, phase=_PHASES[phase], level=level, waves=wv, fp=fp,
                floor=wfloor, sig_a=sig_a, sig_s=sig_s, g=g, b=b, ior=ior, mat=wmat)
