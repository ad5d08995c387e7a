"""Ray intersection with the analytic shapes, one ray at a time (vmap at the top).

Every routine takes a ray (o, d) with |d| = 1 and an interval (tmin, tmax) and returns
the hit distance, `inf` on a miss. `intersect_scene` takes the closest over all shape
kinds (rectangles, spheres, the water heightfield) in a static dispatch.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _vec as vec
from ._fuse import computed_once
from ._queue import masked_map
from ._scene import SHAPE_NONE, SHAPE_RECT, SHAPE_SPHERE, SHAPE_WATER, Rects, Scene, Spheres, Water
from ._vec import Vec3

INF = jnp.inf


class Hit(NamedTuple):
    t: Array  # distance along the ray, inf on a miss
    shape: Array  # SHAPE_* class of the hit
    index: Array  # index within that class
    n: Vec3  # unit geometric normal (rects: e1 x e2; spheres: outward; water: up)
    mat: Array  # material id (-1 on a miss)
    light: Array  # light id (-1 if not emissive)


# ---------------------------------------------------------------- rectangles
def intersect_rects(r: Rects, o: Vec3, d: Vec3, tmin, tmax) -> tuple[Array, Array]:
    """Distances to all R rectangles: ([R] t with inf for misses, and the argmin)."""
    p0 = vec.from_array(r.p0)
    e1 = vec.from_array(r.e1)
    e2 = vec.from_array(r.e2)
    n = vec.cross(e1, e2)
    denom = vec.dot(d, n)
    safe = jnp.where(denom == 0, 1.0, denom)
    num = vec.dot(p0 - o, n)
    t = num / safe
    q = o + d * t - p0
    # (u, v) in the dual basis of (e1, e2): right for parallelograms, not only rectangles
    nn = vec.dot(n, n)
    u = vec.dot(vec.cross(q, e2), n) / nn
    v = vec.dot(vec.cross(e1, q), n) / nn
    # o on the plane to within the rounding of num: the only "hit" would be o itself
    eps = jnp.finfo(o.x.dtype).eps
    on_plane = jnp.abs(num) <= 8 * eps * vec.length(n) * (vec.length(p0) + vec.length(o)
                                                         + vec.length(e1) + vec.length(e2))
    ok = ~on_plane & (denom != 0) & (t > tmin) & (t < tmax) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    t = jnp.where(ok, t, INF)
    return t, jnp.argmin(t)


def rect_normal(r: Rects, i) -> Vec3:
    n = vec.cross(vec.from_array(r.e1[i]), vec.from_array(r.e2[i]))
    return vec.normalize(n)


# ---------------------------------------------------------------- spheres
def intersect_spheres(s: Spheres, o: Vec3, d: Vec3, tmin, tmax) -> tuple[Array, Array]:
    c = vec.from_array(s.center)
    oc = o - c
    b = vec.dot(oc, d)
    # c' = |oc|^2 - R^2 computed as (|oc| - R)(|oc| + R) to keep precision near the surface
    loc = vec.length(oc)
    cc = (loc - s.radius) * (loc + s.radius)
    # discriminant via the distance from the centre to the ray (Hearn-Baker form, pbrt-v4)
    perp = oc - d * b
    disc = (s.radius - vec.length(perp)) * (s.radius + vec.length(perp))
    sq = jnp.sqrt(jnp.maximum(disc, 0.0))
    q = -(b + jnp.where(b >= 0, sq, -sq))
    q_safe = jnp.where(q == 0, 1.0, q)
    t0 = cc / q_safe
    t1 = q
    t_near = jnp.minimum(t0, t1)
    t_far = jnp.maximum(t0, t1)
    t = jnp.where(t_near > tmin, t_near, t_far)
    # o on the sphere to within rounding: its own root cc / q ~ 0 is a self-hit; the other
    # root q (= -2 b) is the far side when entering, negative (a miss) when leaving
    eps = jnp.finfo(o.x.dtype).eps
    on = jnp.abs(loc - s.radius) <= 8 * eps * (vec.length(o) + vec.length(c) + s.radius)
    t = jnp.where(on, q, t)
    ok = (disc >= 0) & (t > tmin) & (t < tmax) & (q != 0)
    t = jnp.where(ok, t, INF)
    return t, jnp.argmin(t)


# ---------------------------------------------------------------- water heightfield
WAVES_UNROLLED = 4  # waves per trip of `over_waves`' loop in the intersector
SOLVER_WAVES_UNROLLED = 1  # ... in the manifold solves and their derivatives


def over_waves(w: Water, body, init, unroll: int = WAVES_UNROLLED):
    """`init` carried through body(amp, kx, kz, phase, carry) once per wave, in a rolled
    loop (`lax.fori_loop`): one copy of a wave's arithmetic in the compiled program
    whatever the number of waves, so compile time and memory do not grow with it (a
    wind-driven surface has hundreds). The carry is elementwise in the batch: every wave
    updates it with elementwise ops, never a reduction over a short trailing axis.
    `unroll` waves per trip: the intersector's march (most of a pass's time) runs four per
    trip; the manifold solves, whose derivatives copy the loop many times over, one
    (`SOLVER_WAVES_UNROLLED`: the glints' program compiles in three quarters of the time,
    at the same pass time)."""
    def step(i, c):
        return body(w.amp[i], w.kx[i], w.kz[i], w.phase0[i], c)

    if w.n_waves == 0:  # flat water (the body's gathers need a wave to trace)
        return init
    return jax.lax.fori_loop(0, w.n_waves, step, init, unroll=max(1, min(w.n_waves, unroll)))


def water_height(w: Water, x, z, grad: bool = True, unroll: int = WAVES_UNROLLED):
    """Surface height h(x, z) and its gradient (dh/dx, dh/dz), elementwise in x, z
    (the sum over the waves in `over_waves`' rolled loop)."""
    zero = jnp.zeros(jnp.broadcast_shapes(jnp.shape(x), jnp.shape(z)), jnp.result_type(x, z))
    if not grad:
        def height(a, kx, kz, ph, h):
            return h + a * jnp.sin(kx * x + kz * z + ph)

        return over_waves(w, height, zero + w.level, unroll), zero, zero

    def wave(a, kx, kz, ph, c):
        h, hx, hz = c
        arg = kx * x + kz * z + ph
        cs = a * jnp.cos(arg)
        return h + a * jnp.sin(arg), hx + kx * cs, hz + kz * cs

    return over_waves(w, wave, (zero + w.level, zero, zero), unroll)


def water_normal(w: Water, x, z) -> Vec3:
    _, hx, hz = water_height(w, jnp.asarray(x), jnp.asarray(z))
    hx, hz = computed_once(hx, hz)  # the waves' cosines once, not once per reader
    return vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))


