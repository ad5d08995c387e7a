"""TOML scene files -> `Scene`, with one-line errors naming file, field and problem.

Schema (metres, y up; "spectrum" = a number or a list of C numbers):

  name = "pool"                                    # optional
  [camera]  position, target, up = [0,1,0], fov (vertical, degrees), width, height
  [materials.NAME]  type = "diffuse" | "mirror", albedo = spectrum
  [[shapes]] type = "rect":   center, normal, size = [w, h], up (tangent hint), material
  [[shapes]] type = "sphere": center, radius, material
  [[shapes]] type = "basin":  min = [x0, floor, z0], max = [x1, top, z1],
                              floor_material, wall_material,
                              wall_tops = [top at x0, at x1, at z0, at z1]   (optional)
             (an open box: floor + 4 inward-facing walls, expanded into 5 rectangles)
  [water]   level, waves = [[A, kx, kz, phase], ...], sigma_a, sigma_s (1/m, spectra),
            phase = "isotropic" | "hg" | "water", g (hg), b = 0.835 (water), ior,
            footprint = [xmin, xmax, zmin, zmax], floor   (default: the basin's interior)
  [[lights]] type = "rect":   center, normal (the side it emits to), size, radiance, up
  [[lights]] type = "sphere": center, radius, radiance                (emits both ways)
  [[lights]] type = "sun":    direction (the way light travels), irradiance
  [[lights]] type = "sky":    radiance                   (directions with y > 0 only)
"""

from __future__ import annotations

import math
import os
import tomllib
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._scene import (
    LIGHT_RECT, LIGHT_SKY, LIGHT_SPHERE, LIGHT_SUN, MAT_DIELECTRIC, MAT_DIFFUSE, MAT_MIRROR,
    PHASE_HG, PHASE_ISOTROPIC, PHASE_WATER, Camera, Lights, Materials, Rects, Scene, Spheres,
    Water,
)

CHANNELS = 3


class SceneError(ValueError):
    """A malformed scene file. str() is one line: 'FILE: FIELD: problem'."""


