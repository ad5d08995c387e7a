"""Connections through one specular vertex on the water surface (manifold connections).

Given a non-delta endpoint `a` (a floor, wall or medium vertex, or the pinhole) and an
endpoint `b` (a point on a light, or, with `b_is_direction`, the direction the sun's light
travels), `solve` finds every point s = (u, h(u, v), v) of the heightfield
h(u, v) = level + sum_i A_i sin(kx_i u + kz_i v + phi_i) for which a -> s -> b obeys the
law of refraction (`refract=True`) or of mirror reflection at the analytic surface.
Everything is written for one connection (scalars); `jax.vmap` batches it.

Constraint (Hanika et al. 2015; Walter et al. 2009). w_a = normalize(a - s), w_b =
normalize(b - s) (w_b = -d for a direction d), eta_a and eta_b the indices of the two
endpoints' media (both 1 for a reflection). The law holds iff the generalised half vector
H = eta_a w_a + eta_b w_b is parallel to the normal, and for a heightfield the normal is
(-h_u, 1, -h_v), orthogonal to the parametric tangents T_u = (1, h_u, 0), T_v = (0, h_v, 1).
So the residual is

    c(u, v) = m (H . T_u, H . T_v) / |H|,    m = r_a r_b / (r_a + r_b)

(r_a = |a - s|, r_b = |b - s|; m = r_a for a direction): two equations in the two surface
parameters. The half-vector form (not the difference of spherical angles of Zeltner et
al. 2020) is smooth and defined on the whole search region: for a refraction
|H| >= |eta_a - eta_b| > 0 everywhere, and no refracted direction has to be formed (one
does not exist under total internal reflection, so the angle form has a branch in the
middle of the region where Newton runs). Its only spurious roots have H parallel to n but
w_a and w_b on the wrong sides of the tangent plane; the side test removes them, and with
the sides right c = 0 is exactly Snell's law (tangential eta w conserved). Under total
internal reflection no unit w_b can balance eta_a |w_a,t| > eta_b, so no root needs it;
the test is repeated explicitly at every root. The lever m (about the distance to the
nearer endpoint) changes no root and no derivative at a root (J -> m J there), but it
keeps Newton's basins wide: without it the unit vector towards a near endpoint saturates
c (|c| -> const once |s - a| exceeds a's distance to the surface) and Newton overshoots
from seeds a few such distances away (a 1 mm under the surface: basins of 0.2 mm).

Where the solutions can lie (the search region). Let L = sum |A_i| |k_i| >= |grad h| (the
slope bound) and [y_lo, y_hi] = level -/+ sum |A_i| (the heights bound). At a solution
H = mu n, so |H_xz| = |H_y| |grad h| <= g := L max|H_y|. The region starts as the
footprint and is cut in a few rounds, each bound computed over the previous round's
region (so each round's region is valid, given the last):
1. Direct caps. On the water side of a refraction the segment is within
   asin(sin(min(theta_other + atan L, 90 deg)) / eta) of the normal (theta_other the
   other segment's largest angle from the vertical over the region; at most the critical
   angle), and the normal within atan L of the vertical; on the air side the same with
   Snell's law the other way (no cap once eta sin(theta_water + atan L) >= 1); a mirror
   leaves within theta_other + 2 atan L of the vertical. Where the cap is below 90 deg
   the solution lies within D_max tan(cap) of the endpoint's foot (D its vertical
   distance), and s lies beyond the endpoint vertically, so an endpoint inside the
   heights' slab only shortens the heights' range. An endpoint inside the slab without
   such a cap has no vertical separation from the solutions: no convexity bound (below).
2. Convexity bound around the flat-water solution. For s at a fixed height y, the optical
   length F(x) = eta_a |a - s| + eta_b |b - s| (- eta_b w_b . s for a direction) is convex
   in the horizontal position x and grad F = -H_xz, so its minimiser is the flat-water
   solution x0(y). Along x0 + t e the curvature of endpoint i's term is at least
   eta_i D_i^2 / (D_i^2 + (P_i0 + t)^2)^(3/2) (P_i0 its horizontal distance from x0),
   whose integral is eta_i [sigma(P_i0 + r) - sigma(P_i0)] with sigma(P) =
   P / sqrt(P^2 + D_i^2) (the sine of the segment's tilt). So at a solution at distance r
   from x0(y): sigma_i0 + g / eta_i >= sigma(P_i0 + r), i.e.
       r <= R_i(y) = D_i(y) [tau(sigma_i0 + g / eta_i) - tau(sigma_i0)],  tau = tan o asin
   (no bound where sigma_i0 + g / eta_i >= 1: grazing). tau is convex, so the bracket
   grows with sigma_i0; sigma_i0(y) (Snell's invariant of the flat solution) is monotone
   in y (differentiate P = D_a tau_a + D_b tau_b at fixed P), so it is largest at y_lo or
   y_hi, D_i at one of them too: R = min_i D_i,max [tau(sigma_i0,max + g / eta_i) -
   tau(sigma_i0,max)]. The flat solutions x0(y) lie on the segment x0(y_lo) x0(y_hi)
   (monotone along the line through the endpoints' feet, or linear for a direction), so
   every solution lies within |x0(y_hi) - x0(y_lo)| / 2 + R of the segment's midpoint.
   max|H_y| comes from the region: the cosines c_i = |w_i,y| lie in
   [cos(theta_i,max), D_max / hypot(D_max, P_min)], and |H_y| = |eta_a c_a - eta_b c_b|
   (refraction) or c_a + c_b (reflection).
The region is the footprint cut to the bounding boxes of these discs, each padded by 1 %
and a relative 1e-4 of the distances (float32 rounding of the flat solution).

Seeds and Newton. A static grid x grid of cell centres covers the region; its spacing
should be at most a quarter of the shortest wavelength 2 pi / max|k| (`undersampled`
says where the static grid is too coarse: the region is too large for it). Newton runs
on all seeds at once for a fixed number of iterations (`iters`): J = dc/d(u, v) (the
waves' first and second derivatives by hand, the rest by forward-mode autodiff), the 2 x 2
system solved in closed form (a Cauchy step on |c|^2 where J is singular to rounding), the
step clamped to a trust region (max(a quarter wave, two seed spacings), and half the
distance to a point endpoint) and the iterate clamped into the region. The search
evaluates the waves with `_sincos` (one shared range reduction: XLA:CPU's sin and cos
dominate the cost otherwise). A seed has converged when |c| <= TOL_FACTOR eps x the
conditioning of c (coordinates over segment lengths, the waves' phase magnitudes,
1 / |H|, times m); measured on 212 roots of folding pools (hard cases included) the true
roots sit at <= 0.09 of that unit and pseudo-roots (near misses of a fold, |c| at a
local minimum) at >= 72: TOL_FACTOR = 2. Converged seeds outside the footprint, with an
endpoint on the wrong side of the tangent plane, or needing total internal reflection
are rejected; the rest are deduplicated greedily (a seed joins the first kept root within
1e-3 of the shortest wave's radian length, widened by both roots' position uncertainty:
the next Newton step plus tol / sigma_min(J)), keeping at most `capacity`; `overflow` is
set when distinct roots remain beyond the capacity.

What a search can miss: a root whose Newton basin holds no seed. Measured against the
float64 brute force of the tests on 400 points 2.5-3.5 m under the shipped pool's four
waves (452 roots, up to 9 per point, folds everywhere; grid 12): 1 missed. Roots within
a few millimetres of a fold come in close pairs of which one may be missed (the
caustic's line, where the generalised geometry term diverges): the estimator that uses
this solver must not rely on finding every root there (MIS with the techniques that
reach those paths otherwise).

Derivatives: the search runs on stopped values; each kept root is passed through
`_root`, a `jax.custom_jvp` that returns one more Newton step and differentiates by the
implicit function theorem, d(u, v) = -J^-1 (dc/dtheta . dtheta) with theta = (water, a,
b, the indices). Its rule evaluates the root through `_root` itself, so derivatives of
any order are the implicit function's (the generalised geometry term is a first
derivative of the root; its gradient needs the second). A hand-rolled fixed-iteration
Newton is used rather than `optimistix.root_find`: a static cost per connection under
`vmap` (no batched while loop), the trust region and the clamping into the region, and
this derivative rule are all one would otherwise wrap around it.

`generalized_geometry` gives the specular chain's Jacobian through the same
differentiable root (`jax.jacfwd` of the root with respect to the perturbed endpoint);
`fresnel_factor` and `radiance_scale` are the interface's Fresnel factor and the eta^2
radiance factor. What the solver does not check: the visibility of the two segments
(a segment may cross the surface or a wall elsewhere; the caller's shadow tests).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _vec as vec
from ._geometry import SOLVER_WAVES_UNROLLED, over_waves, water_height
from ._materials import fresnel_dielectric
from ._scene import Water
from ._vec import Vec3

HALF_PI = 0.5 * math.pi
TOL_FACTOR = 2.0  # residual tolerance in units of eps x the conditioning of c (`_tol`)


class Solutions(NamedTuple):
    """The solutions of one connection (add a leading axis under `vmap`)."""

    s: Vec3  # [K] points on the surface (valid where `valid`; the search's last iterate elsewhere)
    valid: Array  # [K] bool
    count: Array  # int32: number of valid solutions
    overflow: Array  # bool: more distinct solutions were found than `capacity` kept (the
    #                  caller ORs it into its diagnostics: a sticky flag)
    undersampled: Array  # bool: the seed grid is coarser than a quarter of the shortest wave
    residual: Array  # [K] |c| at the returned points (c = m x a sine: a length; inf: unused)
    region: Array  # [4] x0, x1, z0, z1: the searched rectangle (contains every solution)


class _Ends(NamedTuple):
    eta_a: Array  # constraint's indices (both 1 for a reflection)
    eta_b: Array
    a_below: Array  # endpoint in the water
    b_below: Array
    ok: Array  # the endpoints' sides fit the law (refraction: opposite; reflection: same)


# ---------------------------------------------------------------- small helpers
def below(w: Water, p: Vec3) -> Array:
    """p in the water: inside the (closed) footprint and under the surface."""
    fp = w.footprint
    h, _, _ = water_height(w, p.x, p.z, grad=False, unroll=SOLVER_WAVES_UNROLLED)
    return (p.x >= fp[0]) & (p.x <= fp[1]) & (p.z >= fp[2]) & (p.z <= fp[3]) & (p.y < h)


def _ends(w: Water, a: Vec3, b: Vec3, refract: bool, b_is_direction: bool) -> _Ends:
    a_below = below(w, a)
    if b_is_direction:
        b_below = b.y > 0  # light travelling up comes from below
        ok = vec.length(b) > 0
    else:
        b_below = below(w, b)
        ok = jnp.asarray(True)
    ok = ok & w.enabled
    one = jnp.ones_like(a.x)
    if not isinstance(refract, bool):  # a traced law: both, selected
        r = jnp.asarray(refract)
        ok = ok & jnp.where(r, a_below != b_below, a_below == b_below)
        return _Ends(jnp.where(r & a_below, w.ior, one), jnp.where(r & b_below, w.ior, one),
                     a_below, b_below, ok)
    if refract:
        ok = ok & (a_below != b_below)
        eta_a = jnp.where(a_below, w.ior, one)
        eta_b = jnp.where(b_below, w.ior, one)
    else:
        ok = ok & (a_below == b_below)
        eta_a = eta_b = one
    return _Ends(eta_a, eta_b, a_below, b_below, ok)


def _live_etas(w: Water, E: _Ends, refract: bool):
    """The constraint's indices with the water's ior live (differentiable)."""
    if isinstance(refract, bool) and not refract:
        return E.eta_a, E.eta_b
    ea, eb = jnp.where(E.a_below, w.ior, 1.0), jnp.where(E.b_below, w.ior, 1.0)
    if isinstance(refract, bool):
        return ea, eb
    return jnp.where(refract, ea, E.eta_a), jnp.where(refract, eb, E.eta_b)


def _w_b(b: Vec3, s: Vec3, b_is_direction: bool) -> Vec3:
    """Unit direction from s towards b (towards the source for a direction)."""
    return vec.normalize(-b) if b_is_direction else vec.normalize(b - s)


def _sincos(x):
    """(sin x, cos x) in float32 by one shared range reduction and two minimax polynomials
    (Cody-Waite reduction by pi/2 in three parts, Cephes' sinf/cosf coefficients on
    [-pi/4, pi/4]): within 1e-7 of the float64 sine and cosine of the float32 x for
    |x| < 1e4 (measured on 1e6 points; jnp.sin: 3e-8), and some 25 times faster than
    XLA:CPU's sin and cos, which the search evaluates for every wave, seed and iteration.
    Other dtypes: jnp.sin, jnp.cos."""
    if x.dtype != jnp.float32:
        return jnp.sin(x), jnp.cos(x)
    j = jnp.round(x * 0.6366197723675814)
    r = ((x - j * 1.5703125) - j * 4.837512969970703125e-4) - j * 7.54978995489188216e-8
    r2 = r * r
    s = r + r * r2 * (-1.6666654611e-1 + r2 * (8.3321608736e-3 + r2 * -1.9515295891e-4))
    c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166664568298827e-2 + r2 * (-1.388731625493765e-3
                                                                  + r2 * 2.443315711809948e-5))
    q = j.astype(jnp.int32) & 3
    sn = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    cs = jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))
    return sn, cs


def _waves_d2(w: Water, x, z, fast: bool = False):
    """h, (h_u, h_v) and the second derivatives (h_uu, h_uv, h_vv): one sine and one
    cosine per wave, elementwise in `_geometry.over_waves`' rolled loop; `fast`: by
    `_sincos` (the search, on stopped values; the differentiable steps use jnp's)."""
    zero = jnp.zeros(jnp.broadcast_shapes(jnp.shape(x), jnp.shape(z)), jnp.result_type(x, z))

    def wave(a, kx, kz, ph, c):
        h, hx, hz, hxx, hxz, hzz = c
        arg = kx * x + kz * z + ph
        sn, cs = _sincos(arg) if fast else (jnp.sin(arg), jnp.cos(arg))
        sn, cs = a * sn, a * cs
        return (h + sn, hx + kx * cs, hz + kz * cs, hxx - kx * kx * sn, hxz - kx * kz * sn,
                hzz - kz * kz * sn)

    return over_waves(w, wave, (zero + w.level,) + (zero,) * 5, SOLVER_WAVES_UNROLLED)


def _lever(ra, rb, b_is_direction: bool):
    """m = r_a r_b / (r_a + r_b) (r_a for a direction): about the distance to the nearer
    endpoint."""
    return ra if b_is_direction else ra * rb / jnp.maximum(ra + rb, 1e-30)


def _c_of(x, h, z, hx, hz, a: Vec3, b: Vec3, eta_a, eta_b, b_is_direction: bool):
    """c = m (H . T_u, H . T_v) / |H| at s = (x, h, z) with slopes (hx, hz) (module doc)."""
    s = Vec3(x, h, z)
    da = a - s
    ra = vec.length(da)
    if b_is_direction:
        wb, rb = vec.normalize(-b), None
    else:
        db = b - s
        rb = vec.length(db)
        wb = db / jnp.maximum(rb, 1e-30)
    H = da * (eta_a / jnp.maximum(ra, 1e-30)) + wb * eta_b
    inv = _lever(ra, rb, b_is_direction) / jnp.maximum(vec.length(H), 1e-30)
    return (H.x + hx * H.y) * inv, (H.z + hz * H.y) * inv


def _constraint(w: Water, x, z, a: Vec3, b: Vec3, eta_a, eta_b, b_is_direction: bool):
    """c(u, v) = m (H . T_u, H . T_v) / |H| with H = eta_a w_a + eta_b w_b (module doc), as
    a pair of arrays of x's shape (structure of arrays: no short trailing axis)."""
    h, hx, hz = water_height(w, x, z, unroll=SOLVER_WAVES_UNROLLED)
    return _c_of(x, h, z, hx, hz, a, b, eta_a, eta_b, b_is_direction)


def _c_and_jac(w, x, z, a, b, eta_a, eta_b, b_is_direction, fast: bool = False):
    """(c, J, h): c = (c0, c1), J = ((dc0/du, dc0/dv), (dc1/du, dc1/dv)) and the height.
    The waves' part by hand (h's first and second derivatives share one sine and cosine per
    wave), the rest by two forward-mode derivatives of c(s, h_u, h_v) along
    (1, h_u, 0, h_uu, h_uv) and (0, h_v, 1, h_uv, h_vv)."""
    h, hx, hz, hxx, hxz, hzz = _waves_d2(w, x, z, fast)

    def f(x_, h_, z_, hx_, hz_):
        return _c_of(x_, h_, z_, hx_, hz_, a, b, eta_a, eta_b, b_is_direction)

    one, zero = jnp.ones_like(x), jnp.zeros_like(x)
    c, du = jax.jvp(f, (x, h, z, hx, hz), (one, hx, zero, hxx, hxz))
    _, dv = jax.jvp(f, (x, h, z, hx, hz), (zero, hz, one, hxz, hzz))
    return c, ((du[0], dv[0]), (du[1], dv[1])), h


def _newton_delta(c, J, eps):
    """-J^-1 c in closed form; where J is singular to rounding, the Cauchy step on |c|^2/2
    (-g |c|^2 / |g|^2 along g = J^T c, the Gauss-Newton step's length along the gradient)."""
    (j00, j01), (j10, j11) = J
    det = j00 * j11 - j01 * j10
    fro2 = j00 * j00 + j01 * j01 + j10 * j10 + j11 * j11
    ok = jnp.abs(det) > 16.0 * eps * fro2
    sdet = jnp.where(ok, det, 1.0)
    nx = -(j11 * c[0] - j01 * c[1]) / sdet
    nz = -(-j10 * c[0] + j00 * c[1]) / sdet
    gx = j00 * c[0] + j10 * c[1]
    gz = j01 * c[0] + j11 * c[1]
    g2 = jnp.maximum(gx * gx + gz * gz, 1e-30)
    cc = c[0] * c[0] + c[1] * c[1]
    dx = jnp.where(ok, nx, -gx * cc / g2)
    dz = jnp.where(ok, nz, -gz * cc / g2)
    return dx, dz, det, fro2


def _waves(w: Water):
    """(sum |A|, slope bound L = sum |A||k|, max |k| over waves with A != 0)."""
    k = jnp.sqrt(w.kx * w.kx + w.kz * w.kz)
    A = jnp.abs(w.amp)
    if w.n_waves == 0:
        z = jnp.zeros((), w.level.dtype)
        return z, z, z
    return jnp.sum(A), jnp.sum(A * k), jnp.max(jnp.where(A > 0, k, 0.0))


def _tol(w: Water, s: Vec3, a: Vec3, b: Vec3, H_len, eta_a, eta_b, b_is_direction, eps):
    """Residual tolerance at s: TOL_FACTOR eps times the conditioning of c (rounding of
    the coordinate differences over the segment lengths, of the waves' phases, and
    1 / |H|), times c's lever m (module doc: how TOL_FACTOR was chosen)."""
    def inf_norm(p):
        return jnp.maximum(jnp.maximum(jnp.abs(p.x), jnp.abs(p.y)), jnp.abs(p.z))

    sn = inf_norm(s)
    ra = jnp.maximum(vec.length(a - s), 1e-30)
    rb = None if b_is_direction else jnp.maximum(vec.length(b - s), 1e-30)
    scale = 2.0 + (inf_norm(a) + sn) / ra
    if not b_is_direction:
        scale = scale + (inf_norm(b) + sn) / rb
    # sum_i |A_i| k_i (k_i (|s_x| + |s_z|) + |phase_i| + 1), as two sums over the waves
    k = jnp.sqrt(w.kx * w.kx + w.kz * w.kz)
    Ak = jnp.abs(w.amp) * k
    scale = scale + (jnp.abs(s.x) + jnp.abs(s.z)) * jnp.sum(Ak * k) + jnp.sum(
        Ak * (jnp.abs(w.phase0) + 1.0))
    return (TOL_FACTOR * eps * scale * _lever(ra, rb, b_is_direction)
            * jnp.maximum(1.0, (eta_a + eta_b) / jnp.maximum(H_len, 1e-30)))


def _checks(w: Water, x, z, a: Vec3, b: Vec3, E: _Ends, refract: bool, b_is_direction: bool,
            fast: bool = False):
    """(ok, |H|, s): s inside the footprint, a and b on their sides of the tangent plane,
    no total internal reflection needed."""
    fp = w.footprint
    h, hx, hz = _waves_d2(w, x, z, fast)[:3]
    s = Vec3(x, h, z)
    n = vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))
    wa = vec.normalize(a - s)
    wb = _w_b(b, s, b_is_direction)
    ca, cb = vec.dot(n, wa), vec.dot(n, wb)
    ok = (x > fp[0]) & (x < fp[1]) & (z > fp[2]) & (z < fp[3])
    ok = ok & jnp.where(E.a_below, ca < 0, ca > 0) & jnp.where(E.b_below, cb < 0, cb > 0)
    H = wa * E.eta_a + wb * E.eta_b
    # Snell's sine of the far side must be below 1 (E's indices are 1 for a reflection)
    tir_free = (E.eta_a / E.eta_b) ** 2 * (1.0 - ca * ca) < 1.0
    if not isinstance(refract, bool):
        ok = ok & (~jnp.asarray(refract) | tir_free)
    elif refract:
        ok = ok & tir_free
    return ok, vec.length(H), s


