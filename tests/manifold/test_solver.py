"""The one-specular-vertex solver (`jaxvcm._manifold`) against the float64 NumPy forward
optics of `_oracle.py`: a brute force over the whole footprint (a triangulated landing
map, every root refined by Newton in float64), closed forms on flat water, and finite
differences of float64 roots for the generalised geometry term and the gradients.

All solves are float32 (the renderer's dtype), one compiled program per kind of
connection (refraction / reflection x point / sun), every case of a kind in one vmapped
call.

Tolerances (float32, coordinates of order 1 m, ulp 6e-8 m): the solver returns a root
after a last Newton step, so it sits a few roundings from the exact root, amplified by the
constraint's conditioning (|J^-1| |dc/ds|, up to ~1e2 here): observed <= 1.4e-7 m over all
cases. Solver and float64 roots must agree to MATCH = 1e-5 m (70x that), far below the
closest distinct roots of these cases (6 cm), so no root can stand in for another.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

from jaxvcm import _manifold as M
from jaxvcm._scene import Water
from jaxvcm._vec import Vec3

from .. import _caustic_ref as CR
from . import _oracle as O

DT = jnp.float32
IOR = 1.33
FP = (-1.0, 1.0, -1.0, 1.0)
CAP = 6  # solutions kept per connection
GRID = 16  # seeds per side
MATCH = 1e-5  # m: solver root vs float64 root (module doc)
W = 3  # waves per case (flat cases: amplitudes 0)


# ---------------------------------------------------------------- cases
def rand_waves(rng, L, kmin=6.0, kmax=20.0):
    """W waves with random directions, phases and wave numbers in [kmin, kmax], amplitudes
    scaled so that the slope bound sum |A| |k| is L."""
    k = rng.uniform(kmin, kmax, W)
    th = rng.uniform(0, 2 * np.pi, W)
    A = rng.uniform(0.5, 1.0, W)
    A *= L / np.sum(A * k)
    return np.stack([A, k * np.cos(th), k * np.sin(th), rng.uniform(0, 2 * np.pi, W)], 1)


def sun_dir(zenith_deg, azimuth_deg):
    z, p = math.radians(zenith_deg), math.radians(azimuth_deg)
    return np.array([math.sin(z) * math.cos(p), -math.cos(z), math.sin(z) * math.sin(p)])


def cfg(waves, a, b, refract, b_dir, level=0.0):
    w = np.zeros((W, 4))
    waves = np.asarray(waves, float).reshape(-1, 4)
    w[:len(waves)] = waves
    return O.Config(w, level, IOR, FP, np.asarray(a, float), np.asarray(b, float), refract, b_dir)


def random_cases():
    """Seven families of random connections (seeded), six each."""
    out = {}
    U = np.random.default_rng
    r = U(1)
    for i in range(6):  # floor/medium point under water, light point above
        a = [r.uniform(-0.6, 0.6), r.uniform(-1.5, -0.3), r.uniform(-0.6, 0.6)]
        b = [r.uniform(-1.5, 1.5), r.uniform(0.5, 3.0), r.uniform(-1.5, 1.5)]
        waves = rand_waves(r, r.uniform(0.1, 0.45))
        out[f"refract-point-below-{i}"] = cfg(waves, a, b, True, False)
    r = U(2)
    for i in range(6):  # camera above, floor point under water
        a = [r.uniform(-1.0, 1.0), r.uniform(0.5, 3.0), r.uniform(-1.0, 1.0)]
        b = [r.uniform(-0.8, 0.8), r.uniform(-1.5, -0.3), r.uniform(-0.8, 0.8)]
        waves = rand_waves(r, r.uniform(0.1, 0.45))
        out[f"refract-point-above-{i}"] = cfg(waves, a, b, True, False)
    r = U(3)
    for i in range(6):  # point under water lit by the sun
        a = [r.uniform(-0.6, 0.6), r.uniform(-1.5, -0.3), r.uniform(-0.6, 0.6)]
        b = sun_dir(r.uniform(0, 60), r.uniform(0, 360))
        out[f"refract-sun-{i}"] = cfg(rand_waves(r, r.uniform(0.1, 0.45)), a, b, True, True)
    r = U(7)
    for i in range(6):  # deep points under steeper, shorter waves: folds, several solutions
        a = [r.uniform(-0.5, 0.5), r.uniform(-3.0, -2.0), r.uniform(-0.5, 0.5)]
        b = sun_dir(r.uniform(0, 30), r.uniform(0, 360))
        out[f"refract-sun-deep-{i}"] = cfg(rand_waves(r, r.uniform(0.4, 0.6), 8.0, 16.0), a, b,
                                           True, True)
    r = U(4)
    for i in range(6):  # glints: camera and light above (gentle waves: a mirror spreads 2x)
        a = [r.uniform(-1.0, 1.0), r.uniform(0.3, 2.0), r.uniform(-1.0, 1.0)]
        b = [r.uniform(-1.0, 1.0), r.uniform(0.3, 2.0), r.uniform(-1.0, 1.0)]
        waves = rand_waves(r, r.uniform(0.03, 0.1))
        out[f"reflect-point-above-{i}"] = cfg(waves, a, b, False, False)
    r = U(5)
    for i in range(6):  # the surface's underside (partial and total internal reflection)
        a = [r.uniform(-0.8, 0.8), r.uniform(-1.2, -0.3), r.uniform(-0.8, 0.8)]
        b = [r.uniform(-0.8, 0.8), r.uniform(-1.2, -0.3), r.uniform(-0.8, 0.8)]
        waves = rand_waves(r, r.uniform(0.03, 0.1))
        out[f"reflect-point-below-{i}"] = cfg(waves, a, b, False, False)
    r = U(6)
    for i in range(6):  # the sun reflected onto points above the water (walls)
        a = [r.uniform(-1.0, 1.0), r.uniform(0.1, 1.0), r.uniform(-1.0, 1.0)]
        b = sun_dir(r.uniform(10, 70), r.uniform(0, 360))
        out[f"reflect-sun-{i}"] = cfg(rand_waves(r, r.uniform(0.03, 0.1)), a, b, False, True)
    return out


POOL = np.array([[0.010, 11, 6, 0.0], [0.008, -5, 14, 1.3], [0.006, 16, -9, 0.7]])
GENTLE = np.array([[0.004, 9.0, 4.0, 0.3], [0.003, -3.0, 11.0, 1.1]])  # slope bound 0.07
STEEP1 = np.array([[0.04, 12.0, 0.0, 0.4]])  # slope 0.48, focus n/(n-1)/(A k^2) = 0.70 m
CROSS = np.array([[0.05, 10.0, 0.0, 0.3], [0.05, 0.0, 10.0, 1.0]])  # focus 0.81 m both ways


def _h(waves, x, z):
    return float(np.sum(waves[:, 0] * np.sin(waves[:, 1] * x + waves[:, 2] * z + waves[:, 3])))


def hard_cases():
    out = {}
    # grazing: the sun 80 deg from the zenith into gentle waves
    out["grazing-sun"] = cfg(GENTLE, [0.2, -0.5, 0.1], sun_dir(80, 30), True, True)
    # grazing glint: camera 0.15 m above the water, light 0.3 m up, 1.5 m apart: the mirror
    # point sees both at ~80 deg from the normal
    out["grazing-glint"] = cfg(GENTLE, [-0.7, 0.15, 0.0], [0.8, 0.3, 0.1], False, False)
    # near the critical angle from below: the flat-water ray leaves the water at ~87 deg
    # (water side 48.6 deg, the critical angle is 48.75 deg); the light 0.4 m above the
    # water 7.4 m away horizontally
    out["critical-below"] = cfg(GENTLE, [-0.4, -0.5, 0.0], [7.0, 0.4, 0.0], True, False)
    # a 1 mm under the local surface (inside the waves' slab), point light and sun
    x, z = 0.13, -0.21
    out["just-below-point"] = cfg(POOL, [x, _h(POOL, x, z) - 1e-3, z], [0.3, 2.0, 0.4], True, False)
    out["just-below-sun"] = cfg(POOL, [x, _h(POOL, x, z) - 1e-3, z], sun_dir(35, 120), True, True)
    # several solutions: a point 1.5 m deep under a steep short wave (focus 0.7 m)
    out["many-roots"] = cfg(STEEP1, [0.2, -1.5, 0.0], sun_dir(5, 0), True, True)
    # a crest focusing more solutions than the capacity: 3 x 3 from two crossing waves
    out["crest-overflow"] = cfg(CROSS, [0.1, -2.5, 0.2], [0.0, -1.0, 0.0], True, True)
    # endpoints on the wrong sides for the law: no solutions
    out["wrong-sides-refract"] = cfg(POOL, [0.1, -0.8, 0.2], [0.3, -0.4, -0.2], True, False)
    out["wrong-sides-reflect"] = cfg(POOL, [0.1, -0.8, 0.2], [0.3, 2.0, -0.2], False, False)
    return out


def flat_cases():
    """Flat water (amplitudes 0): the closed-form Snell / mirror solutions."""
    z0 = np.zeros((1, 4))
    return {
        "flat-point-below": cfg(z0, [0.1, -0.8, 0.2], [-0.7, 2.0, 0.9], True, False),
        "flat-point-above": cfg(z0, [0.6, 1.7, -0.5], [-0.2, -1.1, 0.3], True, False),
        "flat-sun": cfg(z0, [0.1, -1.2, -0.3], sun_dir(40, 200), True, True),
        "flat-just-below-sun": cfg(z0, [0.1, -1e-3, -0.3], sun_dir(40, 200), True, True),
        "flat-critical": cfg(z0, [-0.4, -0.5, 0.0], [7.0, 0.4, 0.0], True, False),
        "flat-mirror": cfg(z0, [-0.5, 1.3, 0.2], [0.7, 0.6, -0.4], False, False),
        "flat-mirror-below": cfg(z0, [-0.5, -0.9, 0.2], [0.7, -0.3, -0.4], False, False),
    }


RANDOM = random_cases()
HARD = hard_cases()
FLAT = flat_cases()
ALL = {**RANDOM, **HARD, **FLAT}


# ---------------------------------------------------------------- the solver, batched
def water_of(c: O.Config, dt=DT) -> Water:
    A = lambda x: jnp.asarray(np.asarray(x, np.float64), dt)
    return Water(enabled=True, phase_kind=0, level=A(c.level), amp=A(c.waves[:, 0]),
                 kx=A(c.waves[:, 1]), kz=A(c.waves[:, 2]), phase0=A(c.waves[:, 3]),
                 footprint=A(c.footprint), floor=A(-3.0), sigma_a=A([0.0]), sigma_s=A([0.0]),
                 g=A(0.0), b=A(0.0), ior=A(c.ior), mat=0)


def vec3(p, dt=DT) -> Vec3:
    p = np.asarray(p, np.float64)
    return Vec3(*(jnp.asarray(p[..., i], dt) for i in range(3)))


def stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


@functools.cache
def solver(refract, b_dir, capacity=CAP, grid=GRID):
    return jax.jit(jax.vmap(lambda w, a, b: M.solve(w, a, b, refract=refract, b_is_direction=b_dir,
                                                    capacity=capacity, grid=grid)))


def run(cases: dict, make=solver, **kw) -> dict:
    """Solve every case (grouped by kind, one call per kind): name -> numpy Solutions."""
    out = {}
    kinds = sorted({(c.refract, c.b_dir) for c in cases.values()})
    for refract, b_dir in kinds:
        names = [n for n, c in cases.items() if (c.refract, c.b_dir) == (refract, b_dir)]
        cs = [cases[n] for n in names]
        sol = make(refract, b_dir, **kw)(stack([water_of(c) for c in cs]),
                                           vec3(np.stack([c.a for c in cs])),
                                           vec3(np.stack([c.b for c in cs])))
        sol = jax.tree.map(np.asarray, sol)
        for i, n in enumerate(names):
            out[n] = jax.tree.map(lambda x, i=i: x[i], sol)
    return out


@functools.cache
def solved():
    return run(ALL)


@functools.cache
def brute(name):
    return O.brute_roots(ALL[name])


def roots_of(sol) -> np.ndarray:
    """[n, 2] (u, v) of the valid solutions."""
    s = np.stack([sol.s.x, sol.s.z], -1)
    return s[sol.valid]


def compare(c: O.Config, found: np.ndarray, ref: np.ndarray, tol=MATCH) -> dict:
    """The test's check. missing: reference roots with no found root within tol;
    spurious: found roots that are not solutions (their float64 refinement by the forward
    optics fails or moves them by more than tol); unknown: verified found roots that the
    brute force lacks (an incomplete reference)."""
    missing = [r for r in ref if not len(found) or np.min(np.linalg.norm(found - r, axis=1)) > tol]
    spurious, unknown = [], []
    for f in found:
        rr, conv = O.refine(c, f[None])
        if not conv[0] or np.linalg.norm(rr[0] - f) > tol:
            spurious.append(f)
        elif not len(ref) or np.min(np.linalg.norm(ref - f, axis=1)) > tol:
            unknown.append(f)
    return {"missing": missing, "spurious": spurious, "unknown": unknown}


# ---------------------------------------------------------------- solver vs brute force
@pytest.mark.parametrize("name", list(RANDOM) + list(HARD))
def test_every_solution_found(name):
    c, sol, ref = ALL[name], solved()[name], brute(name)
    found = roots_of(sol)
    chk = compare(c, found, ref)
    assert not chk["spurious"], chk
    assert not chk["unknown"], chk  # the brute force itself is complete
    if len(ref) <= CAP:
        # all found: exactly the reference's roots, none dropped for capacity
        assert not chk["missing"], chk
        assert int(sol.count) == len(ref) and not sol.overflow
    else:
        # more roots than kept: the sticky flag, and every kept root real
        assert sol.overflow and int(sol.count) == CAP
    # the search region (derived bound) contains every reference root
    x0, x1, z0, z1 = sol.region
    assert np.all((ref[:, 0] >= x0) & (ref[:, 0] <= x1) & (ref[:, 1] >= z0) & (ref[:, 1] <= z1))
    # residuals at the returned roots (c = lever m <= 3 m x a sine): at float32 rounding,
    # eps x conditioning ~ 1e-7 x m; observed <= 2.2e-7 m over all cases: bound 2e-6
    assert np.all(sol.residual[sol.valid] < 2e-6)


def test_families_have_one_and_many_solutions():
    # the random families and hard cases cover 0, 1 and several solutions per connection
    counts = [len(brute(n)) for n in list(RANDOM) + list(HARD)]
    assert min(counts) <= 1 and 1 in counts and max(counts) >= 3


def test_many_roots_and_overflow():
    # many-roots: 1.5 m under a wave focusing at 0.7 m: beyond the focus the landing map
    # folds, 3 solutions (brute force); crest-overflow: two crossing waves focusing at
    # 0.81 m, a 2.5 m deep: 3 x 3 = 9 solutions > CAP = 6 -> overflow
    assert len(brute("many-roots")) == 3 and int(solved()["many-roots"].count) == 3
    assert len(brute("crest-overflow")) == 9
    s = solved()["crest-overflow"]
    assert s.overflow and int(s.count) == CAP


def test_wrong_sides_have_no_solutions():
    # a refraction needs the endpoints on opposite sides of the surface, a reflection on
    # the same side: both points under the water (refraction) or one under and one above
    # (reflection) have no solution, in the solver as in the forward optics
    for n in ("wrong-sides-refract", "wrong-sides-reflect"):
        assert int(solved()[n].count) == 0 and len(brute(n)) == 0, n


# ---------------------------------------------------------------- flat water: closed forms
def flat_solution(c: O.Config) -> np.ndarray:
    """(u, v) of the flat-water solution in float64: Snell / the mirror law in the vertical
    plane through a and b (bisection on the tangential invariant), or for the sun the
    refracted ray through a traced back to the plane."""
    a, b, lv = c.a, c.b, c.level
    if c.b_dir:
        d = c.b / np.linalg.norm(c.b)
        t, _ = CR.refract_down(d[None], np.array([[0.0, 1.0, 0.0]]), c.ior)
        t = t[0]
        return (a - t * (a[1] - lv) / t[1])[[0, 2]]
    Da, Db = abs(a[1] - lv), abs(b[1] - lv)
    e = (b - a)[[0, 2]]
    P = np.linalg.norm(e)
    ea, eb = c.etas if c.refract else (1.0, 1.0)
    f = lambda p: ea * p / math.hypot(p, Da) - eb * (P - p) / math.hypot(P - p, Db)
    p1 = brentq(f, 0.0, P, xtol=1e-15, rtol=1e-15)
    return a[[0, 2]] + e / P * p1


@pytest.mark.parametrize("name", list(FLAT))
def test_flat_water_is_snell(name):
    c, sol = ALL[name], solved()[name]
    assert int(sol.count) == 1 and not sol.overflow
    s = roots_of(sol)[0]
    ref = flat_solution(c)
    # float32: the root (coordinates < 1 m: ulp 6e-8 m) a few roundings from the exact
    # one (observed <= 9e-8 m); the closed form is exact to 1e-15; 1e-6 m = 16 ulps
    assert np.max(np.abs(s - ref)) < 1e-6, (s, ref)
    assert np.isclose(sol.s.y[sol.valid][0], c.level, atol=1e-6)


# ---------------------------------------------------------------- planted mistakes
def test_planted_one_seed_misses_roots():
    # one seed (a 1 x 1 grid) converges to one root at most: the comparison must report
    # the others missing, while the real solver misses none on the same case
    name = "many-roots"
    c, ref = ALL[name], brute(name)
    one = run({name: c}, grid=1)[name]
    assert len(compare(c, roots_of(one), ref)["missing"]) >= len(ref) - 1 >= 2
    assert not compare(c, roots_of(solved()[name]), ref)["missing"]


def test_planted_wrong_normal_is_rejected(monkeypatch):
    # the slope's sign flipped in the solver's surface derivatives: its roots solve the
    # law for the mirrored normal; the forward optics in float64 must reject them
    orig = M._waves_d2

    def flipped(w, x, z, fast=False):
        h, hx, hz, hxx, hxz, hzz = orig(w, x, z, fast)
        return h, -hx, -hz, -hxx, -hxz, -hzz

    monkeypatch.setattr(M, "_waves_d2", flipped)
    # the random cases of three kinds (point refraction, sun, glint)
    cases = {n: c for n, c in RANDOM.items()
             if n.startswith(("refract-point-below", "refract-sun", "reflect-point-above"))}
    bad = run(cases, make=solver.__wrapped__, grid=8)  # traced afresh, with the flip
    found = {n: roots_of(bad[n]) for n in cases}
    # the broken solver does return roots (of its wrong law) for most cases ...
    assert sum(len(f) > 0 for f in found.values()) >= 10
    # ... and the check rejects every one of them
    for n, f in found.items():
        assert len(compare(ALL[n], f, brute(n))["spurious"]) == len(f), n


# ---------------------------------------------------------------- generalised geometry term
UP, DOWN = np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])


def first_root(name) -> np.ndarray:
    """The solver's first valid root of a case as a point [3] (float32 values)."""
    sol = solved()[name]
    i = int(np.argmax(sol.valid))
    assert sol.valid[i]
    return np.array([sol.s.x[i], sol.s.y[i], sol.s.z[i]], np.float64)


