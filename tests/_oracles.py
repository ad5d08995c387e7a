"""Independent NumPy references for the geometry and sampling tests.

Nothing here imports `jaxvcm`: the references are written from the mathematical
definitions (closed forms in 80-bit long double where cheap, dense sampling + brentq for
the heightfield) so that a shared mistake between a kernel and its oracle is unlikely.
Ray inputs are always the *rounded* values the kernel saw (float32 arrays promoted to
float64/long double), so a reference is exact for the kernel's inputs and a comparison
measures only the kernel's own arithmetic error.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq
from scipy.stats import chi2

LD = np.longdouble


# ----------------------------------------------------------------------------- vectors
def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_unit(rng, n):
    return unit(rng.normal(size=(n, 3)))


def tangent_frame(n):
    """Two unit vectors orthogonal to the unit rows of n (and to each other)."""
    n = np.atleast_2d(n)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    s = unit(np.cross(helper, n))
    t = np.cross(n, s)
    return s, t


def direction_at_angle(rng, axis, cos_lo, cos_hi):
    """Unit directions whose cosine with the unit rows of `axis` is uniform in [cos_lo, cos_hi]."""
    n = axis.shape[0]
    c = rng.uniform(cos_lo, cos_hi, n)
    s = np.sqrt(np.maximum(0.0, 1.0 - c * c))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    t1, t2 = tangent_frame(axis)
    side = np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2
    return unit(c[:, None] * axis + s[:, None] * side)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


# ----------------------------------------------------------------------------- parallelograms
def ref_parallelogram(o, d, p0, e1, e2, tmin=0.0, tmax=np.inf):
    """Exact hit of rays (o, d) [N,3] with parallelograms p0 + u e1 + v e2 [N,3] each.

    Solved in long double with the dual basis of (e1, e2) in their plane, so that
    non-orthogonal edges are handled: q = o + t d - p0 = u e1 + v e2 gives
    u = ((q x e2) . n) / |n|^2 and v = ((e1 x q) . n) / |n|^2 with n = e1 x e2.
    Returns (t with inf on a miss, u, v, cos) where cos = |d . n| / (|d| |n|).
    """
    o, d, p0, e1, e2 = (np.asarray(a, LD) for a in (o, d, p0, e1, e2))
    n = np.cross(e1, e2)
    nn = _dot(n, n)
    denom = _dot(d, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _dot(p0 - o, n) / denom
        q = o + d * t[:, None] - p0
        u = _dot(np.cross(q, e2), n) / nn
        v = _dot(np.cross(e1, q), n) / nn
    ok = (denom != 0) & (t > tmin) & (t < tmax) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    cos = np.abs(denom) / np.sqrt(_dot(d, d) * nn)
    return (np.where(ok, t, np.inf).astype(np.float64), u.astype(np.float64),
            v.astype(np.float64), cos.astype(np.float64))


# ----------------------------------------------------------------------------- spheres
def ref_sphere_roots(o, d, c, r):
    """Both roots (t_lo <= t_hi, nan if the line misses) of |o + t d - c| = r, long double.

    |d| need not be 1 (rounded directions): a t^2 + 2 b t + k = 0 with a = |d|^2,
    b = (o - c) . d, k = |o - c|^2 - r^2, solved with the cancellation-free pairing.
    """
    o, d, c = (np.asarray(a, LD) for a in (o, d, c))
    r = np.asarray(r, LD)
    oc = o - c
    a = _dot(d, d)
    b = _dot(oc, d)
    k = _dot(oc, oc) - r * r
    disc = b * b - a * k
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        qq = -(b + np.copysign(sq, b))
        r1 = qq / a
        r2 = k / qq
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    lo = np.where(disc >= 0, lo, np.nan)
    hi = np.where(disc >= 0, hi, np.nan)
    # cosine between the ray and the surface normal at the hits: sqrt(disc) / (|d| r)
    cos = np.sqrt(np.maximum(disc, 0)) / (np.sqrt(a) * r)
    return lo.astype(np.float64), hi.astype(np.float64), cos.astype(np.float64)


def ref_sphere(o, d, c, r, tmin=0.0, tmax=np.inf):
    lo, hi, cos = ref_sphere_roots(o, d, c, r)
    t = np.where(lo > tmin, lo, hi)
    t = np.where(np.isfinite(t) & (t > tmin) & (t < tmax), t, np.inf)
    return t, cos


# ----------------------------------------------------------------------------- open box
def basin_faces(lo, hi, tops):
    """The basin as axis-aligned faces: (axis, plane value, inward normal, (a1, lo1, hi1),
    (a2, lo2, hi2)) - floor + walls at x0, x1, z0, z1 whose tops are `tops`."""
    x0, y0, z0 = lo
    x1, _, z1 = hi
    return [
        (1, y0, (0, 1, 0), (0, x0, x1), (2, z0, z1)),
        (0, x0, (1, 0, 0), (1, y0, tops[0]), (2, z0, z1)),
        (0, x1, (-1, 0, 0), (1, y0, tops[1]), (2, z0, z1)),
        (2, z0, (0, 0, 1), (0, x0, x1), (1, y0, tops[2])),
        (2, z1, (0, 0, -1), (0, x0, x1), (1, y0, tops[3])),
    ]


def ref_basin(o, d, faces, tmin=0.0, tmax=np.inf):
    """Closest hit of the open box: (t, face index or -1, distance of the hit point to the
    nearest edge of its face, |cos| between ray and face normal)."""
    o, d = np.asarray(o, LD), np.asarray(d, LD)
    n = o.shape[0]
    best = np.full(n, np.inf)
    face = np.full(n, -1)
    margin = np.zeros(n)
    cosv = np.zeros(n)
    dn = np.sqrt(_dot(d, d))
    for fi, (ax, val, _, (a1, l1, h1), (a2, l2, h2)) in enumerate(faces):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (LD(val) - o[:, ax]) / d[:, ax]
            p1 = o[:, a1] + t * d[:, a1]
            p2 = o[:, a2] + t * d[:, a2]
        ok = ((d[:, ax] != 0) & (t > tmin) & (t < tmax)
              & (p1 >= l1) & (p1 <= h1) & (p2 >= l2) & (p2 <= h2))
        t64 = np.where(ok, t, np.inf).astype(np.float64)
        closer = t64 < best
        m = np.minimum.reduce([p1 - l1, h1 - p1, p2 - l2, h2 - p2]).astype(np.float64)
        best = np.where(closer, t64, best)
        face = np.where(closer, fi, face)
        margin = np.where(closer, m, margin)
        cosv = np.where(closer, (np.abs(d[:, ax]) / dn).astype(np.float64), cosv)
    return best, face, margin, cosv


# ----------------------------------------------------------------------------- heightfield
# The water surface y = h(x, z) = level + sum_i A_i sin(kx_i x + kz_i z + phase_i), in float64;
# `waves` is [W, 4]: rows (A, kx, kz, phase). This is the one NumPy heightfield of the tests
# (the geometry tests, the caustic reference, the join pdfs, the peer's water mesh).
def waves_of(water) -> np.ndarray:
    """[W, 4] float64 rows (A, kx, kz, phase) of a scene's water (its amp, kx, kz and
    phase0 arrays)."""
    return np.stack([np.asarray(a, np.float64).reshape(-1)
                     for a in (water.amp, water.kx, water.kz, water.phase0)], 1)


def heightfield(waves, level, x, z):
    """(h, dh/dx, dh/dz) at (x, z), float64, elementwise (the analytic gradient; scalars
    for scalar x, z)."""
    x, z = np.asarray(x, np.float64), np.asarray(z, np.float64)
    h = np.full(np.broadcast(x, z).shape, float(level))
    hx, hz = np.zeros_like(h), np.zeros_like(h)
    for A, kx, kz, ph in np.asarray(waves, np.float64).reshape(-1, 4):
        arg = kx * x + kz * z + ph
        h = h + A * np.sin(arg)
        c = A * np.cos(arg)
        hx = hx + kx * c
        hz = hz + kz * c
    return h[()], hx[()], hz[()]


def heightfield_normal(waves, level, x, z) -> np.ndarray:
    """Unit upward normal (-h_x, 1, -h_z) / |.| at (x, z): [..., 3] float64."""
    _, hx, hz = heightfield(waves, level, x, z)
    n = np.stack([-hx, np.ones_like(hx), -hz], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def water_h(waves, level, x, z):
    """h(x, z) alone."""
    return heightfield(waves, level, x, z)[0]


def water_grad_fd(waves, level, x, z, step=1e-6):
    """Central finite differences of h: truncation step^2 |h'''| / 6 ~ 1e-11, rounding
    eps |h| / step ~ 1e-10: the gradient is good to ~1e-9."""
    hx = (water_h(waves, level, x + step, z) - water_h(waves, level, x - step, z)) / (2 * step)
    hz = (water_h(waves, level, x, z + step) - water_h(waves, level, x, z - step)) / (2 * step)
    return hx, hz


def box_interval(o, d, lo, hi, tmin=0.0, tmax=np.inf):
    """Parameter interval of the ray inside the closed box [lo, hi] (float64, one ray)."""
    t0, t1 = float(tmin), float(tmax)
    for a in range(3):
        if d[a] == 0.0:
            if not lo[a] <= o[a] <= hi[a]:
                return np.inf, -np.inf
            continue
        ta, tb = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return t0, t1


class WaterRef:
    """Crossings of one ray with the heightfield over the footprint.

    The surface lies in the slab level -/+ sum|A|, so all crossings of the footprint
    column lie in [t0, t1] = ray  box(footprint x slab). f(t) = o_y + t d_y - h(x(t), z(t))
    is sampled densely in float64 - spacing 1e-5 m, between 20k and 200k samples, in
    chunks that stop once the first crossing and `scan_to` are covered - and every sign
    change is refined with brentq. Two crossings closer than 1e-5 m would be missed by the
    reference: such a pair dips at most |f''| (5e-6)^2 / 2 < 1e-10 m across the surface,
    far below float32 resolution, so the reference is exact for this purpose.
    """

    def __init__(self, waves, level, footprint):
        self.waves = np.asarray(waves, np.float64)
        self.level = float(level)
        fp = np.asarray(footprint, np.float64)
        a = np.abs(self.waves[:, 0]).sum()
        self.lo = np.array([fp[0], self.level - a, fp[2]])
        self.hi = np.array([fp[1], self.level + a, fp[3]])

    def f(self, o, d, t):
        return o[1] + t * d[1] - water_h(self.waves, self.level, o[0] + t * d[0], o[2] + t * d[2])

    def df(self, o, d, t, step=1e-7):
        return (self.f(o, d, t + step) - self.f(o, d, t - step)) / (2 * step)

    def roots(self, o, d, tmin=0.0, tmax=np.inf, *, first_only=True, scan_to=None,
              spacing=1e-5, nmin=20_000, nmax=200_000, chunk=20_000):
        """Sorted crossings with t in (tmin, tmax); with first_only the scan stops after the
        first crossing (and after `scan_to(t_first)` if given). Returns (roots, (t0, t1))."""
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        t0, t1 = box_interval(o, d, self.lo, self.hi, tmin, tmax)
        if not t0 < t1:
            return np.array([]), (t0, t1)
        n = int(np.clip((t1 - t0) / spacing, nmin, nmax))
        ts_all = np.linspace(t0, t1, n + 1)
        out = []
        stop = np.inf
        prev_t, prev_s = None, None
        f = lambda t: self.f(o, d, t)  # noqa: E731
        for s0 in range(0, n + 1, chunk):
            ts = ts_all[s0:s0 + chunk + 1]
            if ts[0] > stop:
                break
            fs = f(ts)
            sg = fs >= 0
            if prev_s is not None and prev_s != sg[0]:
                out.append(brentq(f, prev_t, ts[0], xtol=1e-14, rtol=1e-15))
            idx = np.nonzero(sg[1:] != sg[:-1])[0]
            for i in idx:
                out.append(brentq(f, ts[i], ts[i + 1], xtol=1e-14, rtol=1e-15))
            prev_t, prev_s = ts[-1], sg[-1]
            if first_only and out and not np.isfinite(stop):
                stop = out[0] if scan_to is None else max(out[0], scan_to(out[0], (t0, t1)))
        out = np.array(sorted(out))
        if first_only and np.isfinite(stop):
            out = out[out <= stop]
        return out, (t0, t1)


# ----------------------------------------------------------------------------- quadrature
def gauss_legendre(edges, n):
    """Nodes [B, n] and weights [B, n] of an n-point Gauss-Legendre rule on each bin."""
    x, w = np.polynomial.legendre.leggauss(n)
    edges = np.asarray(edges, np.float64)
    a, b = edges[:-1, None], edges[1:, None]
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


def bin_integrals_2d(pdf, edges1, edges2, n=8):
    """[B1, B2] integrals of pdf(x1, x2) (vectorised over float64 arrays) over the bins."""
    x1, w1 = gauss_legendre(edges1, n)
    x2, w2 = gauss_legendre(edges2, n)
    X1 = x1[:, None, :, None]
    X2 = x2[None, :, None, :]
    vals = np.asarray(pdf(*np.broadcast_arrays(X1, X2)), np.float64)
    return np.einsum("ijkl,ik,jl->ij", vals, w1, w2)


def bin_integrals_1d(pdf, edges, n=16):
    x, w = gauss_legendre(edges, n)
    return np.sum(np.asarray(pdf(x), np.float64) * w, axis=-1)


# ----------------------------------------------------------------------------- chi-square
def chi2_gof(observed, expected, min_expected=5.0):
    """Pearson chi-square goodness of fit. Bins are visited from the smallest expected
    count up; bins with expected < min_expected are pooled until the pool reaches it (a
    last, still-small pool is merged into the smallest regular bin). A sample in a bin
    of expected count zero is an immediate failure (p = 0). Returns (stat, dof, p)."""
    obs = np.asarray(observed, np.float64).ravel()
    exp = np.asarray(expected, np.float64).ravel()
    if np.any((exp <= 0) & (obs > 0)):
        return np.inf, 0, 0.0
    keep = exp > 0
    obs, exp = obs[keep], exp[keep]
    order = np.argsort(exp)
    obs, exp = obs[order], exp[order]
    mo, me = [], []
    po = pe = 0.0
    for o_, e_ in zip(obs, exp):
        if e_ >= min_expected and pe == 0.0:
            mo.append(o_)
            me.append(e_)
            continue
        po += o_
        pe += e_
        if pe >= min_expected:
            mo.append(po)
            me.append(pe)
            po = pe = 0.0
    if pe > 0:
        if me:
            mo[0] += po
            me[0] += pe
        else:
            mo, me = [po], [pe]
    mo, me = np.array(mo), np.array(me)
    stat = float(np.sum((mo - me) ** 2 / me))
    dof = len(me) - 1
    return stat, dof, float(chi2.sf(stat, dof)) if dof > 0 else 1.0