# ---------------------------------------------------------------- the search region
def _sin_tilt(P, D):
    """Sine of a segment's tilt from the vertical: P / hypot(P, D) (0 for P = 0)."""
    r = jnp.sqrt(P * P + D * D)
    return jnp.where(P > 0, P / jnp.where(r > 0, r, 1.0), 0.0)


def _tan_of_sin(s):
    """tan(asin(s)), inf for s >= 1."""
    ok = s < 1.0
    return jnp.where(ok, s / jnp.sqrt(jnp.where(ok, 1.0 - s * s, 1.0)), jnp.inf)


def _flat_point(P, Da, Db, eta_a, eta_b, iters: int = 48):
    """Flat-water solution between two points at vertical distances Da, Db from the plane
    and horizontal distance P: P1 in [0, P] with eta_a sin_a(P1) = eta_b sin_b(P - P1)
    (increasing in P1: bisection). Returns (P1, Snell's invariant p = eta sin)."""
    def f(p1):
        return eta_a * _sin_tilt(p1, Da) - eta_b * _sin_tilt(P - p1, Db)

    def body(_, lh):
        lo, hi = lh
        m = 0.5 * (lo + hi)
        pos = f(m) > 0
        return jnp.where(pos, lo, m), jnp.where(pos, m, hi)

    lo, hi = jax.lax.fori_loop(0, iters, body, (jnp.zeros_like(P), P))
    p1 = 0.5 * (lo + hi)
    # the invariant from the endpoint farther from the plane (the other may sit on it)
    p = jnp.where(Da >= Db, eta_a * _sin_tilt(p1, Da), eta_b * _sin_tilt(P - p1, Db))
    return p1, p


