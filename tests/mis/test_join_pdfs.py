"""The renderer's own join pdfs, checked per path against brute force.

Every connection technique (s, t) re-evaluates four pdfs at its join (`_connect.JoinPdfs`:
A_s = A(x_s), A_s1 = A(x_{s+1}), B_s1 = B(x_{s-1}), B_s2 = B(x_{s-2})). The renderer
computes them in one pure per-item function per technique family, which its queued items
and dense families both call: `_connect.emitter_hit_join_pdfs` (s = 0),
`nee_join_pdfs` (s = 1), `light_tracing_join_pdfs` (t = 1), `connection_join_pdfs`
(s, t >= 2). tests/mis/test_mis.py checks the MIS sums when it is *handed* the true join pdfs;
here the join pdfs themselves are checked, on random geometric full paths x_0..x_k in
scenes/pool.toml (area light, diffuse floor and walls, medium vertices in the water,
the delta water surface, distance sampling in the water), scenes/cornell_point.toml
(point light, one-sided diffuse walls, one-sided glossy floor with paths steered into
its Phong lobe, delta spheres) and scenes/pool_sky.toml (a light at infinity: escaped
emitter hits, next-event estimation to the sky, solid-angle pdfs of y_0), and with aimed
emission (`AIMED`): scenes/pool_sun.toml with `aim = 0.9` (a delta light at
infinity), once with the default 1 x 1 map over the footprint and once with a hand-made
[4, 4] map with zero cells over a smaller rectangle, and scenes/pool_sky.toml with
`aim = 0.5`; their paths' first vertex x_1 lies on a line that crosses the water's plane
in (or just beside) the aimed rectangle three times in four, float64:

1. the subpath records are built the renderer's way (`_subpath.Vertex` records of each
   subpath through `_subpath.camera_ends` / `light_ends`, so the kind codes and the
   medium flag come from the renderer), and each family's function is called on them;
2. every pdf it returns equals the value computed here from the geometry alone, with
   NumPy formulas written out below (BSDF / phase pdfs, area conversions, distance
   sampling, the pinhole's pdf, the lights' pdfs, the aimed mixture of a light at
   infinity: the line through x_1, its crossing of the water's plane, the map's cell,
   |d_y|, `infinite_emission_pdf`): no renderer pdf helper is reused for the expected
   values (only the scene's numbers, and for the sky the direction `_lights.sample_light`
   draws, so that next-event estimation meets x_0); the pdfs `_lights.sample_emission`
   stores for y_0 of an aimed light are checked against the same mixture;
3. the MIS weights of all techniques, assembled with the renderer's join pdfs (and
   garbage in the stored join slots of the subpaths), sum to one and equal the exact
   oracle of tests/mis/test_mis.py built from the brute-force full-path pdfs;
4. merging's join lives in `_merge.vertex_merging` (its kernel closure, not a function
   of its own): it is checked end to end, by running the merging stage on one camera and
   one light subpath built the renderer's way with the photon exactly at the camera
   vertex and unit throughputs, recovering each merge's MIS weight from its value, and
   comparing the weights (bpm: the merges dominate the sums) with the exact oracle of
   tests/mis/test_mis.py (`oracle_vcm`), which must sum to one with the emitter hit's;
5. planted mistakes (KIND_MEDIUM equal to MAT_GLOSSY, the cosine dropped at the
   receiving vertex, the BSDF pdf with wo and wi swapped, the water's distance sampling
   with the wrong end, the pinhole pdf with cos^2, the emission pdf of the reversed
   direction, the sky's pdf of the reversed direction; aimed: the emission pdf without
   its aimed part, the aimed density without |d_y|, the map's cells transposed) make
   step 2 fail (the last two also the emission's stored pdf), and two in merging (its
   reverse pdfs with the directions swapped, the surface disk kernel at medium vertices)
   make step 4 fail.

Conventions the expected values follow (`_subpath.to_area`, `dist_pdf`; docs/design/mis.md,
"Conventions the weights rest on"): a pdf of vertex x_b generated from x_a is the solid-angle pdf at x_a
(BSDF / phase function / emission / pinhole) times G = |cos(n_b, w)| / d^2 at a surface
vertex x_b, 1 / d^2 at a medium vertex (no cosine), times the distance-sampling factor of
the segment when it runs through the water: p_scatter(d) = mean_c sigma_s,c
exp(-sigma_s,c d) if x_b is a medium vertex, P_pass(d) = mean_c exp(-sigma_s,c d) if it is
a surface (the light included); 1 after a delta vertex. All pdfs are RR-free (the
roulette is applied by the assembly, `_path.path_pdfs`).
"""

from __future__ import annotations

import collections
import functools
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm import _connect as C
from jaxvcm import _lights as L
from jaxvcm import _subpath as SP
from jaxvcm import _merge
from jaxvcm._mis import ExplicitMIS
from jaxvcm._path import log_n_light_tracing

from .._mis_oracle import Pdfs, pdfs, weight
from jaxvcm._io._scene_file import read_scene_doc, scene_from_dict
from jaxvcm._scene import (LIGHT_POINT, LIGHT_RECT, LIGHT_SKY, LIGHT_SUN, MAT_DIELECTRIC,
                           MAT_DIFFUSE, MAT_GLOSSY, MAT_MIRROR, PHASE_ISOTROPIC)
from jaxvcm._vec import Vec3

from .. import _oracles as O
from .test_mis import oracle, oracle_vcm

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
KMAX = 6  # segments per path
LMAX = KMAX + 1
F64 = jnp.float64
RTOL = 1e-9
# the camera of each scene file, for the pinhole pdf (vertical field of view, degrees)
FOV = {"pool": 42.0, "cornell_point": 45.0, "pool_sky": 42.0}
SCENES = list(FOV)
BOX_AND_POOL = ["pool", "cornell_point"]  # what the planted mistakes run on
# Aimed emission (`_lights.aimed_pdf`): name -> (scene file, the aim of its one
# light, (aim_map, aim_rect) or None for the defaults: a 1 x 1 map over the footprint).
# The hand-made map: [4, 4] cells (rows z, columns x) with zero cells, over a rectangle
# smaller than the footprint [-1, 1]^2 and off its centre, so that the lines through the
# random paths' vertices cross the water's plane outside it, inside it and in zero cells.
AIM_MAP = np.array([[1.0, 0.0, 2.0, 0.5],
                    [0.0, 3.0, 1.0, 0.0],
                    [2.0, 0.7, 0.0, 4.0],
                    [0.5, 0.0, 1.5, 1.0]])
AIM_RECT = np.array([-0.55, 0.45, -0.7, 0.35])  # x0, x1, z0, z1
AIMED = {"pool_sun_aim": ("pool_sun", 0.9, None),
         "pool_sun_aim_map": ("pool_sun", 0.9, (AIM_MAP, AIM_RECT)),
         "pool_sky_aim": ("pool_sky", 0.5, None)}
FOV.update({name: FOV["pool"] for name in AIMED})  # the pool's camera
INF = ("sky", "sun")  # the labels of a light vertex at infinity


