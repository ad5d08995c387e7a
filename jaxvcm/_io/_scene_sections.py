"""One parser per section of a scene file (the format: `_scene_file.py`).

Each parser validates its section through a `_Ctx` (one-line errors naming the field) and
returns NumPy float64 values; `_Parts` collects what several sections add to (materials,
rectangles, spheres, lights), in file order: named materials, [[shapes]], [[lights]]
(each emitter adds an internal material and a rectangle or sphere), then the water
surface's dielectric material.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .._scene import (
    LIGHT_BACKGROUND, LIGHT_POINT, LIGHT_RECT, LIGHT_SKY, LIGHT_SPHERE, LIGHT_SUN, MAT_DIELECTRIC, MAT_DIFFUSE,
    MAT_GLOSSY, MAT_MIRROR,
    PHASE_HG, PHASE_ISOTROPIC, PHASE_WATER,
)
from ._toml import CHANNELS, COORD, SIZE, Range, _Ctx, key_path

# ---- the ranges of the scene format's numbers (the schema table in `_scene_file.py`) ----
FOV = Range(0.01, 179.0, "degrees")
MAX_PIXELS = 16384  # per side: a 16384^2 float32 RGB film is 3.2 GB
ALBEDO = Range(0.0, 1.0)  # materials and emitters alike (energy conservation)
RADIANCE = Range(0.0, 1e15, "W/(m^2 sr)")  # irradiance: W/m^2; power stays < 1e29 W
SIGMA = Range(0.0, 1e6, "1/m")  # optical depth 1 over a micrometre
IOR = Range(1.0, 3.0)  # 1: an index-matched boundary (no refraction); diamond is 2.42
WAVE_K = Range(-1e4, 1e4, "rad/m")  # wavelengths down to 0.6 mm
WAVE_PHASE = Range(-1e6, 1e6, "rad")
HG_G = Range(-0.999, 0.999)
WATER_B = Range(0.0, 10.0)  # the 1 + b cos^2 phase of water (0.835 by Morel)
EXPONENT = Range(1.0, 1e5)  # Phong exponent: a lobe of ~1/sqrt(n) rad, 0.2 degrees at 1e5
PARALLEL = 0.999  # |cos| between a rectangle's normal and its `up` hint above which it fails


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
        if "two_sided" not in s or ctx.boolean(s["two_sided"], f + ".two_sided"):
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
    ctx.table(c, {"position", "target", "up", "fov", "width", "height"},
              {"position", "target", "fov", "width", "height"}, "camera")
    pos = ctx.vec(c["position"], "camera.position", rng=COORD)
    tgt = ctx.vec(c["target"], "camera.target", rng=COORD)
    up = ctx.unit(c.get("up", [0.0, 1.0, 0.0]), "camera.up")
    fov = ctx.number(c["fov"], "camera.fov", FOV)
    W = ctx.integer(c["width"] if width is None else width, "camera.width", hi=MAX_PIXELS)
    H = ctx.integer(c["height"] if height is None else height, "camera.height", hi=MAX_PIXELS)
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
def _albedo(ctx: _Ctx, v, field: str) -> np.ndarray:
    """One rule for every albedo, of materials and of emitters: 0 <= albedo <= 1."""
    a = ctx.spectrum(v, field)
    for i, x in enumerate(a):
        if x > 1:
            ctx.fail(field if not isinstance(v, list) else f"{field}[{i}]",
                     f"must be <= 1 (energy conservation), got {x:g}")
    return a


def parse_materials(ctx: _Ctx, mats, parts: _Parts) -> None:
    if not isinstance(mats, dict):
        ctx.fail("materials", "expected a table of named materials")
    parts.named = mats
    for mname, m in mats.items():
        f = key_path("materials", mname)
        ctx.table(m, {"type", "albedo", "ior", "glossy", "exponent"}, {"type"}, f)
        kind = ctx.string(m["type"], f + ".type", ("diffuse", "mirror", "glass", "glossy"))
        if kind == "glass":  # a smooth dielectric: exact Fresnel, lossless
            ctx.table(m, {"type", "ior"}, {"type", "ior"}, f)
            parts.add_material(MAT_DIELECTRIC, 1.0, ctx.number(m["ior"], f + ".ior", IOR),
                               name=mname)
        elif kind == "glossy":  # Lambertian k_d + normalised Phong k_s (SmallVCM's model)
            ctx.table(m, {"type", "albedo", "glossy", "exponent"}, {"type"}, f)
            kd = _albedo(ctx, m.get("albedo", 0.0), f + ".albedo")
            ks = _albedo(ctx, m.get("glossy", 0.5), f + ".glossy")
            for i, x in enumerate(kd + ks):
                if x > 1:
                    ctx.fail(f + ".glossy", f"albedo + glossy must be <= 1 (energy "
                                            f"conservation), got {x:g} in channel {i}")
            n = ctx.number(m.get("exponent", 90.0), f + ".exponent", EXPONENT)
            parts.add_material(MAT_GLOSSY, kd, 1.0, ks, n, name=mname)
        else:
            ctx.table(m, {"type", "albedo"}, {"type"}, f)
            albedo = _albedo(ctx, m.get("albedo", 1.0 if kind == "mirror" else 0.5),
                             f + ".albedo")
            parts.add_material(MAT_DIFFUSE if kind == "diffuse" else MAT_MIRROR, albedo,
                               name=mname)


# ---------------------------------------------------------------- [[shapes]]
def _rect_size(ctx: _Ctx, s: dict, f: str) -> np.ndarray:
    size = ctx.vec(s["size"], f + ".size", 2, rng=COORD)
    if np.any(size <= 0):
        ctx.fail(f + ".size", "zero-size shape: both sides must be > 0")
    for i, x in enumerate(size):
        ctx.number(x, f"{f}.size[{i}]", SIZE)
    return size


def _radius(ctx: _Ctx, s: dict, f: str) -> float:
    r = ctx.number(s["radius"], f + ".radius", COORD)
    if r <= 0:
        ctx.fail(f + ".radius", "zero-size shape: must be > 0")
    return ctx.number(r, f + ".radius", SIZE)


def _rect(ctx: _Ctx, s: dict, f: str, parts: _Parts, mat: int, light: int = -1) -> None:
    """A rectangle of a [[shapes]] or [[lights]] entry: center, normal, size, `up` hint."""
    size = _rect_size(ctx, s, f)
    normal = ctx.unit(s["normal"], f + ".normal")
    hint = None
    if "up" in s:
        hint = ctx.unit(s["up"], f + ".up")
        if abs(np.dot(hint, normal)) > PARALLEL:
            ctx.fail(f + ".up", f"must not be parallel to {f}.normal (it orients the "
                                "rectangle's sides)")
    parts.add_rect(ctx.vec(s["center"], f + ".center", rng=COORD), normal, size, hint, mat,
                   light)
    parts.sizes.append((f + ".size", float(size.min())))


def _rect_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    ctx.table(s, {"type", "center", "normal", "size", "up", "material", "two_sided"},
              {"center", "normal", "size", "material"}, f)
    _rect(ctx, s, f, parts,
          parts.sided(ctx, s, f, parts.mat_ref(ctx, s["material"], f + ".material")))


def _sphere_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    ctx.table(s, {"type", "center", "radius", "material", "two_sided"},
              {"center", "radius", "material"}, f)
    r = _radius(ctx, s, f)
    center = ctx.vec(s["center"], f + ".center", rng=COORD)
    parts.add_sphere(center, r,
                     parts.sided(ctx, s, f, parts.mat_ref(ctx, s["material"], f + ".material")))
    parts.sizes.append((f + ".radius", r))


def _basin_shape(ctx: _Ctx, s: dict, f: str, parts: _Parts) -> None:
    """An open box: the floor and 4 inward-facing walls, as 5 rectangles."""
    ctx.table(s, {"type", "min", "max", "floor_material", "wall_material", "wall_tops",
                  "two_sided"}, {"min", "max", "floor_material", "wall_material"}, f)
    lo = ctx.vec(s["min"], f + ".min", rng=COORD)
    hi = ctx.vec(s["max"], f + ".max", rng=COORD)
    if np.any(hi <= lo):
        ctx.fail(f + ".max", "zero-size shape: max must exceed min on every axis")
    tops = (ctx.vec(s["wall_tops"], f + ".wall_tops", 4, rng=COORD) if "wall_tops" in s
            else np.full(4, hi[1]))
    if np.any(tops <= lo[1]):
        ctx.fail(f + ".wall_tops", "every wall top must be above the floor")
    parts.sizes.append((f + ".max", float(min((hi - lo).min(), (tops - lo[1]).min()))))
    fm = parts.sided(ctx, s, f, parts.mat_ref(ctx, s["floor_material"], f + ".floor_material"))
    wm = parts.sided(ctx, s, f, parts.mat_ref(ctx, s["wall_material"], f + ".wall_material"))
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


def parse_shapes(ctx: _Ctx, shapes, parts: _Parts) -> None:
    if not isinstance(shapes, list):
        ctx.fail("shapes", "expected an array of tables ([[shapes]])")
    for i, s in enumerate(shapes):
        f = f"shapes[{i}]"
        if not isinstance(s, dict) or "type" not in s:
            ctx.fail(f + ".type", "missing required field")
        kind = ctx.string(s["type"], f + ".type", tuple(_SHAPES))
        _SHAPES[kind](ctx, s, f, parts)


# ---------------------------------------------------------------- [[lights]]
def _emitter_material(ctx: _Ctx, l: dict, f: str, parts: _Parts) -> int:
    return parts.add_material(MAT_DIFFUSE, _albedo(ctx, l.get("albedo", 0.0), f + ".albedo"))


def _rect_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    ctx.table(l, {"type", "center", "normal", "size", "radiance", "up", "albedo"},
              {"center", "normal", "size", "radiance"}, f)
    rad = ctx.spectrum(l["radiance"], f + ".radiance", RADIANCE, positive=True)
    m = _emitter_material(ctx, l, f, parts)
    _rect(ctx, l, f, parts, m, len(parts.l_kind))
    return LIGHT_RECT, len(parts.rect_p0) - 1, rad, np.zeros(3)


def _sphere_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    ctx.table(l, {"type", "center", "radius", "radiance", "albedo"},
              {"center", "radius", "radiance"}, f)
    r = _radius(ctx, l, f)
    rad = ctx.spectrum(l["radiance"], f + ".radiance", RADIANCE, positive=True)
    m = _emitter_material(ctx, l, f, parts)
    parts.add_sphere(ctx.vec(l["center"], f + ".center", rng=COORD), r, m, len(parts.l_kind))
    parts.sizes.append((f + ".radius", r))
    return LIGHT_SPHERE, len(parts.sph_c) - 1, rad, np.zeros(3)


def _aim(ctx: _Ctx, l: dict, f: str) -> float:
    """`aim`: the fraction of the light's photons aimed at the water's footprint (issue
    13; 0 <= aim < 1: the rest start on the scene's bounding disk, so light that never
    meets the water is still emitted)."""
    a = ctx.number(l.get("aim", 0.0), f + ".aim", nonneg=True)
    if a >= 1.0:
        ctx.fail(f + ".aim", "must be below 1 (the rest of the photons cover the scene)")
    return a


def _sun_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    ctx.table(l, {"type", "direction", "irradiance", "aim"}, {"direction", "irradiance"}, f)
    dvec = ctx.unit(l["direction"], f + ".direction")
    rad = ctx.spectrum(l["irradiance"], f + ".irradiance", RADIANCE, positive=True)
    aim = _aim(ctx, l, f)
    if aim > 0 and dvec[1] >= 0:
        ctx.fail(f + ".aim", "an aimed sun must shine downwards (direction y < 0)")
    parts.l_aim.append((f + ".aim", aim))
    return LIGHT_SUN, -1, rad, dvec


def _constant_light(kind: int, ctx: _Ctx, l: dict, f: str, parts: _Parts):
    """Sky (upper hemisphere) and background (every direction): a constant radiance."""
    if kind == LIGHT_SKY:
        ctx.table(l, {"type", "radiance", "aim"}, {"radiance"}, f)
        parts.l_aim.append((f + ".aim", _aim(ctx, l, f)))
        rad = ctx.spectrum(l["radiance"], f + ".radiance", RADIANCE, positive=True)
        return kind, -1, rad, np.zeros(3)
    ctx.table(l, {"type", "radiance"}, {"radiance"}, f)
    rad = ctx.spectrum(l["radiance"], f + ".radiance", RADIANCE, positive=True)
    return kind, -1, rad, np.zeros(3)


def _point_light(ctx: _Ctx, l: dict, f: str, parts: _Parts):
    ctx.table(l, {"type", "position", "intensity"}, {"position", "intensity"}, f)
    pos = ctx.vec(l["position"], f + ".position", rng=COORD)
    rad = ctx.spectrum(l["intensity"], f + ".intensity", RADIANCE, positive=True)
    return LIGHT_POINT, -1, rad, pos


_LIGHTS = {"rect": _rect_light, "sphere": _sphere_light, "sun": _sun_light,
           "sky": functools.partial(_constant_light, LIGHT_SKY),
           "background": functools.partial(_constant_light, LIGHT_BACKGROUND),
           "point": _point_light}


def parse_lights(ctx: _Ctx, lights, parts: _Parts) -> None:
    if not isinstance(lights, list) or not lights:
        ctx.fail("lights", "the scene has no light (add a [[lights]] table)")
    for i, l in enumerate(lights):
        f = f"lights[{i}]"
        if not isinstance(l, dict) or "type" not in l:
            ctx.fail(f + ".type", "missing required field")
        kind = ctx.string(l["type"], f + ".type", tuple(_LIGHTS))
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
def _wave(ctx: _Ctx, w, f: str) -> np.ndarray:
    """[A, kx, kz, phase]: amplitude in metres, wave numbers in rad/m, phase in rad."""
    if not isinstance(w, list) or len(w) != 4:
        ctx.fail(f, "expected a list of 4 numbers [A, kx, kz, phase]")
    rngs = (COORD, WAVE_K, WAVE_K, WAVE_PHASE)
    return np.array([ctx.number(x, f"{f}[{i}]", r) for i, (x, r) in enumerate(zip(w, rngs))])


_PHASES = dict(isotropic=PHASE_ISOTROPIC, hg=PHASE_HG, water=PHASE_WATER)


def _no_water() -> dict:
    return dict(enabled=False, phase=PHASE_ISOTROPIC, level=0.0, waves=np.zeros((0, 4)),
                fp=np.zeros(4), floor=0.0, sig_a=np.zeros(CHANNELS), sig_s=np.zeros(CHANNELS),
                g=0.0, b=0.835, ior=1.0, mat=0)


def parse_water(ctx: _Ctx, wdoc, parts: _Parts) -> dict:
    """[water] (optional) -> the surface, footprint, floor and medium; adds the surface's
    dielectric material last."""
    if wdoc is None:
        return _no_water()
    ctx.table(wdoc, {"level", "waves", "sigma_a", "sigma_s", "phase", "g", "b", "ior",
                     "footprint", "floor"}, {"level", "sigma_a", "sigma_s", "ior"}, "water")
    level = ctx.number(wdoc["level"], "water.level", COORD)
    waves = wdoc.get("waves", [])
    if not isinstance(waves, list):
        ctx.fail("water.waves", "expected a list of [A, kx, kz, phase]")
    wv = np.array([_wave(ctx, w, f"water.waves[{j}]") for j, w in enumerate(waves)]
                  ).reshape(-1, 4)
    sig_a = ctx.spectrum(wdoc["sigma_a"], "water.sigma_a", SIGMA)
    sig_s = ctx.spectrum(wdoc["sigma_s"], "water.sigma_s", SIGMA)
    phase = ctx.string(wdoc.get("phase", "isotropic"), "water.phase", tuple(_PHASES))
    g = ctx.number(wdoc.get("g", 0.0), "water.g", HG_G)
    b = ctx.number(wdoc.get("b", 0.835), "water.b", WATER_B)
    ior = ctx.number(wdoc["ior"], "water.ior", IOR)
    basin = parts.basin
    if "footprint" in wdoc:
        fp = ctx.vec(wdoc["footprint"], "water.footprint", 4, rng=COORD)
    elif basin is not None:
        fp = np.array([basin[0][0], basin[1][0], basin[0][2], basin[1][2]])
    else:
        ctx.fail("water.footprint", "missing required field (no basin to take it from)")
    if fp[1] <= fp[0] or fp[3] <= fp[2]:
        ctx.fail("water.footprint", "zero-size shape: need xmin < xmax and zmin < zmax")
    if "floor" in wdoc:
        wfloor = ctx.number(wdoc["floor"], "water.floor", COORD)
    elif basin is not None:
        wfloor = basin[0][1]
    else:
        ctx.fail("water.floor", "missing required field (no basin to take it from)")
    if wfloor >= level - np.abs(wv[:, 0]).sum():
        ctx.fail("water.floor", "must lie below the lowest point of the water surface")
    wmat = parts.add_material(MAT_DIELECTRIC, 1.0, ior)
    return dict(enabled=True, phase=_PHASES[phase], level=level, waves=wv, fp=fp,
                floor=wfloor, sig_a=sig_a, sig_s=sig_s, g=g, b=b, ior=ior, mat=wmat)