def _rect_dist(px, pz, r):
    """(min, max) horizontal distance from (px, pz) to the rectangle r = (x0, x1, z0, z1)."""
    dx = jnp.maximum(jnp.maximum(r[0] - px, px - r[1]), 0.0)
    dz = jnp.maximum(jnp.maximum(r[2] - pz, pz - r[3]), 0.0)
    fx = jnp.maximum(jnp.abs(px - r[0]), jnp.abs(px - r[1]))
    fz = jnp.maximum(jnp.abs(pz - r[2]), jnp.abs(pz - r[3]))
    return jnp.sqrt(dx * dx + dz * dz), jnp.sqrt(fx * fx + fz * fz)


def _region(w: Water, a: Vec3, b: Vec3, E: _Ends, refract: bool, b_is_direction: bool,
            rounds: int = 4):
    """The rectangle x0, x1, z0, z1 that contains every solution (module doc), as [4]:
    the footprint, cut in `rounds` rounds by the direct caps' discs and the convexity
    bound's disc, each computed over the previous round's rectangle."""
    dt = a.x.dtype
    eps = float(jnp.finfo(dt).eps)
    inf = jnp.asarray(jnp.inf, dt)
    A, L, _ = _waves(w)
    y_lo, y_hi = w.level - A, w.level + A
    alpha = jnp.arctan(L)
    ior = w.ior
    eta_a, eta_b = E.eta_a, E.eta_b
    right = HALF_PI * (1.0 - 1e-4)  # caps at or above this bound nothing
    points = ((a, E.a_below),) + (() if b_is_direction else ((b, E.b_below),))

    def D(p, below, y):  # vertical distance from height y to the endpoint, on its side
        return jnp.maximum(jnp.where(below, y - p.y, p.y - y), 0.0)

    def inside(p, below):  # the endpoint lies within the heights' slab
        return jnp.where(below, p.y > y_lo, p.y < y_hi)

    if b_is_direction:
        wb_sun = vec.normalize(-b)
        th_sun = jnp.arccos(jnp.clip(jnp.abs(wb_sun.y), 0.0, 1.0))

    def cap_from(th_other, water_side):
        """Largest angle from the vertical of a segment, given the other segment's."""
        if not refract:
            return th_other + 2.0 * alpha
        inc = jnp.minimum(th_other + alpha, HALF_PI)  # angle to the normal, other side
        if water_side:  # refracted into the water
            return alpha + jnp.arcsin(jnp.sin(inc) / ior)
        sin_t = ior * jnp.sin(inc)  # refracted out into the air
        return jnp.where(sin_t < 1.0, alpha + jnp.arcsin(jnp.minimum(sin_t, 1.0)), HALF_PI)

    def cap_of(th_other, below):
        return jnp.where(below, cap_from(th_other, True), cap_from(th_other, False))

    def one_round(_, carry):
        rect, Y0, Y1, sep = carry
        sep = list(sep)
        # ---- each segment's largest tilt from the vertical over the current region
        rng = []
        for (p, below), sp in zip(points, sep):
            Dl, Dh = D(p, below, Y0), D(p, below, Y1)
            Dmin, Dmax = jnp.minimum(Dl, Dh), jnp.maximum(Dl, Dh)
            Pmin, Pmax = _rect_dist(p.x, p.z, rect)
            th = jnp.where(sp, jnp.arctan2(Pmax, Dmin), HALF_PI)
            rng.append((Dmin, Dmax, Pmin, Pmax, th))
        th_a = rng[0][4]
        th_b = th_sun if b_is_direction else rng[1][4]
        caps = [cap_of(th_b, E.a_below)] + ([] if b_is_direction else [cap_of(th_a, E.b_below)])
        # ---- a capped endpoint has its solutions on its far side: clip the heights
        for i, (p, below) in enumerate(points):
            capped = caps[i] < right
            sep[i] = sep[i] | capped
            Y0 = jnp.where(capped & below, jnp.maximum(Y0, p.y), Y0)
            Y1 = jnp.where(capped & ~below, jnp.minimum(Y1, p.y), Y1)
        Y1 = jnp.maximum(Y0, Y1)
        Ds = [(D(p, below, Y0), D(p, below, Y1)) for p, below in points]
        Da0, Da1 = Ds[0]

        # ---- flat-water solutions at Y0 and Y1 (Snell's invariant sigma_i0 = p / eta_i)
        if b_is_direction:
            sx = -(eta_b / eta_a) * wb_sun.x  # w_a's horizontal part
            sz = -(eta_b / eta_a) * wb_sun.z
            sa = jnp.sqrt(sx * sx + sz * sz)
            flat_ok = sa < 1.0
            ca = jnp.sqrt(jnp.where(flat_ok, 1.0 - sa * sa, 1.0))
            x00, z00 = a.x - sx * Da0 / ca, a.z - sz * Da0 / ca
            x01, z01 = a.x - sx * Da1 / ca, a.z - sz * Da1 / ca
            s0 = [sa]
            flat_ok = flat_ok & sep[0]
            cb_lo = cb_hi = jnp.abs(wb_sun.y)
        else:
            Db0, Db1 = Ds[1]
            ex, ez = b.x - a.x, b.z - a.z
            P = jnp.sqrt(ex * ex + ez * ez)
            ex = jnp.where(P > 0, ex / jnp.where(P > 0, P, 1.0), 1.0)
            ez = jnp.where(P > 0, ez / jnp.where(P > 0, P, 1.0), 0.0)
            p10, inv0 = _flat_point(P, Da0, Db0, eta_a, eta_b)
            p11, inv1 = _flat_point(P, Da1, Db1, eta_a, eta_b)
            x00, z00 = a.x + ex * p10, a.z + ez * p10
            x01, z01 = a.x + ex * p11, a.z + ez * p11
            inv = jnp.maximum(inv0, inv1)
            s0 = [inv / eta_a, inv / eta_b]
            flat_ok = sep[0] & sep[1]
            cb_lo, cb_hi = jnp.cos(rng[1][4]), _cos_max(rng[1], Ds[1])
        ca_lo, ca_hi = jnp.cos(rng[0][4]), _cos_max(rng[0], Ds[0])
        cx, cz = 0.5 * (x00 + x01), 0.5 * (z00 + z01)
        half = 0.5 * jnp.sqrt((x01 - x00) ** 2 + (z01 - z00) ** 2)

        # ---- the convexity bound: g = L max|H_y| over the region
        if refract:
            Hy = jnp.maximum(eta_a * ca_hi - eta_b * cb_lo, eta_b * cb_hi - eta_a * ca_lo)
        else:
            Hy = ca_hi + cb_hi
        g = L * Hy
        R = inf
        for (Dl, Dh), si, eta in zip(Ds, s0, (eta_a, eta_b)):
            Dmx = jnp.maximum(Dl, Dh)
            R = jnp.minimum(R, Dmx * (_tan_of_sin(si + g / eta) - _tan_of_sin(si)))
        R = jnp.where(flat_ok, half + R, inf)

        # ---- cut the rectangle: bounding boxes of the discs, padded (rounding of the flat
        # solution and of the caps' tangents)
        dist = sum(_rect_dist(p.x, p.z, rect)[1] for p, _ in points)
        scale = dist + sum(jnp.maximum(*d) for d in Ds)
        pad = 1e-4 * scale + 64.0 * eps * (jnp.abs(a.x) + jnp.abs(a.z) + scale + 1.0)
        discs = [(cx, cz, R)]
        for i, (p, below) in enumerate(points):
            Dmx = jnp.maximum(*Ds[i])
            discs.append((p.x, p.z, jnp.where(caps[i] < right,
                                               Dmx * jnp.tan(jnp.minimum(caps[i], right)), inf)))
        x0, x1, z0, z1 = rect[0], rect[1], rect[2], rect[3]
        for ox, oz, r in discs:
            rp = r * 1.01 + pad
            x0, x1 = jnp.maximum(x0, ox - rp), jnp.minimum(x1, ox + rp)
            z0, z1 = jnp.maximum(z0, oz - rp), jnp.minimum(z1, oz + rp)
        return jnp.stack([x0, x1, z0, z1]), Y0, Y1, tuple(sep)

    fp = w.footprint
    sep = tuple(~inside(p, below) for p, below in points)  # s on the far side of p vertically
    carry = (jnp.stack([fp[0], fp[1], fp[2], fp[3]]), y_lo, y_hi, sep)
    return jax.lax.fori_loop(0, rounds, one_round, carry)[0]