class _Ctx:
    def __init__(self, src: str):
        self.src = src

    def fail(self, field: str, msg: str):
        raise SceneError(f"{self.src}: {field}: {msg}")

    # ---- typed getters ----
    def table(self, d: dict, allowed: set[str], required: set[str], field: str):
        if not isinstance(d, dict):
            self.fail(field, f"expected a table, got {type(d).__name__}")
        for k in d:
            if k not in allowed:
                self.fail(f"{field}.{k}" if field else k,
                          f"unknown key (allowed: {', '.join(sorted(allowed))})")
        for k in sorted(required):
            if k not in d:
                self.fail(f"{field}.{k}" if field else k, "missing required field")

    def number(self, v: Any, field: str, *, positive=False, nonneg=False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(field, f"expected a number, got {type(v).__name__}")
        v = float(v)
        if not math.isfinite(v):
            self.fail(field, f"must be finite, got {v}")
        if positive and not v > 0:
            self.fail(field, f"must be > 0, got {v}")
        if nonneg and v < 0:
            self.fail(field, f"must be >= 0, got {v}")
        return v

    def integer(self, v: Any, field: str, lo: int = 1) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(field, f"expected an integer, got {type(v).__name__}")
        if v < lo:
            self.fail(field, f"must be >= {lo}, got {v}")
        return v

    def vec(self, v: Any, field: str, n: int = 3) -> np.ndarray:
        if not isinstance(v, list) or len(v) != n:
            self.fail(field, f"expected a list of {n} numbers")
        return np.array([self.number(x, f"{field}[{i}]") for i, x in enumerate(v)])

    def spectrum(self, v: Any, field: str, *, positive=False) -> np.ndarray:
        if isinstance(v, list):
            if len(v) != CHANNELS:
                self.fail(field, f"expected a number or a list of {CHANNELS} numbers")
            vals = [self.number(x, f"{field}[{i}]", nonneg=True) for i, x in enumerate(v)]
        else:
            vals = [self.number(v, field, nonneg=True)] * CHANNELS
        a = np.array(vals)
        if positive and not np.any(a > 0):
            self.fail(field, "must be > 0 in some channel")
        return a

    def string(self, v: Any, field: str, choices=None) -> str:
        if not isinstance(v, str):
            self.fail(field, f"expected a string, got {type(v).__name__}")
        if choices is not None and v not in choices:
            self.fail(field, f"unknown value {v!r} (one of: {', '.join(choices)})")
        return v

    def unit(self, v: Any, field: str) -> np.ndarray:
        a = self.vec(v, field)
        n = np.linalg.norm(a)
        if n == 0:
            self.fail(field, "must be a non-zero vector")
        return a / n


def _frame(normal: np.ndarray, hint: np.ndarray | None):
    if hint is None or abs(np.dot(hint / np.linalg.norm(hint), normal)) > 0.999:
        hint = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([0.0, 0.0, -1.0])
    t1 = np.cross(hint, normal)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    return t1, t2


def load_scene(path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
               dtype=jnp.float32) -> Scene:
    """Load and validate a TOML scene file; raises `SceneError` with a one-line message."""
    src = os.fspath(path)
    ctx = _Ctx(src)
    try:
        with open(src, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise SceneError(f"{src}: file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{src}: TOML syntax: {e}") from None
    return scene_from_dict(doc, src, width=width, height=height, dtype=dtype)


def scene_from_dict(doc: dict, src: str = "<scene>", *, width=None, height=None,
                    dtype=jnp.float32) -> Scene:
    ctx = _Ctx(src)
    ctx.table(doc, {"name", "camera", "materials", "shapes", "water", "lights"},
              {"camera", "lights"}, "")
    name = ctx.string(doc.get("name", os.path.splitext(os.path.basename(src))[0]), "name")

    # ---- camera ----
    c = doc["camera"]
    ctx.table(c, {"position", "target", "up", "fov", "width", "height"},
              {"position", "target", "fov", "width", "height"}, "camera")
    pos = ctx.vec(c["position"], "camera.position")
    tgt = ctx.vec(c["target"], "camera.target")
    up = ctx.unit(c.get("up", [0.0, 1.0, 0.0]), "camera.up")
    fov = ctx.number(c["fov"], "camera.fov", positive=True)
    if fov >= 180:
        ctx.fail("camera.fov", f"must be < 180 degrees, got {fov}")
    W = ctx.integer(c["width"] if width is None else width, "camera.width")
    H = ctx.integer(c["height"] if height is None else height, "camera.height")
    fwd = tgt - pos
    if np.linalg.norm(fwd) == 0:
        ctx.fail("camera.target", "must differ from camera.position")
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-6:
        ctx.fail("camera.up", "must not be parallel to the view direction")
    right /= np.linalg.norm(right)
    cup = np.cross(right, fwd)

    # ---- materials ----
    mat_names: list[str] = []
    mat_kind: list[int] = []
    mat_albedo: list[np.ndarray] = []
    mat_ior: list[float] = []
    mats = doc.get("materials", {})
    if not isinstance(mats, dict):
        ctx.fail("materials", "expected a table of named materials")
    for mname, m in mats.items():
        f = f"materials.{mname}"
        ctx.table(m, {"type", "albedo"}, {"type"}, f)
        kind = ctx.string(m["type"], f + ".type", ("diffuse", "mirror"))
        albedo = ctx.spectrum(m.get("albedo", 1.0 if kind == "mirror" else 0.5), f + ".albedo")
        if np.any(albedo > 1):
            ctx.fail(f + ".albedo", "must be <= 1 (energy conservation)")
        mat_names.append(mname)
        mat_kind.append(MAT_DIFFUSE if kind == "diffuse" else MAT_MIRROR)
        mat_albedo.append(albedo)
        mat_ior.append(1.0)

    def add_material(kind, albedo, ior=1.0):
        mat_kind.append(kind)
        mat_albedo.append(np.asarray(albedo, float) * np.ones(CHANNELS))
        mat_ior.append(ior)
        mat_names.append(f"<internal {len(mat_kind)}>")
        return len(mat_kind) - 1

    def mat_ref(v, field):
        s = ctx.string(v, field)
        if s not in mats:
            ctx.fail(field, f"unknown material {s!r}")
        return mat_names.index(s)

    rect_p0, rect_e1, rect_e2, rect_mat, rect_light = [], [], [], [], []
    sph_c, sph_r, sph_mat, sph_light = [], [], [], []
    basin = None

    def add_rect(center, normal, size, hint, mat, light=-1):
        t1, t2 = _frame(normal, hint)
        e1, e2 = t1 * size[0], t2 * size[1]
        rect_p0.append(center - 0.5 * e1 - 0.5 * e2)
        rect_e1.append(e1)
        rect_e2.append(e2)
        rect_mat.append(mat)
        rect_light.append(light)

    def add_rect_corners(p0, e1, e2, mat):
        rect_p0.append(np.asarray(p0, float))
        rect_e1.append(np.asarray(e1, float))
        rect_e2.append(np.asarray(e2, float))
        rect_mat.append(mat)
        rect_light.append(-1)

    # ---- shapes ----
    shapes = doc.get("shapes", [])
    if not isinstance(shapes, list):
        ctx.fail("shapes", "expected an array of tables ([[shapes]])")
    for i, s in enumerate(shapes):
        f = f"shapes[{i}]"
        if not isinstance(s, dict) or "type" not in s:
            ctx.fail(f + ".type", "missing required field")
        kind = ctx.string(s["type"], f + ".type", ("rect", "sphere", "basin"))
        if kind == "rect":
            ctx.table(s, {"type", "center", "normal", "size", "up", "material"},
                      {"center", "normal", "size", "material"}, f)
            size = ctx.vec(s["size"], f + ".size", 2)
            if np.any(size <= 0):
                ctx.fail(f + ".size", "zero-size shape: both sides must be > 0")
            hint = ctx.vec(s["up"], f + ".up") if "up" in s else None
            add_rect(ctx.vec(s["center"], f + ".center"), ctx.unit(s["normal"], f + ".normal"),
                     size, hint, mat_ref(s["material"], f + ".material"))
        elif kind == "sphere":
            ctx.table(s, {"type", "center", "radius", "material"}, {"center", "radius", "material"}, f)
            r = ctx.number(s["radius"], f + ".radius")
            if r <= 0:
                ctx.fail(f + ".radius", "zero-size shape: must be > 0")
            sph_c.append(ctx.vec(s["center"], f + ".center"))
            sph_r.append(r)
            sph_mat.append(mat_ref(s["material"], f + ".material"))
            sph_light.append(-1)
        else:  # basin
            ctx.table(s, {"type", "min", "max", "floor_material", "wall_material", "wall_tops"},
                      {"min", "max", "floor_material", "wall_material"}, f)
            lo = ctx.vec(s["min"], f + ".min")
            hi = ctx.vec(s["max"], f + ".max")
            if np.any(hi <= lo):
                ctx.fail(f + ".max", "zero-size shape: max must exceed min on every axis")
            tops = (ctx.vec(s["wall_tops"], f + ".wall_tops", 4) if "wall_tops" in s
                    else np.full(4, hi[1]))
            if np.any(tops <= lo[1]):
                ctx.fail(f + ".wall_tops", "every wall top must be above the floor")
            fm = mat_ref(s["floor_material"], f + ".floor_material")
            wm = mat_ref(s["wall_material"], f + ".wall_material")
            x0, y0, z0 = lo
            x1, _, z1 = hi
            dx, dz = x1 - x0, z1 - z0
            # e1 x e2 must point into the pool
            add_rect_corners([x0, y0, z0], [0, 0, dz], [dx, 0, 0], fm)  # floor, +y
            add_rect_corners([x0, y0, z0], [0, tops[0] - y0, 0], [0, 0, dz], wm)  # x0 wall, +x
            add_rect_corners([x1, y0, z0], [0, 0, dz], [0, tops[1] - y0, 0], wm)  # x1 wall, -x
            add_rect_corners([x0, y0, z0], [dx, 0, 0], [0, tops[2] - y0, 0], wm)  # z0 wall, +z
            add_rect_corners([x0, y0, z1], [0, tops[3] - y0, 0], [dx, 0, 0], wm)  # z1 wall, -z
            basin = (lo, hi)

    # ---- lights ----
    lights = doc["lights"]
    if not isinstance(lights, list) or not lights:
        ctx.fail("lights", "the scene has no light (add a [[lights]] table)")
    l_kind, l_shape, l_rad, l_dir = [], [], [], []
    for i, l in enumerate(lights):
        f = f"lights[{i}]"
        if not isinstance(l, dict) or "type" not in l:
            ctx.fail(f + ".type", "missing required field")
        kind = ctx.string(l["type"], f + ".type", ("rect", "sphere", "sun", "sky"))
        lid = len(l_kind)
        dvec = np.zeros(3)
        if kind == "rect":
            ctx.table(l, {"type", "center", "normal", "size", "radiance", "up", "albedo"},
                      {"center", "normal", "size", "radiance"}, f)
            size = ctx.vec(l["size"], f + ".size", 2)
            if np.any(size <= 0):
                ctx.fail(f + ".size", "zero-size shape: both sides must be > 0")
            rad = ctx.spectrum(l["radiance"], f + ".radiance", positive=True)
            m = add_material(MAT_DIFFUSE, ctx.spectrum(l.get("albedo", 0.0), f + ".albedo"))
            hint = ctx.vec(l["up"], f + ".up") if "up" in l else None
            add_rect(ctx.vec(l["center"], f + ".center"), ctx.unit(l["normal"], f + ".normal"),
                     size, hint, m, lid)
            l_kind.append(LIGHT_RECT)
            l_shape.append(len(rect_p0) - 1)
        elif kind == "sphere":
            ctx.table(l, {"type", "center", "radius", "radiance", "albedo"},
                      {"center", "radius", "radiance"}, f)
            r = ctx.number(l["radius"], f + ".radius")
            if r <= 0:
                ctx.fail(f + ".radius", "zero-size shape: must be > 0")
            rad = ctx.spectrum(l["radiance"], f + ".radiance", positive=True)
            m = add_material(MAT_DIFFUSE, ctx.spectrum(l.get("albedo", 0.0), f + ".albedo"))
            sph_c.append(ctx.vec(l["center"], f + ".center"))
            sph_r.append(r)
            sph_mat.append(m)
            sph_light.append(lid)
            l_kind.append(LIGHT_SPHERE)
            l_shape.append(len(sph_c) - 1)
        elif kind == "sun":
            ctx.table(l, {"type", "direction", "irradiance"}, {"direction", "irradiance"}, f)
            dvec = ctx.unit(l["direction"], f + ".direction")
            rad = ctx.spectrum(l["irradiance"], f + ".irradiance", positive=True)
            l_kind.append(LIGHT_SUN)
            l_shape.append(-1)
        else:
            ctx.table(l, {"type", "radiance"}, {"radiance"}, f)
            rad = ctx.spectrum(l["radiance"], f + ".radiance", positive=True)
            l_kind.append(LIGHT_SKY)
            l_shape.append(-1)
        l_rad.append(rad)
        l_dir.append(dvec)

    # ---- water ----
    wdoc = doc.get("water")
    if wdoc is not None:
        f = "water"
        ctx.table(wdoc, {"level", "waves", "sigma_a", "sigma_s", "phase", "g", "b", "ior",
                         "footprint", "floor"}, {"level", "sigma_a", "sigma_s", "ior"}, f)
        level = ctx.number(wdoc["level"], "water.level")
        waves = wdoc.get("waves", [])
        if not isinstance(waves, list):
            ctx.fail("water.waves", "expected a list of [A, kx, kz, phase]")
        wv = np.array([ctx.vec(w, f"water.waves[{j}]", 4) for j, w in enumerate(waves)]
                      ).reshape(-1, 4)
        sig_a = ctx.spectrum(wdoc["sigma_a"], "water.sigma_a")
        sig_s = ctx.spectrum(wdoc["sigma_s"], "water.sigma_s")
        phase = ctx.string(wdoc.get("phase", "isotropic"), "water.phase",
                           ("isotropic", "hg", "water"))
        g = ctx.number(wdoc.get("g", 0.0), "water.g")
        if not -1 < g < 1:
            ctx.fail("water.g", f"must lie in (-1, 1), got {g}")
        b = ctx.number(wdoc.get("b", 0.835), "water.b", nonneg=True)
        ior = ctx.number(wdoc["ior"], "water.ior", positive=True)
        if "footprint" in wdoc:
            fp = ctx.vec(wdoc["footprint"], "water.footprint", 4)
        elif basin is not None:
            fp = np.array([basin[0][0], basin[1][0], basin[0][2], basin[1][2]])
        else:
            ctx.fail("water.footprint", "missing required field (no basin to take it from)")
        if fp[1] <= fp[0] or fp[3] <= fp[2]:
            ctx.fail("water.footprint", "zero-size shape: need xmin < xmax and zmin < zmax")
        if "floor" in wdoc:
            wfloor = ctx.number(wdoc["floor"], "water.floor")
        elif basin is not None:
            wfloor = basin[0][1]
        else:
            ctx.fail("water.floor", "missing required field (no basin to take it from)")
        if wfloor >= level - np.abs(wv[:, 0]).sum():
            ctx.fail("water.floor", "must lie below the lowest point of the water surface")
        wmat = add_material(MAT_DIELECTRIC, 1.0, ior)
        water = dict(enabled=True, phase=dict(isotropic=PHASE_ISOTROPIC, hg=PHASE_HG,
                                               water=PHASE_WATER)[phase],
                     level=level, waves=wv, fp=fp, floor=wfloor, sig_a=sig_a, sig_s=sig_s,
                     g=g, b=b, ior=ior, mat=wmat)
    else:
        water = dict(enabled=False, phase=PHASE_ISOTROPIC, level=0.0, waves=np.zeros((0, 4)),
                     fp=np.zeros(4), floor=0.0, sig_a=np.zeros(CHANNELS),
                     sig_s=np.zeros(CHANNELS), g=0.0, b=0.835, ior=1.0, mat=0)

    # ---- bounds and light power ----
    pts = [pos[None]]
    for p0, e1, e2 in zip(rect_p0, rect_e1, rect_e2):
        pts.append(np.array([p0, p0 + e1, p0 + e2, p0 + e1 + e2]))
    for cc, r in zip(sph_c, sph_r):
        pts.append(np.array([cc - r, cc + r]))
    if water["enabled"]:
        fp = water["fp"]
        a = np.abs(water["waves"][:, 0]).sum()
        pts.append(np.array([[fp[0], water["floor"], fp[2]], [fp[1], level + a, fp[3]]]))
    pts = np.concatenate(pts)
    bounds = np.stack([pts.min(0), pts.max(0)])
    rb = 0.5 * np.linalg.norm(bounds[1] - bounds[0])
    power = []
    for k, sh, rad in zip(l_kind, l_shape, l_rad):
        if k == LIGHT_RECT:
            area = np.linalg.norm(np.cross(rect_e1[sh], rect_e2[sh]))
            power.append(rad.mean() * math.pi * area)
        elif k == LIGHT_SPHERE:
            power.append(rad.mean() * math.pi * 4 * math.pi * sph_r[sh] ** 2)
        elif k == LIGHT_SUN:
            power.append(rad.mean() * math.pi * rb * rb)
        else:
            power.append(rad.mean() * math.pi * math.pi * rb * rb)

    A = lambda x: jnp.asarray(np.asarray(x, dtype=np.float64), dtype=dtype)  # noqa: E731
    I = lambda x: jnp.asarray(np.asarray(x, dtype=np.int32))  # noqa: E731

    def arr3(lst):
        return A(np.array(lst).reshape(-1, 3))

    cam = Camera(A(pos), A(fwd), A(right), A(cup), A(math.tan(math.radians(fov) / 2)), W, H)
    materials = Materials(tuple(mat_kind), A(np.array(mat_albedo)), A(mat_ior))
    rects = Rects(arr3(rect_p0), arr3(rect_e1), arr3(rect_e2), I(rect_mat), I(rect_light))
    spheres = Spheres(arr3(sph_c), A(sph_r), I(sph_mat), I(sph_light))
    wv = water["waves"]
    wat = Water(water["enabled"], water["phase"], A(water["level"]), A(wv[:, 0]), A(wv[:, 1]),
                A(wv[:, 2]), A(wv[:, 3]), A(water["fp"]), A(water["floor"]), A(water["sig_a"]),
                A(water["sig_s"]), A(water["g"]), A(water["b"]), A(water["ior"]), water["mat"])
    lts = Lights(tuple(l_kind), tuple(l_shape), A(np.array(l_rad)), arr3(l_dir), A(power))
    return Scene(cam, materials, rects, spheres, wat, lts, A(bounds), name)