def water_slab(w: Water) -> tuple[Array, Array]:
    """y-range that contains the surface: level -/+ (sum |A_i| + a 1 mm pad, so that flat
    water still has a slab of non-zero thickness to bracket its crossing in)."""
    a = jnp.sum(jnp.abs(w.amp)) + 1e-3
    return w.level - a, w.level + a


STEEP_EXTRA_REFINE = 2  # Illinois steps added when the bracket is the whole box (`steep`)


def _f_rounding(w: Water, o: Vec3, d: Vec3, t0, x0, z0):
    """A bound on the rounding of f(t0) = o_y + t0 d_y - h(x0, z0): below it, o is on the
    surface. The waves' terms sum_i |A_i| (1 + |kx_i x0| + |kz_i z0| + |phase_i|), as three
    sums over the waves (scalars) times |x0|, |z0|: a constant-size program."""
    eps = jnp.finfo(o.x.dtype).eps
    A = jnp.abs(w.amp)
    s = (jnp.abs(o.y) + jnp.abs(t0 * d.y) + jnp.abs(w.level)
         + jnp.sum(A * (1 + jnp.abs(w.phase0))) + jnp.abs(x0) * jnp.sum(A * jnp.abs(w.kx))
         + jnp.abs(z0) * jnp.sum(A * jnp.abs(w.kz)))
    return 8 * eps * s