def _cos_max(rng, Ds):
    """Largest |w_y| of a segment over the region: D_max / hypot(D_max, P_min) (1 where
    both vanish)."""
    _, _, Pmin, _, _ = rng
    Dmax = jnp.maximum(*Ds)
    hyp = jnp.sqrt(Dmax * Dmax + Pmin * Pmin)
    return jnp.where(hyp > 0, Dmax / jnp.where(hyp > 0, hyp, 1.0), 1.0)


# ---------------------------------------------------------------- the solver
def _polish(w, x, z, a, b, eta_a, eta_b, b_is_direction):
    """The root from the stopped search result (x, z), differentiable with respect to the
    parameters (w, a, b, eta_a, eta_b) by the implicit function theorem (`_root`)."""
    sg = jax.lax.stop_gradient
    return _root(sg(x), sg(z), (w, a, b, eta_a, eta_b), b_is_direction)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _root(x, z, params, b_is_direction):
    """One Newton step from the converged (x, z) (values only); derivatives by the rule
    below: d(u, v) = -J^-1 (dc/dparams . dparams) at the root, J = dc/d(u, v). The rule
    evaluates the root through `_root` itself, so derivatives of the rule (second and
    higher orders, e.g. the gradient of the generalised geometry term) use it again."""
    w, a, b, eta_a, eta_b = params
    c, J, _ = _c_and_jac(w, x, z, a, b, eta_a, eta_b, b_is_direction)
    dx, dz, _, _ = _newton_delta(c, J, float(jnp.finfo(x.dtype).eps))
    return x + dx, z + dz