@functools.lru_cache(maxsize=None)
def scene_of(name):
    if name in AIMED:
        src, aim, guide = AIMED[name]
        path = os.path.join(ROOT, "scenes", f"{src}.toml")
        doc = read_scene_doc(path)
        doc["lights"][0]["aim"] = aim
        sc = scene_from_dict(doc, path, dtype=F64)
        if guide is not None:
            sc = eqx.tree_at(lambda s: (s.lights.aim_map, s.lights.aim_rect), sc,
                             tuple(jnp.asarray(g, F64) for g in guide))
        return sc
    return jaxvcm.load_scene(os.path.join(ROOT, "scenes", f"{name}.toml"), dtype=F64)


def unit(v):
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------- brute force, NumPy
COVER = collections.Counter()  # what the brute force evaluated (coverage of the checks)


class Vx(dict):
    """A vertex of a full path: position, normal, what it is (the generator's label, not
    the renderer's kind code), and for surfaces the material's numbers."""

    __getattr__ = dict.__getitem__


def pdf_w(sc, v, wo, wi):
    """Solid-angle pdf of sampling wi at vertex v arriving from wo (both unit, pointing
    away from v). Medium: the isotropic phase function 1 / (4 pi). Lambertian: |cos_i| / pi
    on wo's side (one-sided: only in front). Glossy (SmallVCM's): lobe probability
    P_d = mean k_d / (mean k_d + mean k_s); P_d cos_i / pi + (1 - P_d) (n + 1) / (2 pi)
    cos^n(alpha), alpha between wi and the mirror direction of wo, on wo's side."""
    if v.what == "medium":
        assert sc.water.phase_kind == PHASE_ISOTROPIC
        COVER["medium"] += 1
        return 1.0 / (4.0 * np.pi)
    assert v.what == "surface" and v.mkind in (MAT_DIFFUSE, MAT_GLOSSY), v
    co, ci = float(np.dot(wo, v.n)), float(np.dot(wi, v.n))
    if co * ci <= 0 or (v.one_sided and co <= 0):
        return 0.0
    if v.mkind == MAT_DIFFUSE:
        return abs(ci) / np.pi
    ns = v.n * np.sign(co)
    r = 2.0 * np.dot(wo, ns) * ns - wo
    ca = max(float(np.dot(r, wi)), 0.0)
    kd, ks, e = np.mean(v.kd), np.mean(v.ks), v.exponent
    p_d = kd / (kd + ks)
    COVER["glossy"] += 1
    COVER["phong lobe"] += (1.0 - p_d) * (e + 1.0) / (2.0 * np.pi) * ca**e > p_d * abs(ci) / np.pi
    return p_d * abs(ci) / np.pi + (1.0 - p_d) * (e + 1.0) / (2.0 * np.pi) * ca**e


def area(sc, pw, a, b, water):
    """Solid-angle pdf pw at vertex a of the direction to vertex b -> b's area (volume)
    measure: |cos_b| / d^2 (1 / d^2 at a medium vertex), times the distance sampling of a
    segment through the water (p_scatter ending in the medium, P_pass on a surface)."""
    dv = b.p - a.p
    d = np.linalg.norm(dv)
    g = 1.0 if b.what == "medium" else abs(float(np.dot(b.n, dv / d)))
    f = 1.0
    if water:
        ss = np.asarray(sc.water.sigma_s, float)
        f = np.mean(ss * np.exp(-ss * d)) if b.what == "medium" else np.mean(np.exp(-ss * d))
    return pw * g / d**2 * f


def pinhole_pdf(sc, name, w):
    """Solid-angle pdf of the pinhole's direction w: 1 / (A_pix cos^3), A_pix the pixel's
    area on the image plane at distance 1 (2 tan(fov/2) aspect / W by 2 tan(fov/2) / H);
    0 off the film."""
    cam = sc.camera
    f, r, u = (np.asarray(x, float) for x in (cam.forward, cam.right, cam.up))
    th = np.tan(np.radians(FOV[name] / 2.0))
    aspect = cam.width / cam.height
    c = float(np.dot(w, f))
    if c <= 0:
        return 0.0
    sx, sy = np.dot(w, r) / c, np.dot(w, u) / c
    if abs(sx) >= aspect * th or abs(sy) >= th:
        return 0.0
    return 1.0 / ((2.0 * th * aspect / cam.width) * (2.0 * th / cam.height) * c**3)


def aimed_density(sc, d, p):
    """The aimed part of an infinite light's emission per unit area
    perpendicular to d, for the line of direction d through p (NumPy, from the scene's
    numbers alone): the line crosses the water's plane y = level at c; if c lies in the
    rectangle [x0, x1) x [z0, z1) of `aim_rect`, in cell (i, j) of the [G, G] `aim_map`
    (rows i along z, columns j along x), the aimed photons cross the plane there with
    density G^2 w_ij / (sum w (x1 - x0)(z1 - z0)) per unit plane area, which is
    1 / |d_y| times as dense per unit perpendicular area; 0 outside the rectangle."""
    if abs(d[1]) < 1e-12:
        return 0.0
    c = p + d * ((float(sc.water.level) - p[1]) / d[1])
    x0, x1, z0, z1 = np.asarray(sc.lights.aim_rect, float)
    if not (x0 <= c[0] < x1 and z0 <= c[2] < z1):
        COVER["aim outside"] += 1
        return 0.0
    w = np.asarray(sc.lights.aim_map, float)
    G = w.shape[0]
    i = min(int((c[2] - z0) / (z1 - z0) * G), G - 1)
    j = min(int((c[0] - x0) / (x1 - x0) * G), G - 1)
    COVER["aim zero cell" if w[i, j] == 0 else "aim inside"] += 1
    return G * G * w[i, j] / (w.sum() * (x1 - x0) * (z1 - z0) * abs(d[1]))


def infinite_emission_pdf(sc, d, p):
    """Per perpendicular area, the pdf of the line of direction d through p that a light
    at infinity emits along: 1 / (pi R^2) on the disk of the scene's bounding radius R
    (centred on the line through the bounding sphere's centre), for an aimed light (aim P)
    the mixture (1 - P) / (pi R^2) + P `aimed_density`."""
    lo, hi = (np.asarray(x, float) for x in sc.bounds)
    R = 0.5 * np.linalg.norm(hi - lo)
    aim = sc.lights.aim
    P = float(aim[0]) if len(aim) else 0.0
    disk = 1.0 / (np.pi * R * R)
    return disk if P == 0 else (1.0 - P) * disk + P * aimed_density(sc, d, p)


def light_pdfs(sc, x0, w, x1):
    """(A(y_0), emission pdf of direction w leaving y_0 towards x1) of the scene's one
    light: a rectangle (1 / area; cos / pi about its normal), a point (delta: the selection
    probability 1; uniform 1 / (4 pi)), the sky (y_0 the direction x0.dir to the sky,
    cosine-distributed about +y: cos / pi) or the sun (delta: the selection probability
    1); from the sky or the sun the ray's line through x1 (`infinite_emission_pdf`: the
    bounding disk's 1 / (pi R^2) per perpendicular area, mixed with the aimed density)."""
    assert len(sc.lights.kind) == 1
    if sc.lights.kind[0] in (LIGHT_SKY, LIGHT_SUN):
        pe = infinite_emission_pdf(sc, -x0.dir, x1.p)
        if sc.lights.kind[0] == LIGHT_SUN:
            return 1.0, pe
        return max(x0.dir[1], 0.0) / np.pi, pe
    if sc.lights.kind[0] == LIGHT_RECT:
        i = sc.lights.shape[0]
        A = np.linalg.norm(np.cross(np.asarray(sc.rects.e1[i]), np.asarray(sc.rects.e2[i])))
        return 1.0 / A, max(float(np.dot(x0.n, w)), 0.0) / np.pi
    assert sc.lights.kind[0] == LIGHT_POINT
    return 1.0, 1.0 / (4.0 * np.pi)