def _slab_interval(lo: Vec3, hi: Vec3, o: Vec3, d: Vec3, tmin, tmax):
    ts = []
    for oc, dc, l, h in ((o.x, d.x, lo.x, hi.x), (o.y, d.y, lo.y, hi.y), (o.z, d.z, lo.z, hi.z)):
        inv = 1.0 / jnp.where(dc == 0, 1e-30, dc)
        ta, tb = (l - oc) * inv, (h - oc) * inv
        ts.append((jnp.minimum(ta, tb), jnp.maximum(ta, tb)))
    t0 = jnp.maximum(jnp.maximum(ts[0][0], ts[1][0]), jnp.maximum(ts[2][0], tmin))
    t1 = jnp.minimum(jnp.minimum(ts[0][1], ts[1][1]), jnp.minimum(ts[2][1], tmax))
    return t0, t1


def steep(w: Water, d: Vec3) -> Array:
    """The direction is steeper than any slope of the surface: |d_y| > L |d_xz| with L =
    sum |A_i| |k_i| >= |grad h|, so f(t) = o_y + t d_y - h(x(t), z(t)) is strictly
    monotone along the ray (f' = d_y - grad h . d_xz) and crosses zero at most once: the
    surface's box brackets the crossing without the march (1 % margin for rounding)."""
    L = jnp.sum(jnp.abs(w.amp) * jnp.sqrt(w.kx * w.kx + w.kz * w.kz)).astype(d.x.dtype)
    return jnp.abs(d.y) > 1.01 * L * jnp.sqrt(d.x * d.x + d.z * d.z)