@_root.defjvp
def _root_jvp(b_is_direction, primals, tangents):
    x0, z0, params = primals
    _, _, dparams = tangents
    x, z = _root(x0, z0, params, b_is_direction)
    w, a, b, eta_a, eta_b = params

    def c_of_params(p):
        w_, a_, b_, ea_, eb_ = p
        return _constraint(w_, x, z, a_, b_, ea_, eb_, b_is_direction)

    _, dc = jax.jvp(c_of_params, (params,), (dparams,))
    _, J, _ = _c_and_jac(w, x, z, a, b, eta_a, eta_b, b_is_direction)
    # -J^-1 dc by the closed-form 2 x 2 inverse, linear in dc (reverse mode transposes
    # it); a singular J (a fold: the root has no derivative there) gives 0
    (j00, j01), (j10, j11) = J
    det = j00 * j11 - j01 * j10
    fro2 = j00 * j00 + j01 * j01 + j10 * j10 + j11 * j11
    inv = jnp.where(jnp.abs(det) > 16.0 * float(jnp.finfo(x.dtype).eps) * fro2,
                    1.0 / jnp.where(det != 0, det, 1.0), 0.0)
    return (x, z), (-(j11 * dc[0] - j01 * dc[1]) * inv, -(-j10 * dc[0] + j00 * dc[1]) * inv)