def height(w, x, z):
    """The water surface's height and its gradient (dh/dx, dh/dz) at (x, z) (NumPy)."""
    return O.heightfield(O.waves_of(w), float(w.level), x, z)


def in_water(sc, p):
    """The water body (NumPy): inside the footprint, above the floor, below the surface."""
    w = sc.water
    if not w.enabled:
        return False
    fp = np.asarray(w.footprint, float)
    h = height(w, p[0], p[2])[0]
    return bool(fp[0] < p[0] < fp[1] and fp[2] < p[2] < fp[3] and float(w.floor) < p[1] < h)


def full_path_pdfs(sc, name, X, water):
    """Brute-force A_i, B_i (RR-free) of the full path X[0..k] (X[0] on the light, X[k] the
    pinhole); water[i]: segment x_i - x_{i+1} runs through the water."""
    k = len(X) - 1
    A, B = [0.0] * (k + 1), [0.0] * (k + 1)
    A[0], pe = light_pdfs(sc, X[0], unit(X[1].p - X[0].p), X[1])
    A[1] = area(sc, pe, X[0], X[1], water[0])
    for i in range(2, k + 1):
        a = X[i - 1]
        A[i] = 1.0 if a.delta else area(sc, pdf_w(sc, a, unit(X[i - 2].p - a.p),
                                                  unit(X[i].p - a.p)), a, X[i], water[i - 1])
    B[k] = 1.0
    B[k - 1] = area(sc, pinhole_pdf(sc, name, unit(X[k - 1].p - X[k].p)), X[k], X[k - 1],
                    water[k - 1])
    for i in range(k - 2, -1, -1):
        b = X[i + 1]
        B[i] = 1.0 if b.delta else area(sc, pdf_w(sc, b, unit(X[i + 2].p - b.p),
                                                  unit(X[i].p - b.p)), b, X[i], water[i])
    if X[0].what in INF:  # y_0 at infinity: per perpendicular area / solid angle
        w, x1 = X[0].dir, X[1]
        A[1] = pe * (1.0 if x1.what == "medium" else abs(float(np.dot(x1.n, w))))
        if k == 1:  # the pinhole sees the sky
            B[0] = pinhole_pdf(sc, name, w)
        else:  # x_1 samples the sky's direction: a solid-angle pdf
            B[0] = 1.0 if x1.delta else pdf_w(sc, x1, unit(X[2].p - x1.p), w)
    return A, B


# ---------------------------------------------------------------- random geometric paths
def _surfaces(sc):
    """(p0, e1, e2, normal, material) of every rectangle that is not a light."""
    r = sc.rects
    out = []
    for i in range(r.count):
        if int(r.light[i]) >= 0:
            continue
        p0, e1, e2 = (np.asarray(x[i], float) for x in (r.p0, r.e1, r.e2))
        out.append((p0, e1, e2, unit(np.cross(e1, e2)), int(r.mat[i])))
    return out


def _surface_vertex(sc, p, n, mat):
    m = sc.materials
    one_sided = bool(m.one_sided[mat]) if m.one_sided else False
    return Vx(p=p, n=n, what="surface", mkind=m.kind[mat], mat=mat, delta=m.kind[mat]
              in (MAT_DIELECTRIC, MAT_MIRROR), one_sided=one_sided,
              kd=np.asarray(m.albedo[mat], float), ks=np.asarray(m.glossy[mat], float),
              exponent=float(m.exponent[mat]))


def _hit_rects(sc, o, d):
    """The closest non-light rectangle hit by the ray o + t d (None: none)."""
    best = None
    for p0, e1, e2, n, mat in _surfaces(sc):
        den = np.dot(d, n)
        if abs(den) < 1e-12:
            continue
        t = np.dot(p0 - o, n) / den
        if t <= 1e-6 or (best is not None and t >= best[0]):
            continue
        q = o + t * d - p0
        u, v = np.dot(q, e1) / np.dot(e1, e1), np.dot(q, e2) / np.dot(e2, e2)
        if 0 <= u <= 1 and 0 <= v <= 1:
            best = (t, o + t * d, n, mat)
    return best


def _interior_vertex(sc, rng, prev, prev2):
    """A random interior vertex: on a rectangle (diffuse or glossy), in the water (medium),
    on the water surface or a sphere (delta). After a glossy vertex, half of the time the
    next vertex is where a direction close to the mirror direction meets the box (so that
    the Phong lobe's pdf is not ~0)."""
    if (prev2 is not None and prev.what == "surface" and prev.mkind == MAT_GLOSSY
            and rng.uniform() < 0.5):
        wo = unit(prev2.p - prev.p)
        ns = prev.n * np.sign(np.dot(wo, prev.n))
        r = 2.0 * np.dot(wo, ns) * ns - wo
        d = unit(r + rng.normal(size=3) * 0.08)
        hit = _hit_rects(sc, prev.p + 1e-9 * ns, d)
        if hit is not None:
            return _surface_vertex(sc, hit[1], hit[2], hit[3])
    w = sc.water
    choices = ["rect"] * 3 + (["medium", "medium", "water_surface"] if w.enabled else [])
    choices += ["sphere"] * (sc.spheres.count > 0)
    c = choices[rng.integers(len(choices))]
    if c == "rect":
        rects = _surfaces(sc)
        p0, e1, e2, n, mat = rects[rng.integers(len(rects))]
        p = p0 + rng.uniform(0.02, 0.98) * e1 + rng.uniform(0.02, 0.98) * e2
        return _surface_vertex(sc, p, n, mat)
    if c == "sphere":
        i = rng.integers(sc.spheres.count)
        n = unit(rng.normal(size=3))
        p = np.asarray(sc.spheres.center[i], float) + float(sc.spheres.radius[i]) * n
        return _surface_vertex(sc, p, n, int(sc.spheres.mat[i]))
    x, z = rng.uniform(-0.95, 0.95, 2)
    h, hx, hz = height(w, x, z)
    if c == "medium":  # the record's normal is whatever the ray would have hit: random
        return Vx(p=np.array([x, rng.uniform(float(w.floor) + 0.05, h - 0.05), z]),
                  n=unit(rng.normal(size=3)), what="medium", delta=False)
    return Vx(p=np.array([x, h, z]), n=unit(np.array([-hx, 1.0, -hz])), what="surface",
              mkind=MAT_DIELECTRIC, mat=w.mat, delta=True)


def aimed(sc):
    return len(sc.lights.aim) > 0 and float(sc.lights.aim[0]) > 0