def intersect_water(w: Water, o: Vec3, d: Vec3, tmin, tmax, steps: int = 16, refine: int = 6,
                    any_hit: bool = False, steep: bool = False) -> Array:
    """First crossing of the heightfield along the ray, to float32 precision.

    1. Clip the ray to the box footprint x [level - sum|A|, level + sum|A|] (padded by
       1 mm) that contains the surface: no crossing can lie outside it.
    2. March `steps` uniform segments over that interval and take the first segment whose
       end-point values of f(t) = o_y + t d_y - h(x(t), z(t)) differ in sign (the bracket).
       With `any_hit` (shadow rays) the answer is already known here: a sign change inside
       (tmin, tmax) is a crossing, so no refinement is done.
    3. Refine: `refine` Illinois (modified regula falsi) steps, which keep the bracket and
       converge superlinearly, then one Newton step clamped to the bracket.

    `steep` (static; only for rays that `steep` holds for): f is monotone along the ray,
    so the box's two ends bracket the only crossing: no march, and STEEP_EXTRA_REFINE more
    Illinois steps for the wider bracket (the same root to float32 round-off).

    A crossing pair closer together than one march segment (the ray grazing a crest by
    less than a segment) can be missed; with 16 segments the segment is at most ~18 cm
    against a shortest wavelength of ~29 cm in the shipped pools, so this only happens
    for near-tangent grazing rays (tests bound how often).
    """
    ylo, yhi = water_slab(w)
    fp = w.footprint
    lo = Vec3(fp[0], ylo, fp[2])
    hi = Vec3(fp[1], yhi, fp[3])
    t0, t1 = _slab_interval(lo, hi, o, d, tmin, tmax)
    empty = ~(t0 < t1)
    t1c = jnp.where(empty, t0 + 1.0, t1)

    def f(t):
        h, _, _ = water_height(w, o.x + t * d.x, o.z + t * d.z, grad=False)
        return o.y + t * d.y - h

    if steep:  # (a ray that `steep` holds for): its two end points alone, the second as
        # the march computes its last one
        ts = t0 + (t1c - t0) * (jnp.asarray([0, steps], o.x.dtype) / steps)
        refine = refine + STEEP_EXTRA_REFINE  # a bracket `steps` times as wide
    else:
        ts = t0 + (t1c - t0) * (jnp.arange(steps + 1, dtype=o.x.dtype) / steps)
    fs = f(ts)
    # o on the surface (f(t0) within its rounding): use the sign the ray moves towards
    x0, z0 = o.x + t0 * d.x, o.z + t0 * d.z
    _, hx0, hz0 = water_height(w, x0, z0)
    df0 = d.y - (hx0 * d.x + hz0 * d.z)
    ferr = _f_rounding(w, o, d, t0, x0, z0)
    sgn0 = jnp.where(jnp.abs(fs[0]) <= ferr, df0 >= 0, fs[0] >= 0)
    change = (fs[1:] >= 0) != sgn0
    found = jnp.any(change) & ~empty
    if any_hit:
        return jnp.where(found, t0, INF)
    k = jnp.argmax(change)
    a, b = ts[k], ts[k + 1]
    fa, fb = fs[k], fs[k + 1]

    def secant(a, b, fa, fb):
        denom = fb - fa
        m = jnp.where(denom != 0, (a * fb - b * fa) / jnp.where(denom != 0, denom, 1.0),
                      0.5 * (a + b))
        return jnp.clip(m, jnp.minimum(a, b), jnp.maximum(a, b))

    def keep(a, b, fa, fb, side, m, fm):
        # side: which end was kept last time (Illinois: if the same end survives twice,
        # halve its function value)
        left = (fm >= 0) != (fa >= 0)  # root in [a, m]: b <- m
        fa = jnp.where(left & (side == 1), 0.5 * fa, fa)
        fb = jnp.where(~left & (side == -1), 0.5 * fb, fb)
        b, fb = jnp.where(left, m, b), jnp.where(left, fm, fb)
        a, fa = jnp.where(left, a, m), jnp.where(left, fa, fm)
        return a, b, fa, fb, jnp.where(left, 1, -1).astype(jnp.int32)

    def illinois(_, c):
        # software-pipelined: the carry holds the new point m and f(m), evaluated by the
        # previous iteration, so f (the waves' sines) is the body's only expensive output
        # (computed in the body and read by the five bracket updates, f would be fused
        # into each of them by the CPU backend); the values are the same bit for bit.
        a, b, fa, fb, side = keep(*c)
        m = secant(a, b, fa, fb)
        return a, b, fa, fb, side, m, f(m)

    # a rolled loop: one copy of the step in the program (compile time), same arithmetic
    m = secant(a, b, fa, fb)
    c = (a, b, fa, fb, jnp.zeros((), jnp.int32), m, f(m))
    if refine > 0:
        c = keep(*jax.lax.fori_loop(0, refine - 1, illinois, c))
    # the bracket carries no derivatives (its secant steps divide by f's differences,
    # which vanish as it converges: their derivatives overflow, and a masked-out lane's
    # inf times 0 is a NaN in the gradient); the last Newton step gives the crossing's
    # derivatives by the implicit function theorem, dt = -df / (df/dt)
    # derivatives by the implicit function theorem, dt = -df / (df/dt). A miss takes a
    # finite stand-in (t = 0, df/dt = 1): its value is discarded below, and nothing
    # non-finite may reach the gradients through the discarded branch.
    a, b, fa, fb, _ = jax.lax.stop_gradient(c[:5])
    a, b = jnp.where(found, a, 0.0), jnp.where(found, b, 0.0)
    t = jnp.where(jnp.abs(fa) < jnp.abs(fb), a, b)
    h, hx, hz = water_height(w, o.x + t * d.x, o.z + t * d.z)
    ft = o.y + t * d.y - h
    dft = d.y - (hx * d.x + hz * d.z)
    dft = jnp.where(found, jnp.where(dft == 0, 1e-30, dft), 1.0)
    t = jnp.clip(t - ft / dft, a, b)
    ok = found & (t > tmin) & (t < tmax)
    return jnp.where(ok, t, INF)