def g_cases(kind):
    """(name, n_a, n_b) of the G tests: point connections (area and point-light forms on
    the same cases) and the sun."""
    r = np.random.default_rng(11)
    unit = lambda v: v / np.linalg.norm(v)
    if kind == "refract":
        out = [(n, UP, DOWN) for n in RANDOM if n.startswith("refract-point-below")]
        out += [(n, DOWN, UP) for n in RANDOM if n.startswith("refract-point-above")]
    elif kind == "reflect":
        out = [(n, unit(r.normal(size=3)), unit(r.normal(size=3)))
               for n in RANDOM if n.startswith("reflect-point")]
    else:
        out = [(n, UP, None) for n in RANDOM if n.startswith("refract-sun-") and "deep" not in n]
    return [(n, na, nb) for n, na, nb in out if len(brute(n))]


def g_fn(refract, b_dir):
    """G of a batch of connections: (area form with n_b, point-light form) for a point b,
    the sun's form for a direction (float32, one program per kind of connection)."""
    def f(w, a, s, b, na, nb):
        kw = {"refract": refract, "b_is_direction": b_dir, "n_a": na}
        if b_dir:
            return M.generalized_geometry(w, a, s, b, **kw)
        return (M.generalized_geometry(w, a, s, b, n_b=nb, **kw),
                M.generalized_geometry(w, a, s, b, **kw))
    return jax.jit(jax.vmap(f))