def _aimed_vertex(sc, rng, d):
    """For an aimed light, a vertex x_1 on a line of the light's direction d
    (the way light travels) that crosses the water's plane at a point c drawn uniformly
    over `aim_rect` widened by 15 % on each side: where the line meets the basin from
    above the footprint (a surface vertex), or a point of the line in the water (a medium
    vertex; also for lines that cross the plane beside the pool and enter the water through
    a wall's plane). So the lines through x_1 cross the plane inside the rectangle (in zero
    cells of a map too) and just outside it. None where there is no such vertex."""
    x0, x1, z0, z1 = np.asarray(sc.lights.aim_rect, float)
    mx, mz = 0.15 * (x1 - x0), 0.15 * (z1 - z0)
    level = float(sc.water.level)
    c = np.array([rng.uniform(x0 - mx, x1 + mx), level, rng.uniform(z0 - mz, z1 + mz)])
    if rng.uniform() < 0.5:
        fx0, fx1, fz0, fz1 = np.asarray(sc.water.footprint, float)
        hit = _hit_rects(sc, c, d)
        if hit is None or not (fx0 < c[0] < fx1 and fz0 < c[2] < fz1):
            return None
        return _surface_vertex(sc, hit[1], hit[2], hit[3])
    p = c + d * (rng.uniform(float(sc.water.floor), level) - level) / d[1]
    if not in_water(sc, p):
        return None
    return Vx(p=p, n=unit(rng.normal(size=3)), what="medium", delta=False)


def random_path(sc, name, rng, k):
    """x_0 on the light (rectangle: at uniforms (u1, u2), returned for next-event
    estimation to sample the same point; sky: the direction next-event estimation samples
    from x_1 at (u1, u2); sun: its direction), k - 1 interior vertices (for an aimed light
    x_1 three times in four on a line through its rectangle, `_aimed_vertex`), x_k the
    pinhole; the vertex before the pinhole is redrawn until the film sees it. Returns (X,
    water flags per segment, (u1, u2))."""
    u12 = rng.uniform(0.02, 0.98, 2)
    if sc.lights.kind[0] == LIGHT_RECT:
        i = sc.lights.shape[0]
        p0, e1, e2 = (np.asarray(x[i], float) for x in (sc.rects.p0, sc.rects.e1, sc.rects.e2))
        mat = int(sc.rects.mat[i])  # what a camera subpath's record of the light holds
        x0 = Vx(p=p0 + u12[0] * e1 + u12[1] * e2, n=unit(np.cross(e1, e2)), what="light",
                delta=False, mat=mat, mkind=sc.materials.kind[mat])
    elif sc.lights.kind[0] == LIGHT_POINT:  # its record's normal: the emission direction
        x0 = Vx(p=np.asarray(sc.lights.position[0], float), n=None, what="light", delta=False)
    else:
        assert sc.lights.kind[0] in (LIGHT_SKY, LIGHT_SUN)
        x0 = Vx(p=None, n=None, what="sky" if sc.lights.kind[0] == LIGHT_SKY else "sun",
                delta=False, mat=0, mkind=-1)  # set below
    cam = Vx(p=np.asarray(sc.camera.origin, float), n=np.asarray(sc.camera.forward, float),
             what="camera", delta=False)
    if x0.what in INF:  # the direction next-event estimation samples at u12 (the sun's:
        # its own), from any point: the sky's is cosine-distributed about +y wherever
        ls = L.sample_light(sc, Vec3(*(jnp.asarray(c, F64) for c in cam.p)),
                            jnp.asarray(0.5, F64), jnp.asarray(u12[0], F64),
                            jnp.asarray(u12[1], F64))
        x0["dir"] = np.array([float(c) for c in ls.wi])
    X = [x0]
    for i in range(1, k):
        for _ in range(50):
            v = None
            if i == 1 and aimed(sc) and rng.uniform() < 0.75:
                v = _aimed_vertex(sc, rng, -x0.dir)
            if v is None:
                v = _interior_vertex(sc, rng, X[-1], X[-2] if i >= 2 else None)
            coplanar = (v.what == X[-1].what == "surface"
                        and abs(np.dot(v.p - X[-1].p, v.n)) < 1e-9)  # a 0 pdf both ways
            if not coplanar and (i < k - 1 or pinhole_pdf(sc, name, unit(v.p - cam.p)) > 0):
                break
        X.append(v)
    X.append(cam)
    if x0.what in INF:
        w = x0.dir
        lo, hi = (np.asarray(x, float) for x in sc.bounds)
        # y_0's record: a point on the emission disk outside the bounding sphere, on the
        # ray that reaches x_1; its normal the direction to the sky
        x0.update(dir=w, p=X[1].p + 1.01 * np.linalg.norm(hi - lo) * w, n=w)
    if x0.n is None:
        x0["n"] = unit(X[1].p - x0.p)
    water = [in_water(sc, 0.5 * (X[i].p + X[i + 1].p)) for i in range(k)]
    if x0.what in INF:
        water[0] = False  # the light's first ray starts outside the scene
    return X, water, u12


# ---------------------------------------------------------------- the renderer's records
def _records(sc, seq, seg, fwd=None, rev=None, q=None, rows=None):
    """One subpath's `_subpath.Vertex` records [M, 1] for the vertices seq[1..], as the
    tracer writes them: the kind code (`_subpath.KIND_MEDIUM` in the water), the material,
    the direction back to the previous vertex, the water of the arriving segment (and,
    where given, the stored pdfs and local roulette q); padded with dead records to `rows`."""
    live = seq[1:]
    n_live = len(live)
    M = rows or n_live
    rows = live + [live[-1]] * (M - n_live)
    seg = list(seg) + [False] * (M - n_live)
    pad = lambda v: [1.0] * M if v is None else list(v) + [1.0] * (M - n_live)  # noqa: E731

    def a(vals, dt=F64):
        return jnp.asarray(np.asarray(vals).reshape(M, 1), dt)

    def v3(vs):
        return Vec3(*(a([x[c] for x in vs]) for c in range(3)))

    kind = [SP.KIND_MEDIUM if v.what == "medium" else v.get("mkind", -1) for v in rows]
    f = a([False] * M, bool)
    Cn = sc.channels
    beta = jnp.ones((M, 1, Cn), F64)
    wo = [unit(seq[i].p - seq[i + 1].p) for i in range(n_live)]
    # an escaped camera vertex (the sky) records the direction to the sky as its position
    return SP.Vertex(v3([v.dir if v.what in INF else v.p for v in rows]),
                     v3([v.n for v in rows]),
                     v3(wo + [wo[-1]] * (M - n_live)), beta, a(pad(fwd)), a(pad(rev)),
                     a(kind, jnp.int32), a([v.get("mat", 0) for v in rows], jnp.int32),
                     a([-1] * M, jnp.int32), jnp.zeros((M, 1, Cn), F64), a(pad(q)), a(seg, bool),
                     a([v.delta for v in rows], bool), f, a([i < n_live for i in range(M)], bool),
                     f)