def meets_slab(w: Water, o: Vec3, d: Vec3, tmin, tmax) -> Array:
    """The ray's interval (tmin, tmax) meets the box that contains the surface (the first
    step of `intersect_water`): a ray that does not cannot cross the water."""
    ylo, yhi = water_slab(w)
    fp = w.footprint
    t0, t1 = _slab_interval(Vec3(fp[0], ylo, fp[2]), Vec3(fp[1], yhi, fp[3]), o, d, tmin, tmax)
    return t0 < t1


def crosses_water(w: Water, o: Vec3, d: Vec3, tmin, tmax, steps: int = 16) -> Array:
    """The segment (tmin, tmax) surely crosses the water surface: the end points of its
    part inside the surface's box lie on opposite sides (f(t) = o_y + t d_y - h changes
    sign between them, so the continuous f has a root in between). This is exactly
    `intersect_water`'s any-hit answer on the march's first and last points (the same
    expressions, the same on-surface rule for the first), so wherever it holds
    `intersect_water(..., any_hit=True)` is finite: a shadow segment known blocked at the
    cost of two height evaluations instead of the march (a delta interface blocks every
    connection through it). False says nothing: the segment may still cross twice."""
    ylo, yhi = water_slab(w)
    fp = w.footprint
    t0, t1 = _slab_interval(Vec3(fp[0], ylo, fp[2]), Vec3(fp[1], yhi, fp[3]), o, d, tmin, tmax)
    empty = ~(t0 < t1)
    t1c = jnp.where(empty, t0 + 1.0, t1)
    tE = t0 + (t1c - t0) * (jnp.asarray(steps, o.x.dtype) / steps)  # the march's last point
    hE, _, _ = water_height(w, o.x + tE * d.x, o.z + tE * d.z, grad=False)
    fE = o.y + tE * d.y - hE
    x0, z0 = o.x + t0 * d.x, o.z + t0 * d.z
    h0, hx0, hz0 = water_height(w, x0, z0)
    f0 = o.y + t0 * d.y - h0
    df0 = d.y - (hx0 * d.x + hz0 * d.z)
    ferr = _f_rounding(w, o, d, t0, x0, z0)
    sgn0 = jnp.where(jnp.abs(f0) <= ferr, df0 >= 0, f0 >= 0)
    return ~empty & ((fE >= 0) != sgn0)


def water_hits(w: Water, o: Vec3, d: Vec3, want, steps: int, split: int) -> Array:
    """`intersect_water` on (0, inf) for a batch of rays [B], run only where `want` holds
    and the ray meets the surface's box (`meets_slab`); inf elsewhere, which is
    `intersect_water`'s own answer for a ray that misses the box. The rays that meet it go
    through a work queue (`_queue.masked_map`), because under `vmap` every lane would pay
    for the march and the refinement, and in a pool a large share of the rays never meet
    the box. The `steep` rays among them are queued first and bracketed by the box alone
    (no march): in a pool most are steep (camera rays, and diffuse bounces off the floor)."""
    meet = want & jax.vmap(meets_slab, in_axes=(None, 0, 0, None, None))(w, o, d, 0.0, INF)
    return masked_map(lambda o_, d_: intersect_water(w, o_, d_, 0.0, INF, steps), meet,
                      (o, d), INF, split,
                      cheap=(lambda o_, d_: intersect_water(w, o_, d_, 0.0, INF, steps,
                                                            steep=True),
                             jax.vmap(steep, in_axes=(None, 0))(w, d)))


def inside_water(w: Water, p: Vec3) -> Array:
    """Membership of the water body: inside the footprint, above the floor, below the surface."""
    if not w.enabled:
        return jnp.zeros(p.x.shape, bool)
    fp = w.footprint
    h, _, _ = water_height(w, p.x, p.z, grad=False)
    return (p.x > fp[0]) & (p.x < fp[1]) & (p.z > fp[2]) & (p.z < fp[3]) & (p.y > w.floor) & (p.y < h)