def g_inputs(cases):
    cs = [ALL[n] for n, _, _ in cases]
    nb = [UP if x is None else x for _, _, x in cases]
    return (stack([water_of(c) for c in cs]), vec3(np.stack([c.a for c in cs])),
            vec3(np.stack([first_root(n) for n, _, _ in cases])), vec3(np.stack([c.b for c in cs])),
            vec3(np.stack([x for _, x, _ in cases])), vec3(nb))


@functools.cache
def g_solver(kind):
    """G of every case of a kind in one call (float32): cases, then G [n] (sun) or the
    area and point-light forms [n] each."""
    cases = g_cases(kind)
    c0 = ALL[cases[0][0]]
    G = g_fn(c0.refract, c0.b_dir)(*g_inputs(cases))
    G = G if isinstance(G, tuple) else (G,)
    return (cases,) + tuple(np.asarray(g, np.float64) for g in G)


def sun_factor_ray_mapping(c: O.Config, uv, delta=1e-6):
    """E(a) / E_sun on the horizontal plane through a, by the ray mapping of
    `tests/_caustic_ref.py`: parallel sun rays from a square of side 2 delta on the plane
    y = level + 1 around the ray through the root, intersected, refracted (Fresnel T) and
    landed on the plane; flux E |d_y| dA_0 T over the landing parallelogram's area."""
    pool = CR.Pool(level=c.level, waves=c.waves, ior=c.ior, sigma_t=np.zeros(1), floor=c.a[1],
                   footprint=c.footprint, wall_top=c.level + 1.0, sun=O._unit(c.b), E=np.ones(1),
                   albedo=np.ones(1))
    d = pool.sun
    s = O.point(c, uv)
    o = s + d * ((pool.wall_top - s[1]) / d[1])

    def land(dx, dz):
        o_ = o + np.array([dx, 0.0, dz])
        p = o_ + d * CR.intersect_surface(pool, o_[None], d[None])[0]
        n = CR.surface_normal(pool, p[0], p[2])
        wt, T = CR.refract_down(d[None], n[None], pool.ior)
        q = p + wt[0] * (c.a[1] - p[1]) / wt[0, 1]
        return q[[0, 2]], float(T[0])

    jx = (land(delta, 0)[0] - land(-delta, 0)[0]) / (2 * delta)
    jz = (land(0, delta)[0] - land(0, -delta)[0]) / (2 * delta)
    return abs(d[1]) * land(0, 0)[1] / abs(jx[0] * jz[1] - jx[1] * jz[0])