def subpath_ends(sc, X, water, s):
    """(light PathEnds of y_0..y_{s-1} = x_0..x_{s-1}, camera PathEnds of z_0..z_{t-1} =
    x_k..x_s), built by `_subpath.light_ends` / `camera_ends` from the records."""
    k = len(X) - 1
    t = k + 1 - s
    lig = None
    if s >= 1:
        e = emission(sc, X, 1.0)
        seq = X[:s]
        if s >= 2:
            verts = _records(sc, seq, water[:s - 1])
        else:  # y_0 alone: one dummy record, dropped below
            verts = _records(sc, X[:2], water[:1])
        lig = SP.light_ends(sc, e, jnp.ones((1,), F64), verts, 1)
        lig = jax.tree.map(lambda a: a[:s], lig)
    cam = None
    if t >= 1:
        seq = X[::-1][:max(t, 2)]
        verts = _records(sc, seq, water[::-1][:max(t, 2) - 1])
        cam = SP.camera_ends(sc, Vec3(*(jnp.asarray([c], F64) for c in X[k].p)), verts, 1)
        cam = jax.tree.map(lambda a: a[:t], cam)
    return lig, cam


def emission(sc, X, pdf_pos):
    """y_0's `_lights.Emission` (one lane) for the light vertex X[0], emitting towards X[1]."""
    x0 = X[0]
    return L.Emission(*(Vec3(*(jnp.asarray([c], F64) for c in v)) for v in
                        (x0.p, x0.n, x0.p, unit(X[1].p - x0.p))),
                      jnp.ones((1, sc.channels), F64), jnp.ones((1, sc.channels), F64),
                      jnp.asarray([pdf_pos], F64), jnp.ones((1,), F64), jnp.zeros((1,), jnp.int32),
                      jnp.asarray([x0.what in INF]),
                      jnp.asarray([sc.lights.kind[0] in (LIGHT_POINT, LIGHT_SUN)]))


def vertex(ends, i):
    return SP.vertex_table(ends)(i, 0)


# ---------------------------------------------------------------- the renderer's functions
class Renderer:
    """The four join-pdf functions of `_connect` and the merging stage, looked up when a
    `Renderer` is made (a planted mistake patches them before) and traced afresh: jitted
    (one program per scene), or the join pdfs run op by op (`jit=False`: a planted mistake
    fails on its first path or two, cheaper than compiling)."""

    def __init__(self, jit=True):
        jit_ = jax.jit if jit else (lambda f: f)
        self.emitter = jit_(lambda sc, *a: C.emitter_hit_join_pdfs(sc, *a))
        self.nee = jit_(lambda sc, z, zp, u, wseg: C.nee_join_pdfs(
            sc, z, zp, L.sample_light(sc, z.p, jnp.asarray(0.5, F64), u[0], u[1]), wseg))
        self.lt = jit_(lambda sc, *a: C.light_tracing_join_pdfs(sc, *a))
        self.conn = jit_(lambda sc, *a: C.connection_join_pdfs(sc, *a))
        self.merge = jax.jit(lambda *a: _merges(*a))  # a new function: traced anew


MERGE_RADIUS = 0.25  # large: with N = 1 light path the merges must weigh (eta = pi r^2 N)


def _merges(sc, cam, lig, e):
    """bpm / vcm's merging stage (`_merge.vertex_merging`) on one camera lane and one light
    lane, with both subpaths' partials as the integrator builds them: [D-1, 1, D-1, C] per
    gather vertex z_j and photon y_i (`by_photon`), and the overflow flag."""
    r = jnp.asarray(MERGE_RADIUS, F64)
    radius = _merge.Radii(r, r)
    etas = _merge.log_etas(radius, 1, F64)
    log_n = log_n_light_tracing(CFG_MERGE, 1, F64)
    parts = ExplicitMIS().subpaths(CFG_MERGE, pdfs(lig), pdfs(cam), e.delta, log_n, etas)
    out = _merge.vertex_merging(sc, CFG_MERGE, cam, lig, e, radius, parts, by_photon=True)
    # (est, overflow, need) or (est, `_merge.Merged` report): _merge.py is being changed
    overflow = out[1].overflow if hasattr(out[1], "overflow") else out[1]
    return out[0], overflow


_weight = jax.jit(weight, static_argnums=(0,))
CFG = RenderConfig(algorithm="bdpt", max_depth=KMAX, rr_depth=2, mis="power")
# merging: bpm (emitter hits and merges at every vertex), so that the merges dominate the
# MIS sums and a wrong pdf in merging's join moves their weights by O(1) (under vcm, with
# one light path, the connections dominate and the merge weights are ~1e-6: a wrong join
# pdf there moved them by 2e-8 relative); the merge code is the same for both
CFG_MERGE = RenderConfig(algorithm="bpm", max_depth=KMAX, rr_depth=2, mis="power")


def _close(what, got, want):
    got, want = float(got), float(want)
    assert np.isfinite(got) and abs(got - want) <= RTOL * abs(want) + 1e-300, (
        f"join pdf {what}: renderer {got!r}, brute force {want!r}")