# ---------------------------------------------------------------- scene
def closest_t(scene: Scene, o: Vec3, d: Vec3, tmin=0.0, tmax=INF, steps: int = 16,
              any_hit: bool = False, t_water=None) -> tuple[Array, Array, Array]:
    """(t, shape, index) of the closest hit over every shape kind (static dispatch); a miss
    has t = inf, shape = -1. Shadow rays stop here (`unoccluded`). `t_water`: the water's
    distance on (tmin, tmax) when the caller computed it already (`water_hits`)."""
    dt = o.x.dtype
    t = jnp.asarray(INF, dt)
    shape = jnp.asarray(SHAPE_NONE, jnp.int32)
    index = jnp.asarray(0, jnp.int32)
    if scene.rects.count:
        tr, ir = intersect_rects(scene.rects, o, d, tmin, tmax)
        tr = tr[ir]
        closer = tr < t
        t = jnp.where(closer, tr, t)
        shape = jnp.where(closer, SHAPE_RECT, shape)
        index = jnp.where(closer, ir.astype(jnp.int32), index)
    if scene.spheres.count:
        tsph, isph = intersect_spheres(scene.spheres, o, d, tmin, tmax)
        tsph = tsph[isph]
        closer = tsph < t
        t = jnp.where(closer, tsph, t)
        shape = jnp.where(closer, SHAPE_SPHERE, shape)
        index = jnp.where(closer, isph.astype(jnp.int32), index)
    if scene.water.enabled:
        tw = (intersect_water(scene.water, o, d, tmin, tmax, steps=steps, any_hit=any_hit)
              if t_water is None else t_water)
        closer = tw < t
        t = jnp.where(closer, tw, t)
        shape = jnp.where(closer, SHAPE_WATER, shape)
        index = jnp.where(closer, 0, index)
    return t, shape, index


def intersect_scene(scene: Scene, o: Vec3, d: Vec3, tmin=0.0, tmax=INF, steps: int = 16,
                    any_hit: bool = False, t_water=None) -> Hit:
    """Closest hit over every shape kind (static dispatch); a miss has t = inf, shape = -1."""
    t, shape, index = closest_t(scene, o, d, tmin, tmax, steps, any_hit, t_water)

    # ---- normal, material, light of the closest hit ----
    tt = jnp.where(jnp.isfinite(t), t, 0.0)
    p = o + d * tt
    n = Vec3(jnp.zeros_like(t), jnp.ones_like(t), jnp.zeros_like(t))
    mat = jnp.asarray(-1, jnp.int32)
    light = jnp.asarray(-1, jnp.int32)
    if scene.rects.count:
        is_r = shape == SHAPE_RECT
        ir = jnp.where(is_r, index, 0)
        n = vec.where(is_r, rect_normal(scene.rects, ir), n)
        mat = jnp.where(is_r, scene.rects.mat[ir], mat)
        light = jnp.where(is_r, scene.rects.light[ir], light)
    if scene.spheres.count:
        is_s = shape == SHAPE_SPHERE
        isp = jnp.where(is_s, index, 0)
        c = vec.from_array(scene.spheres.center[isp])
        n = vec.where(is_s, vec.normalize(p - c), n)
        mat = jnp.where(is_s, scene.spheres.mat[isp], mat)
        light = jnp.where(is_s, scene.spheres.light[isp], light)
    if scene.water.enabled:
        is_w = shape == SHAPE_WATER
        n = vec.where(is_w, water_normal(scene.water, p.x, p.z), n)
        mat = jnp.where(is_w, scene.water.mat, mat)
        light = jnp.where(is_w, -1, light)
    return Hit(t, shape, index, n, mat, light)


def unoccluded(scene: Scene, o: Vec3, d: Vec3, tmax, steps: int = 16) -> Array:
    """True if nothing is hit on (0, tmax): the shadow-ray test. Any surface blocks,
    the water surface included (NEE through a delta interface is impossible)."""
    return ~jnp.isfinite(closest_t(scene, o, d, 0.0, tmax, steps, any_hit=True)[0])