@pytest.mark.parametrize("kind", ["refract", "reflect", "sun"])
def test_generalized_geometry_vs_finite_differences(kind):
    # float32 G (jax.jacfwd of the root, implicit function theorem) against central
    # differences (step 1e-5 m: truncation ~1e-10 relative; the float64 roots converge to
    # ~1e-15 m) of float64 roots, or for the sun the caustic reference's ray mapping. A
    # float32 Jacobian of the root carries ~eps x conditioning (~1e-6 x 1e2): 2e-3 relative.
    cases, *Gs = g_solver(kind)
    assert len(cases) >= 5
    for i, (n, na, nb) in enumerate(cases):
        c = ALL[n]
        uv = O.root_near(c, first_root(n)[[0, 2]])  # the float64 root
        if kind == "sun":
            T = M.fresnel_factor(water_of(c), vec3(c.a), vec3(first_root(n)), vec3(c.b),
                                 refract=True, b_is_direction=True)
            checks = [(Gs[0][i] * float(T), sun_factor_ray_mapping(c, uv))]
        else:
            checks = [(Gs[0][i], O.g_area_fd(c, uv, nb, na)), (Gs[1][i], O.g_point_fd(c, uv, na))]
        for g, ref in checks:
            assert ref > 0 and abs(g / ref - 1) < 2e-3, (n, g, ref)