def solve(water: Water, a: Vec3, b: Vec3, *, refract: bool, b_is_direction: bool = False,
          capacity: int = 4, grid: int = 12, iters: int = 12) -> Solutions:
    """Every surface point s with a -> s -> b obeying refraction (`refract`) or mirror
    reflection at the water surface (module doc).

    `a`: a non-delta endpoint (under or above the water: its side is where it lies).
    `b`: a point (on a light, the pinhole), or with `b_is_direction` the unit direction the
    light travels (the sun). A refraction needs the endpoints on opposite sides, a
    reflection on the same side (else no solutions). `capacity`: solutions kept;
    `grid`: the seed grid's side (grid^2 seeds); `iters`: Newton iterations. Static
    arguments; one connection (scalars); vmap over connections. The returned points are
    differentiable with respect to the water's parameters, a and b (the implicit function
    theorem, to any order: `_root`)."""
    dt = a.x.dtype
    eps = float(jnp.finfo(dt).eps)
    sg = jax.lax.stop_gradient
    w0, a0, b0 = sg(water), sg(a), sg(b)
    E = _ends(w0, a0, b0, refract, b_is_direction)
    rect = _region(w0, a0, b0, E, refract, b_is_direction)
    x0, x1, z0, z1 = rect[0], rect[1], rect[2], rect[3]
    nonempty = (x1 >= x0) & (z1 >= z0)
    x1, z1 = jnp.maximum(x0, x1), jnp.maximum(z0, z1)
    _, _, kmax = _waves(w0)
    quarter = jnp.where(kmax > 0, HALF_PI / jnp.where(kmax > 0, kmax, 1.0), jnp.inf)
    hx_, hz_ = (x1 - x0) / grid, (z1 - z0) / grid
    spacing = jnp.maximum(hx_, hz_)
    undersampled = nonempty & E.ok & (spacing > quarter)
    step_max = jnp.maximum(quarter, 2.0 * spacing)

    t = (jnp.arange(grid, dtype=dt) + 0.5)
    sx = jnp.repeat(x0 + t * hx_, grid)
    sz = jnp.tile(z0 + t * hz_, grid)

    def run(x, z):
        def body(_, xz):
            x, z = xz
            c, J, h = _c_and_jac(w0, x, z, a0, b0, E.eta_a, E.eta_b, b_is_direction, True)
            dx, dz, _, _ = _newton_delta(c, J, eps)
            ln = jnp.sqrt(dx * dx + dz * dz)
            # trust region: a quarter wave, and half the distance to a point endpoint (c
            # bends on the scale of that distance: far from the root Newton overshoots)
            s = Vec3(x, h, z)
            lim = jnp.minimum(step_max, 0.5 * vec.length(a0 - s))
            if not b_is_direction:
                lim = jnp.minimum(lim, 0.5 * vec.length(b0 - s))
            f = jnp.minimum(1.0, lim / jnp.maximum(ln, 1e-30))
            return jnp.clip(x + f * dx, x0, x1), jnp.clip(z + f * dz, z0, z1)

        x, z = jax.lax.fori_loop(0, iters, body, (x, z))
        c, J, _ = _c_and_jac(w0, x, z, a0, b0, E.eta_a, E.eta_b, b_is_direction, True)
        ddx, ddz, det, fro2 = _newton_delta(c, J, eps)
        ok, H_len, s = _checks(w0, x, z, a0, b0, E, refract, b_is_direction, True)
        res = jnp.sqrt(c[0] * c[0] + c[1] * c[1])
        tol = _tol(w0, s, a0, b0, H_len, E.eta_a, E.eta_b, b_is_direction, eps)
        # position uncertainty of the root: the next Newton step (the error left, near a
        # root) and tol / sigma_min(J) <= tol |J|_F / |det| (what the tolerance allows)
        unc = jnp.sqrt(ddx * ddx + ddz * ddz) + tol * jnp.sqrt(fro2) / jnp.maximum(
            jnp.abs(det), 1e-30)
        return x, z, ok & (res <= tol), unc

    xs, zs, good, unc = jax.vmap(run)(sx, sz)
    good = good & E.ok & nonempty
    unc = jnp.where(good, jnp.minimum(unc, 1e3), 0.0)

    # ---- deduplicate: greedy, the first remaining converged seed becomes a root
    ell = jnp.where(kmax > 0, 1.0 / jnp.where(kmax > 0, kmax, 1.0), jnp.inf)
    tol_d = 1e-3 * jnp.minimum(ell, jnp.maximum(x1 - x0, z1 - z0) + 1e-30) + 64.0 * eps * (
        jnp.abs(x0) + jnp.abs(x1) + jnp.abs(z0) + jnp.abs(z1) + 1.0)
    left = good
    idx, kept = [], []
    for _ in range(capacity):
        i = jnp.argmax(left)
        has = left[i]
        r = tol_d + 4.0 * (unc[i] + unc)
        near = (xs - xs[i]) ** 2 + (zs - zs[i]) ** 2 <= r * r
        left = left & ~(near & has)
        idx.append(i)
        kept.append(has)
    overflow = jnp.any(left)
    idx = jnp.stack(idx)
    kept = jnp.stack(kept)

    # ---- differentiable roots: two Newton steps from the stopped roots, live parameters
    eta_a, eta_b = _live_etas(water, E, refract)

    def finish(x, z, keep):
        x, z = _polish(water, x, z, a, b, eta_a, eta_b, b_is_direction)
        h, _, _ = water_height(water, x, z, unroll=SOLVER_WAVES_UNROLLED)
        xs_, zs_ = sg(x), sg(z)
        c, _, _ = _c_and_jac(w0, xs_, zs_, a0, b0, E.eta_a, E.eta_b, b_is_direction)
        ok, H_len, s = _checks(w0, xs_, zs_, a0, b0, E, refract, b_is_direction)
        res = jnp.sqrt(c[0] * c[0] + c[1] * c[1])
        tol = _tol(w0, s, a0, b0, H_len, E.eta_a, E.eta_b, b_is_direction, eps)
        return Vec3(x, h, z), keep & ok & (res <= tol), jnp.where(keep, res, jnp.inf)

    s, valid, res = jax.vmap(finish)(xs[idx], zs[idx], kept)
    return Solutions(s, valid, jnp.sum(valid.astype(jnp.int32)), overflow, undersampled, res,
                     jnp.stack([x0, x1, z0, z1]))