def check_path(name, seed, k, R: Renderer, merging=False):
    """Steps 1-3 of the module doc on one random path; returns the number of join pdfs
    compared per family (non-trivially: the brute-force value is not 0). `merging`: the
    weights are bpm's, the merges' from `_merge.vertex_merging` (`merge_weight`)."""
    sc = scene_of(name)
    rng = np.random.default_rng(seed)
    X, water, u12 = random_path(sc, name, rng, k)
    A, B = full_path_pdfs(sc, name, X, water)
    delta = [v.delta for v in X]
    delta_light = sc.lights.kind[0] in (LIGHT_POINT, LIGHT_SUN)
    infinite = X[0].what in INF
    b = jnp.asarray
    checked = collections.Counter()  # family -> join pdfs compared that are not 0
    fam = None

    def cmp(what, got, want):
        _close(what, got, want)
        checked[fam] += want != 0

    cfg = CFG_MERGE if merging else CFG
    med = [v.what == "medium" for v in X]
    # merging: the kernels' size times N = 1 (surface disk, medium sphere), eta_VCM
    r = MERGE_RADIUS
    eta = [4.0 / 3.0 * np.pi * r**3 if m else np.pi * r**2 for m in med]
    log_eta = (np.log(np.pi * r**2), np.log(4.0 / 3.0 * np.pi * r**3)) if merging else (0, 0)
    q = [SP.Q_SPECULAR if v.what == "medium" or v.delta else
         float(np.clip(np.max(v.kd + v.ks), 0.05, 0.95)) if v.what == "surface" else 1.0
         for v in X]
    ws = []
    for s in range(0, k + 2):
        t = k + 1 - s
        # a valid technique: its join vertices are not delta (`_connect`'s queue masks)
        valid = t >= 1 and not (s >= 1 and delta[s - 1]) and not (t >= 1 and delta[s])
        valid = valid and not (s == 0 and delta_light)
        valid = valid and not (s == 1 and t == 1 and infinite)  # no splat of the sky itself
        if not valid:
            ws.append(0.0)
            continue
        lig, cam = subpath_ends(sc, X, water, s)
        tag = f"{name} seed {seed} k {k} (s, t) = ({s}, {t})"
        fam = ("emitter hit" if s == 0 else "nee" if s == 1 and t >= 2 else
               "light tracing" if t == 1 else "connection")
        if s == 0:  # the camera subpath hits the light at z_k = x_0
            jp = R.emitter(sc, vertex(cam, t - 1), vertex(cam, t - 2), b(0), b(infinite))
        elif s == 1 and t >= 2:  # next-event estimation from z_{t-1} = x_1 samples x_0
            z, zp = vertex(cam, t - 1), vertex(cam, t - 2)
            A0, jp = R.nee(sc, z, zp, b(u12, F64), b(water[0]))
            ls = L.sample_light(sc, z.p, b(0.5, F64), b(u12[0], F64), b(u12[1], F64))
            assert bool(ls.valid) and np.allclose([float(c) for c in ls.wi],
                                                  unit(X[0].p - X[1].p), atol=1e-12), tag
            cmp(f"A(y_0) {tag}", A0, A[0])
        elif t == 1:  # light tracing from y_{s-1} = x_{k-1}
            y, yp = vertex(lig, s - 1), vertex(lig, max(s - 2, 0))
            dv = X[k - 1].p - X[k].p
            jp = R.lt(sc, y, yp, Vec3(*(b(c) for c in unit(dv))), b(np.linalg.norm(dv)),
                      b(water[k - 1]), b(s == 2 and infinite))  # as `_connect` passes it
        else:  # z_{t-1} = x_s joined to y_{s-1} = x_{s-1}
            y, yp = vertex(lig, s - 1), vertex(lig, s - 2)
            z, zp = vertex(cam, t - 1), vertex(cam, t - 2)
            dv = X[s - 1].p - X[s].p
            jp = R.conn(sc, y, yp, z, zp, Vec3(*(b(c) for c in unit(dv))),
                        b(np.linalg.norm(dv)), b(water[s - 1]), b(s == 2 and infinite))
        A_s, A_s1, B_s1, B_s2 = (float(x) for x in jp)
        # ---- step 2: the join pdfs the technique reads, against brute force ----
        # Which full-path pdf each one is (y_i = x_i, z_j = x_{k-j}; G = |cos| / d^2 at the
        # receiving vertex, 1 / d^2 at a medium vertex, times the water's distance sampling
        # of the segment, `area`; from / to a light at infinity per perpendicular area /
        # solid angle, `full_path_pdfs`):
        #   A_s  = A(x_s): s = 0 the light's pdf of the point the camera path hit; s = 1
        #          the light's emission pdf towards x_1, times G at x_1; s >= 2 y_{s-1}'s
        #          pdf of scattering from x_{s-2} towards x_s, times G at x_s;
        #   A_s1 = A(x_{s+1}), read iff t >= 3: z_{t-1} = x_s scattering the light that
        #          arrives from x_{s-1} towards x_{s+1}, times G at x_{s+1};
        #   B_s1 = B(x_{s-1}): t = 1 the pinhole's pdf of the direction to x_{k-1}, times
        #          G there; else z_{t-1} = x_s scattering from x_{s+1} towards x_{s-1},
        #          times G at x_{s-1};
        #   B_s2 = B(x_{s-2}), read iff s >= 2: y_{s-1} = x_{s-1} scattering from x_s
        #          towards x_{s-2}, times G at x_{s-2}.
        if s < k + 1 and t >= 2:
            cmp(f"A_s {tag}", A_s, A[s])
        if t >= 3:
            cmp(f"A_s1 {tag}", A_s1, A[s + 1])
        if s >= 1:
            cmp(f"B_s1 {tag}", B_s1, B[s - 1])
        if s >= 2:
            cmp(f"B_s2 {tag}", B_s2, B[s - 2])
        # ---- step 3: the technique's weight from these pdfs, garbage in the join slots ----
        pad = lambda v: jnp.asarray(list(v) + [1.0] * (LMAX - len(v)), F64)  # noqa: E731
        padb = lambda v: jnp.asarray(list(v) + [False] * (LMAX - len(v)))  # noqa: E731
        lP = Pdfs(pad([A[i] for i in range(s)]),
                  pad([B[i] if i < s - 2 else 7.0 for i in range(s)]),
                  pad([q[i] for i in range(s)]), padb([delta[i] for i in range(s)]),
                  padb([med[i] for i in range(s)]))
        cP = Pdfs(pad([A[k - j] if j < t - 2 else 7.0 for j in range(t)]),
                  pad([B[k - j] for j in range(t)]), pad([q[k - j] for j in range(t)]),
                  padb([delta[k - j] for j in range(t)]), padb([med[k - j] for j in range(t)]))
        w = _weight(cfg, jnp.int32(s), jnp.int32(t), lP, cP, b(A_s, F64), b(A_s1, F64),
                    b(B_s1, F64), b(B_s2, F64), b(delta_light), b(infinite),
                    jnp.log(jnp.asarray(1.0, F64)), b(log_eta[0], F64), b(log_eta[1], F64))
        ws.append(float(w))

    def rr(index, qq):
        return 1.0 if index < CFG.rr_depth else qq

    a_true = [A[i] * (rr(i - 1, q[i - 1]) if i >= 1 else 1.0) for i in range(k + 1)]
    b_true = [B[i] * (rr(k - i - 1, q[i + 1]) if i < k else 1.0) for i in range(k + 1)]
    if merging:
        ref, ref_vm = oracle_vcm(a_true, b_true, delta, k, delta_light, infinite, 1, eta, "bpm", 2)
        vm = [merge_weight(sc, R, X, water, A, B, q, s) if 1 <= s <= k - 1 and not delta[s]
              else 0.0 for s in range(k + 1)]
        # a merge whose path carries nothing (f_z = 0: the photon arrives on the other side
        # of z's surface) shows no weight: it takes the oracle's
        vm = [ref_vm[s] if w is None else w for s, w in enumerate(vm)]
        # (merge weights are small with one light path: compared relative to themselves)
        np.testing.assert_allclose(vm, ref_vm, rtol=1e-9, atol=1e-300,
                                   err_msg=f"merge weight {name} seed {seed} k {k}")
    else:
        ref, vm = oracle(a_true, b_true, delta, k, delta_light, infinite, 1, "bdpt", 2), []
    np.testing.assert_allclose(ws, ref, rtol=1e-9, atol=1e-12)
    if sum(ref) + sum(vm) > 0:
        assert abs(sum(ws) + sum(vm) - 1.0) < 1e-10, (ws, vm)
    return checked


def f_merge(sc, z, wo, wi):
    """Channel 0 of what merging at z multiplies the photon by: the BSDF without its cosine
    on surfaces (Lambertian k_d / pi, glossy k_d / pi + k_s (n + 2) / (2 pi) cos^n(alpha)),
    the phase function over sigma_s in the medium (one scattering event, `_merge`)."""
    if z.what == "medium":
        return 1.0 / (4.0 * np.pi) / float(sc.water.sigma_s[0])
    co, ci = float(np.dot(wo, z.n)), float(np.dot(wi, z.n))
    if co * ci <= 0 or (z.one_sided and co <= 0):
        return 0.0
    f = z.kd[0] / np.pi
    if z.mkind == MAT_GLOSSY:
        ns = z.n * np.sign(co)
        ca = max(float(np.dot(2.0 * np.dot(wo, ns) * ns - wo, wi)), 0.0)
        f += z.ks[0] * (z.exponent + 2.0) / (2.0 * np.pi) * ca**z.exponent
    return f