def test_generalized_geometry_reciprocity():
    # etendue: eta_a^2 |cos_a| dA_a dw_a = eta_b^2 |cos_b| dA_b dw_b along the chain, so the
    # area form (perturb b) and the point form (perturb a) agree:
    #   |cos_a| dw_a/dA_b = (eta_b / eta_a)^2 |cos_b| dw_b/dA_a   (float32 both: 1e-3)
    for kind in ("refract", "reflect"):
        cases, Ga, Gp = g_solver(kind)
        for (n, na, nb), ga, gp in zip(cases, Ga, Gp):
            c = ALL[n]
            eta_a, eta_b = c.etas
            w_b = O._unit(first_root(n) - c.b)
            assert abs(ga / ((eta_b / eta_a) ** 2 * abs(w_b @ nb) * gp) - 1) < 1e-3, n


def test_generalized_geometry_gradient():
    # d G / d A_0 (reverse mode through the root's implicit-function rule, which evaluates
    # the root through itself: second derivatives of the root) against central differences
    # (step 1e-6 in A ~ 1e-2: truncation ~1e-8 relative) of the float64 finite-difference
    # G; the float32 second derivatives: ~1e-3 of the largest
    cases = g_cases("refract")[:4]

    def g_of_amp(w, a, s, b, na, nb):
        def f(A0):
            w_ = eqx.tree_at(lambda m: m.amp, w, w.amp.at[0].set(A0))
            return M.generalized_geometry(w_, a, s, b, refract=True, n_a=na, n_b=nb)
        return jax.grad(f)(w.amp[0])

    dG = np.asarray(jax.jit(jax.vmap(g_of_amp))(*g_inputs(cases)), np.float64)
    for (n, na, nb), d in zip(cases, dG):
        c = ALL[n]
        uv = O.root_near(c, first_root(n)[[0, 2]])
        h = 1e-6
        cu, cd = _waves_with(c, 0, 0, h), _waves_with(c, 0, 0, -h)
        ref = (O.g_area_fd(cu, O.root_near(cu, uv), nb, na)
               - O.g_area_fd(cd, O.root_near(cd, uv), nb, na)) / (2 * h)
        assert abs(d - ref) < 2e-3 * abs(ref), (n, d, ref)