class Near(NamedTuple):
    """The root Newton reaches from one seed (`solve_near`)."""

    s: Vec3  # the point on the surface (the last iterate where not `valid`)
    valid: Array  # bool: a root (residual within tolerance, the law's sides, no TIR)
    residual: Array  # |c| at s


def solve_near(water: Water, a: Vec3, b: Vec3, x, z, *, refract,
               b_is_direction: bool = False, iters: int = 8) -> Near:
    """The root of a -> s -> b that Newton reaches from the one seed (x, z): `solve`'s
    iteration (trust region of a quarter of the shortest wave and half the distance to a
    point endpoint), clamped into the footprint, with its convergence test and its
    differentiable polish. A deterministic function of (a, b, seed): an estimator that
    counts only the roots it returns stays unbiased if every other technique knows the
    same function (`_glints`: the seed is fixed per pixel). `refract` may be traced (a
    bool array: the law chosen per connection; so may `generalized_geometry`'s,
    `fresnel_factor`'s and `radiance_scale`'s). Scalars; vmap over connections."""
    dt = a.x.dtype
    eps = float(jnp.finfo(dt).eps)
    sg = jax.lax.stop_gradient
    w0, a0, b0 = sg(water), sg(a), sg(b)
    E = _ends(w0, a0, b0, refract, b_is_direction)
    fp = w0.footprint
    _, _, kmax = _waves(w0)
    quarter = jnp.where(kmax > 0, HALF_PI / jnp.where(kmax > 0, kmax, 1.0), jnp.inf)

    def body(_, xz):
        x, z = xz
        c, J, h = _c_and_jac(w0, x, z, a0, b0, E.eta_a, E.eta_b, b_is_direction, True)
        dx, dz, _, _ = _newton_delta(c, J, eps)
        ln = jnp.sqrt(dx * dx + dz * dz)
        s = Vec3(x, h, z)
        lim = jnp.minimum(quarter, 0.5 * vec.length(a0 - s))
        if not b_is_direction:
            lim = jnp.minimum(lim, 0.5 * vec.length(b0 - s))
        f = jnp.minimum(1.0, lim / jnp.maximum(ln, 1e-30))
        return jnp.clip(x + f * dx, fp[0], fp[1]), jnp.clip(z + f * dz, fp[2], fp[3])

    x, z = jax.lax.fori_loop(0, iters, body, (sg(jnp.asarray(x, dt)), sg(jnp.asarray(z, dt))))
    p = polished(water, a, b, x, z, refract=refract, b_is_direction=b_is_direction, E=E)
    xp, h, zp = p.x, p.y, p.z
    xs_, zs_ = sg(xp), sg(zp)
    c, _, _ = _c_and_jac(w0, xs_, zs_, a0, b0, E.eta_a, E.eta_b, b_is_direction)
    ok, H_len, s = _checks(w0, xs_, zs_, a0, b0, E, refract, b_is_direction)
    res = jnp.sqrt(c[0] * c[0] + c[1] * c[1])
    tol = _tol(w0, s, a0, b0, H_len, E.eta_a, E.eta_b, b_is_direction, eps)
    return Near(Vec3(xp, h, zp), E.ok & ok & (res <= tol), res)


def polished(water: Water, a: Vec3, b: Vec3, x, z, *, refract, b_is_direction: bool = False,
             E: _Ends | None = None) -> Vec3:
    """The surface point one Newton step from a converged root (x, z) (stopped values), with
    its implicit-function derivatives (`_root`): a root the search found, made
    differentiable with respect to the water, a and b. Scalars; vmap over connections."""
    if E is None:
        sg = jax.lax.stop_gradient
        E = _ends(sg(water), sg(a), sg(b), refract, b_is_direction)
    eta_a, eta_b = _live_etas(water, E, refract)
    xp, zp = _polish(water, x, z, a, b, eta_a, eta_b, b_is_direction)
    h, _, _ = water_height(water, xp, zp, unroll=SOLVER_WAVES_UNROLLED)
    return Vec3(xp, h, zp)


def flat_seed(water: Water, a: Vec3, b: Vec3, b_is_direction: bool = False):
    """(x, z): the refraction point of a -> b on the water's mean level (flat water; a and b
    on opposite sides; with `b_is_direction`, b the direction the sun's light travels and a
    under the water), the natural seed of `solve_near` for a connection whose root lies
    near it (the waves' slopes move it by a fraction of the endpoints' depths). The seed is
    clamped into the footprint."""
    sg = jax.lax.stop_gradient
    w, a, b = sg(water), sg(a), sg(b)
    fp = w.footprint
    Da = jnp.abs(a.y - w.level)
    if b_is_direction:  # the refracted sun ray through a, traced back up to the level
        d = vec.normalize(b)
        sin_i = jnp.sqrt(jnp.maximum(d.x * d.x + d.z * d.z, 0.0))
        sin_t = sin_i / w.ior
        tan_t = sin_t / jnp.sqrt(jnp.maximum(1.0 - sin_t * sin_t, 1e-30))
        h = jnp.where(sin_i > 0, 1.0 / jnp.where(sin_i > 0, sin_i, 1.0), 0.0)
        x, z = a.x - d.x * h * Da * tan_t, a.z - d.z * h * Da * tan_t
        return jnp.clip(x, fp[0], fp[1]), jnp.clip(z, fp[2], fp[3])
    a_below = below(w, a)
    Db = jnp.abs(b.y - w.level)
    eta_a = jnp.where(a_below, w.ior, 1.0)
    eta_b = jnp.where(a_below, 1.0, w.ior)
    dx, dz = b.x - a.x, b.z - a.z
    P = jnp.sqrt(dx * dx + dz * dz)
    p1, _ = _flat_point(P, Da, Db, eta_a, eta_b)
    f = jnp.where(P > 0, p1 / jnp.where(P > 0, P, 1.0), 0.0)
    return jnp.clip(a.x + f * dx, fp[0], fp[1]), jnp.clip(a.z + f * dz, fp[2], fp[3])