def merge_weight(sc, R, X, water, A, B, q, s):
    """The MIS weight `_merge.vertex_merging` gives merging at x_s: the light subpath
    y_0..y_s (the photon y_s at x_s, arriving from x_{s-1}) and the camera subpath
    z_0..z_{t-1} = x_k..x_s, built the renderer's way with their stored pdfs (garbage in
    the join slots: B of y_{s-1}, y_s; A of z_{t-1}, z_{t-2}); unit throughputs, so the
    merged value is f_z w / (kernel N) with N = 1 and the weight is recovered from it
    (None where f_z = 0: the value is 0 whatever the weight)."""
    k = len(X) - 1
    t = k + 1 - s
    G = 7.0
    lv = _records(sc, X[:s + 1], water[:s], fwd=A[1:s + 1],
                  rev=[B[i] if i < s - 1 else G for i in range(1, s + 1)], q=q[1:s + 1],
                  rows=KMAX - 1)
    e = emission(sc, X, A[0])
    lig = SP.light_ends(sc, e, jnp.asarray([B[0] if s >= 2 else G], F64), lv, 1)
    Xc = X[::-1]
    cv = _records(sc, Xc[:t], water[::-1][:t - 1], fwd=[B[k - j] for j in range(1, t)],
                  rev=[A[k - j] if j < t - 2 else G for j in range(1, t)],
                  q=[q[k - j] for j in range(1, t)], rows=KMAX)
    cam = SP.camera_ends(sc, Vec3(*(jnp.asarray([c], F64) for c in X[k].p)), cv, 1)
    est, overflow = R.merge(sc, cam, lig, e)
    assert not bool(overflow)
    z = X[s]
    kernel = 4.0 / 3.0 * np.pi * MERGE_RADIUS**3 if z.what == "medium" else np.pi * MERGE_RADIUS**2
    f = f_merge(sc, z, unit(X[s + 1].p - z.p), unit(X[s - 1].p - z.p))
    val = float(est[t - 2, 0, s - 1, 0])
    if f == 0.0:
        assert val == 0.0
        return None
    return val * kernel / f


@functools.lru_cache(maxsize=None)
def renderer():
    return Renderer()


@pytest.mark.parametrize("name", SCENES)
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, KMAX))
def test_join_pdfs_equal_brute_force_and_weights_sum_to_one(name, seed, k):
    check_path(name, seed, k, renderer())


@pytest.mark.parametrize("name", SCENES)
@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(2, KMAX))
def test_merges_and_connections_weights_sum_to_one(name, seed, k):
    # bpm: the emitter hit's weight from the renderer's join pdfs and the merges' weights
    # as `_merge.vertex_merging` computes them (its own join: A_s from the photon's record,
    # A_s1 and B_s1 re-evaluated through the camera vertex), against the exact oracle
    check_path(name, seed, k, renderer(), merging=True)


# ---------------------------------------------------------------- fixed paths, planted mistakes
CASES = [(seed, k) for seed in range(4) for k in (2, 3, 4, 6)]


def test_fixed_paths_cover_every_family():
    # the same paths the planted mistakes run on pass unpatched, and the comparisons are
    # not vacuous: each family compares non-zero pdfs, glossy vertices are met with wi in
    # the Phong lobe, medium vertices and water segments take part
    COVER.clear()
    checked = collections.Counter()
    for name in SCENES:
        for seed, k in CASES:
            for fam, n in check_path(name, seed, k, renderer()).items():
                checked[name, fam] += n
    for name in SCENES:
        for fam in ("emitter hit", "nee", "light tracing", "connection"):
            if fam == "emitter hit" and name == "cornell_point":
                continue  # a point light cannot be hit
            assert checked[name, fam] >= 4, (name, fam, checked)
    assert COVER["phong lobe"] >= 3 and COVER["medium"] >= 10, COVER


# ---------------------------------------------------------------- aimed emission
# the aimed scenes' fixed paths: 16 first vertices x_1 (x_1 depends on the seed alone), so
# that their lines cross the water's plane inside and outside each scene's rectangle and in
# zero cells of the hand-made map
AIM_CASES = [(seed, (2, 3, 4, 6)[seed % 4]) for seed in range(16)]


@pytest.mark.parametrize("name", list(AIMED))
@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, KMAX))
def test_aimed_join_pdfs_equal_brute_force_and_weights_sum_to_one(name, seed, k):
    # the emission pdf of a sun or sky light with `aim` (the disk / aimed mixture of the
    # line through x_1, `infinite_emission_pdf`) in every technique's join pdfs and in the
    # MIS weights built from them; the same paths as the fixed ones below, other seeds
    check_path(name, seed, k, renderer())


@pytest.mark.parametrize("name", ["pool_sun_aim_map", "pool_sky_aim"])
@settings(max_examples=2, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(2, KMAX))
def test_aimed_merges_and_connections_weights_sum_to_one(name, seed, k):
    # bpm with the aimed lights (the sun: a delta light at infinity, no emitter hit):
    # the merges' weights from `_merge.vertex_merging` against the exact oracle
    check_path(name, seed, k, renderer(), merging=True)


def test_aimed_fixed_paths_cover_the_rectangle_and_every_family():
    # the aimed scenes' fixed paths pass, each family compares non-zero pdfs, and the lines
    # through x_1 cross the water's plane inside each scene's aimed rectangle and outside
    # it, and in zero cells of the hand-made map (its disk part alone there)
    for name in AIMED:
        COVER.clear()
        checked = collections.Counter()
        for seed, k in AIM_CASES:
            checked.update(check_path(name, seed, k, renderer()))
        fams = ["nee", "light tracing", "connection"]  # the sun cannot be hit
        fams += ["emitter hit"] * (scene_of(name).lights.kind[0] == LIGHT_SKY)
        assert all(checked[f] >= 4 for f in fams), (name, checked)
        assert COVER["aim inside"] >= 1 and COVER["aim outside"] >= 1, (name, COVER)
        if AIMED[name][2] is not None:
            assert COVER["aim zero cell"] >= 1, (name, COVER)


@functools.lru_cache(maxsize=None)
def _sample_emissions():
    return jax.jit(jax.vmap(lambda sc, u: L.sample_emission(sc, u), in_axes=(None, 0)))


def check_emissions(name, sample, n=48):
    """The light subpath's y_0 pdfs (`_lights.sample_emission`, which `_subpath.light_start`
    stores as the pdf of the first segment) of n emissions of an aimed light: pdf_dir equals
    `infinite_emission_pdf` of the emitted line, pdf_pos the light's pdf of its direction;
    the aimed part of the samples (u_3 < aim) crosses the water's plane in the rectangle in
    cells of non-zero weight. Returns the `aimed_density` coverage of the lines."""
    sc = scene_of(name)
    P = float(sc.lights.aim[0])
    u = np.random.default_rng(7).uniform(0.0, 1.0, (n, 5))
    e = sample(sc, jnp.asarray(u, F64))
    o, d = (np.stack([np.asarray(c, float) for c in v], -1) for v in (e.o, e.d))
    COVER.clear()
    for i in range(n):
        zero_before = COVER["aim zero cell"]
        want = infinite_emission_pdf(sc, d[i], o[i])
        _close(f"emission pdf_dir {name} sample {i}", e.pdf_dir[i], want)
        pos = 1.0 if sc.lights.kind[0] == LIGHT_SUN else max(-d[i, 1], 0.0) / np.pi
        _close(f"emission pdf_pos {name} sample {i}", e.pdf_pos[i], pos)
        if u[i, 3] < P:  # aimed: its line crosses in a cell of the map of non-zero weight
            x0, x1, z0, z1 = np.asarray(sc.lights.aim_rect, float)
            c = o[i] + d[i] * (float(sc.water.level) - o[i, 1]) / d[i, 1]
            assert x0 <= c[0] < x1 and z0 <= c[2] < z1, (name, i, c)
            assert COVER["aim zero cell"] == zero_before, (name, i, c)
    return {key: v for key, v in COVER.items() if key.startswith("aim")}