# ---------------------------------------------------------------- gradients through the roots
def _waves_with(c: O.Config, i, col, dv):
    w = c.waves.copy()
    w[i, col] += dv
    return O.Config(w, c.level, c.ior, c.footprint, c.a, c.b, c.refract, c.b_dir)


@functools.cache
def root_jac(b_dir):
    """d(u, v)/d(A_0, phase_0) of the first valid root, float32, vmapped over cases."""
    def f(w, a, b):
        def root(th):
            w_ = eqx_tree_at(w, th)
            sol = M.solve(w_, a, b, refract=True, b_is_direction=b_dir, capacity=CAP, grid=GRID)
            i = jnp.argmax(sol.valid)
            return jnp.stack([sol.s.x[i], sol.s.z[i]])
        return jax.jacfwd(root)(jnp.stack([w.amp[0], w.phase0[0]]))
    return jax.jit(jax.vmap(f))


def eqx_tree_at(w: Water, th):
    return eqx.tree_at(lambda m: (m.amp, m.phase0), w,
                       (w.amp.at[0].set(th[0]), w.phase0.at[0].set(th[1])))


@pytest.mark.parametrize("family", ["refract-point-below", "refract-sun-deep"])
def test_root_gradients_vs_finite_differences(family):
    # d s / d(amplitude, phase) of wave 0 by the implicit function theorem (float32) against
    # central differences of the float64 root (steps 1e-6 in A, 1e-5 in phase: truncation
    # ~1e-8 relative); float32 derivatives: ~eps x conditioning -> 2e-3 of the largest
    names = [n for n in RANDOM if n.startswith(family) and len(brute(n))]
    cs = [ALL[n] for n in names]
    J = np.asarray(root_jac(cs[0].b_dir)(stack([water_of(c) for c in cs]),
                                         vec3(np.stack([c.a for c in cs])),
                                         vec3(np.stack([c.b for c in cs]))), np.float64)
    for n, c, j in zip(names, cs, J):
        uv = O.root_near(c, first_root(n)[[0, 2]])
        ref = np.zeros((2, 2))
        for col, (k, h) in enumerate(((0, 1e-6), (3, 1e-5))):
            up = O.root_near(_waves_with(c, 0, k, h), uv)
            dn = O.root_near(_waves_with(c, 0, k, -h), uv)
            ref[:, col] = (up - dn) / (2 * h)
        assert np.max(np.abs(j - ref)) < 2e-3 * np.max(np.abs(ref)), (n, j, ref)