# ---------------------------------------------------------------- the specular chain's Jacobian
def _root_fn(water: Water, a: Vec3, s: Vec3, b: Vec3, refract: bool, b_is_direction: bool):
    """The root near s (a point) as a differentiable function of the endpoints (a, b)."""
    sg = jax.lax.stop_gradient
    E = _ends(sg(water), sg(a), sg(b), refract, b_is_direction)
    eta_a, eta_b = _live_etas(water, E, refract)

    def root(a_, b_):
        x, z = _polish(water, s.x, s.z, a_, b_, eta_a, eta_b, b_is_direction)
        h, _, _ = water_height(water, x, z, unroll=SOLVER_WAVES_UNROLLED)
        return Vec3(x, h, z)

    return root


def _tangent_frame(n: Vec3) -> tuple[Vec3, Vec3]:
    return vec.onb(vec.normalize(n))


def _area_of(f, t1: Vec3, t2: Vec3, p: Vec3):
    """|df/du x df/dv| for f(p + u t1 + v t2) at u = v = 0 (f -> Vec3)."""
    def g(uv):
        q = f(p + t1 * uv[0] + t2 * uv[1])
        return jnp.stack([q.x, q.y, q.z])

    J = jax.jacfwd(g)(jnp.zeros((2,), p.x.dtype))
    cr = vec.cross(vec.from_array(J[:, 0]), vec.from_array(J[:, 1]))
    return vec.length(cr)


def generalized_geometry(water: Water, a: Vec3, s: Vec3, b: Vec3, *, refract: bool,
                         b_is_direction: bool = False, n_a: Vec3 | None = None,
                         n_b: Vec3 | None = None) -> Array:
    """The specular chain's generalised geometry term at the solution s of a -> s -> b.

    - b a point on an area light with unit normal `n_b`:
          G_gen(a <-> b) = |cos theta_a| |d w_a / d A_b|
      the projected solid angle at a per unit area at b through the chain (w_a =
      normalize(s - a); |cos theta_a| with `n_a`, 1 for a medium vertex): the contribution
      of the solution is f(a) T L_e(b) (eta_a / eta_b)^2 G_gen / p_A(b).
    - b a point light (`n_b` None): d omega_b / d A_a, the solid angle at b per unit area
      at a (on a's surface with normal `n_a`; for a medium vertex, on the plane across the
      ray): the irradiance at a is I T d omega_b / d A_a.
    - b the sun's direction: d A_perp / d A_a, the beam's cross-section per unit area at a
      (the irradiance at a per unit sun irradiance, before the transmittance T): the
      float64 ray-mapping reference's |cos theta_i| T / |det(d a / d s)| without T.
    `s`: a solution (`solve`'s; only its value is used). The Jacobians are `jax.jacfwd`
    of the root moved with the perturbed endpoint (`_root`: the implicit function
    theorem); G is differentiable in turn (second derivatives of the root)."""
    root = _root_fn(water, a, s, b, refract, b_is_direction)
    sg = jax.lax.stop_gradient
    if not b_is_direction and n_b is not None:
        t1, t2 = _tangent_frame(sg(n_b))

        def wa(bp):
            return vec.normalize(root(a, bp) - a)

        dw = _area_of(wa, t1, t2, sg(b))
        w_a = vec.normalize(root(a, b) - a)  # the live root: cos_a's derivatives too
        cos_a = jnp.ones_like(dw) if n_a is None else jnp.abs(vec.dot(vec.normalize(n_a), w_a))
        return cos_a * dw
    # perturb a on its surface (or across the ray at a medium vertex)
    na = vec.normalize(sg(s) - sg(a)) if n_a is None else n_a
    t1, t2 = _tangent_frame(sg(na))
    if b_is_direction:
        d = vec.normalize(b)

        def q(ap):  # the entry point projected on the plane across the beam
            sp = root(ap, b)
            return sp - d * vec.dot(sp, d)

        return _area_of(q, t1, t2, sg(a))

    def wb(ap):
        return vec.normalize(root(ap, b) - b)

    return _area_of(wb, t1, t2, sg(a))


# ---------------------------------------------------------------- interface factors
def fresnel_factor(water: Water, a: Vec3, s: Vec3, b: Vec3, *, refract: bool,
                   b_is_direction: bool = False) -> Array:
    """Fresnel transmittance T (refraction) or reflectance R (reflection) at the solution s
    (exact unpolarised Fresnel, `_materials.fresnel_dielectric`)."""
    E = _ends(water, jax.lax.stop_gradient(a), jax.lax.stop_gradient(b), refract,
              b_is_direction)
    _, hx, hz = water_height(water, s.x, s.z, unroll=SOLVER_WAVES_UNROLLED)
    n = vec.normalize(Vec3(-hx, jnp.ones_like(hx), -hz))
    cos_b = vec.dot(n, _w_b(b, s, b_is_direction))
    ior = water.ior
    side = jnp.where(E.b_below, ior, 1.0)
    other = jnp.where(refract, jnp.where(E.a_below, ior, 1.0), jnp.where(E.b_below, 1.0, ior))
    R, _ = fresnel_dielectric(cos_b, other / side)
    return jnp.where(refract, 1.0 - R, R)


def radiance_scale(water: Water, a: Vec3, b: Vec3, *, refract: bool,
                   b_is_direction: bool = False) -> Array:
    """(eta_a / eta_b)^2 for a refraction (the n^2 law of radiance arriving at a from b's
    medium), 1 for a reflection."""
    if isinstance(refract, bool) and not refract:
        return jnp.ones_like(a.x)
    E = _ends(water, jax.lax.stop_gradient(a), jax.lax.stop_gradient(b), refract,
              b_is_direction)
    eta_a = jnp.where(E.a_below, water.ior, 1.0)
    eta_b = jnp.where(E.b_below, water.ior, 1.0)
    return jnp.where(refract, (eta_a / eta_b) ** 2, 1.0)