def test_aimed_emission_pdfs_equal_brute_force():
    for name in AIMED:
        cover = check_emissions(name, _sample_emissions())
        assert cover.get("aim inside", 0) >= 5, (name, cover)
    # the hand-made map's smaller rectangle: the disk part's lines cross outside it too
    assert cover.get("aim outside", 0) >= 2, cover


def _no_cosine(orig):
    def to_area(pdf_w, target_medium, target_n, w, d, seg_water, water, infinite_source=False):
        g = jnp.where(infinite_source, 1.0, 1.0 / jnp.maximum(d * d, 1e-30))
        return pdf_w * g * SP.dist_pdf(water, seg_water, target_medium, d)
    return to_area


def _swapped(orig):
    return lambda scene, kind, mat, md, wo, wi, n, *rest: orig(scene, kind, mat, md, wi, wo, n,
                                                               *rest)


def _wrong_end(orig):
    return lambda water, seg_water, target_medium, d: orig(water, seg_water,
                                                           ~jnp.asarray(target_medium), d)


def _cos2(orig):
    def camera_importance(scene, w, *rest):
        pix, imp, inside = orig(scene, w, *rest)
        f = scene.camera.forward
        return pix, imp * (w.x * f[0] + w.y * f[1] + w.z * f[2]), inside
    return camera_importance


def _backwards(orig):
    return lambda scene, light, n, w, *rest: orig(scene, light, n, -w, *rest)


def _flipped(orig):
    return lambda scene, light, w, *rest: orig(scene, light, -w, *rest)


def _aim_ignored(orig):
    def emission_pdf_dir(scene, light, n, w, p=None):  # lights at infinity: the disk alone
        _, rb = L.bounding_sphere(scene)
        inf = jnp.asarray([k in (LIGHT_SKY, LIGHT_SUN) for k in scene.lights.kind])[light]
        return jnp.where(inf, 1.0 / (jnp.pi * rb * rb), orig(scene, light, n, w, p))
    return emission_pdf_dir


def _no_dy(orig):
    return lambda scene, d, p: orig(scene, d, p) * jnp.abs(d.y)


def _map_transposed(orig):  # rows along x, columns along z
    return lambda scene, d, p: orig(
        eqx.tree_at(lambda s: s.lights.aim_map, scene, scene.lights.aim_map.T), d, p)


# name -> (scenes, module, attribute, the mistake given the original)
PLANTED = {
    # a medium vertex's kind equal to the glossy material's: every glossy vertex a medium
    # vertex at the joins
    "glossy_is_medium": (["cornell_point"], SP, "KIND_MEDIUM", lambda orig: MAT_GLOSSY),
    "cosine_dropped": (BOX_AND_POOL, SP, "to_area", _no_cosine),
    "bsdf_pdf_swapped": (BOX_AND_POOL, SP, "bsdf_pdf", _swapped),
    "distance_sampling_wrong_end": (["pool"], SP, "dist_pdf", _wrong_end),
    "pinhole_cos2": (BOX_AND_POOL, C, "camera_importance", _cos2),
    "emission_pdf_backwards": (["pool"], L, "emission_pdf_dir", _backwards),
    # the sky's pdf of the direction away from the sky (emitter hits, next-event estimation)
    "sky_direction_flipped": (["pool_sky"], L, "light_point_pdf", _flipped),
    # aimed emission: the emission pdf of a light at infinity without its aimed
    # part (the bounding disk's alone), the aimed density per unit area of the water's
    # plane instead of per unit perpendicular area (|d_y| dropped), the map's cells looked
    # up transposed
    "aim_ignored": (["pool_sun_aim", "pool_sky_aim"], L, "emission_pdf_dir", _aim_ignored),
    "aimed_pdf_without_dy": (list(AIMED), L, "aimed_pdf", _no_dy),
    "aim_map_transposed": (["pool_sun_aim_map"], L, "aimed_pdf", _map_transposed),
}


@pytest.mark.parametrize("mistake", list(PLANTED))
def test_planted_mistake_fails(mistake, monkeypatch):
    scenes, module, attr, plant = PLANTED[mistake]
    monkeypatch.setattr(module, attr, plant(getattr(module, attr)))
    R = Renderer(jit=False)  # run afresh with the mistake in place
    for name in scenes:
        with pytest.raises(AssertionError, match="join pdf"):
            for seed, k in AIM_CASES if name in AIMED else CASES:
                check_path(name, seed, k, R)


@pytest.mark.parametrize("mistake", ["aimed_pdf_without_dy", "aim_map_transposed"])
def test_planted_emission_mistake_fails(mistake, monkeypatch):
    # the same mistakes in the pdf the emission stores for y_0's first segment
    scenes, module, attr, plant = PLANTED[mistake]
    monkeypatch.setattr(module, attr, plant(getattr(module, attr)))
    sample = jax.jit(jax.vmap(lambda sc, u: L.sample_emission(sc, u), in_axes=(None, 0)))  # afresh
    for name in scenes:
        with pytest.raises(AssertionError, match="join pdf emission pdf_dir"):
            check_emissions(name, sample, n=16)


def _swap_directions(orig):
    return lambda scene, kind, mat, n, p, w_from, w_to, *rest: orig(scene, kind, mat, n, p, w_to,
                                                                     w_from, *rest)


def _disk_everywhere(orig):
    return lambda medium, radius: orig(jnp.zeros_like(medium), radius)


# merging's own join (`_merge.vertex_merging`, not in `_connect`): name -> (scenes, module,
# attribute, the mistake given the original)
PLANTED_MERGE = {
    # A(z_{t-2}) and B(y_{s-1}) through z with the scattering directions the wrong way round
    "merge_reverse_pdf_swapped": (["pool"], _merge, "reverse_pdf", _swap_directions),
    # the surface disk at medium vertices too (the kernel a KIND_MEDIUM equal to MAT_GLOSSY
    # would pick at glossy vertices)
    "merge_disk_kernel_in_medium": (["pool"], _merge, "kernel_size", _disk_everywhere),
}


@pytest.mark.parametrize("mistake", list(PLANTED_MERGE))
def test_planted_merge_mistake_fails(mistake, monkeypatch):
    scenes, module, attr, plant = PLANTED_MERGE[mistake]
    monkeypatch.setattr(module, attr, plant(getattr(module, attr)))
    R = Renderer()
    for name in scenes:
        with pytest.raises(AssertionError, match="merge weight"):
            for seed, k in CASES:
                check_path(name, seed, k, R, merging=True)
