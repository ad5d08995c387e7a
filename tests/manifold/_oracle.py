"""Float64 NumPy oracle of one specular vertex on the water surface, written from the
forward optics (no half vector, no jaxvcm): a light ray leaves b (or arrives along the
sun's direction), meets the surface at s, refracts (Snell, with total internal
reflection) or reflects there, and goes on; s is a solution iff that ray passes through
a. Brute force: the landing map s(u, v) -> the ray's crossing of the horizontal plane
through a is sampled on a fine triangulated grid of the whole footprint (1/60 of the
shortest wavelength, at most 1 cm); every triangle whose image contains a's foot, and
every local minimum of the landing distance below 5 cm, starts a float64 Newton
refinement; around roots near a fold (landing Jacobian |det| < 0.05) rings of starting
points look for the fold's partner root (two roots closer than a grid cell); converged
roots are deduplicated. Checked against the solver on 400 points under folding waves:
the oracle found every root the solver found (the solver's extra roots, verified by
refinement, first revealed the fold pairs that the triangles alone missed)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._oracles import heightfield, tangent_frame


@dataclass(frozen=True)
class Config:
    waves: np.ndarray  # [W, 4] rows (A, kx, kz, phase)
    level: float
    ior: float
    footprint: tuple  # x0, x1, z0, z1
    a: np.ndarray  # [3]
    b: np.ndarray  # [3] point, or the direction light travels
    refract: bool
    b_dir: bool

    def below(self, p):
        x0, x1, z0, z1 = self.footprint
        h = heightfield(self.waves, self.level, p[0], p[2])[0]
        return bool(x0 <= p[0] <= x1 and z0 <= p[2] <= z1 and p[1] < h)

    @property
    def a_below(self):
        return self.below(self.a)

    @property
    def b_below(self):
        return bool(self.b[1] > 0) if self.b_dir else self.below(self.b)

    @property
    def etas(self):
        n = self.ior
        if not self.refract:
            e = n if self.a_below else 1.0
            return e, e
        return (n if self.a_below else 1.0), (n if self.b_below else 1.0)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def trace(cfg: Config, u, v, a=None, b=None):
    """Forward optics at surface points (u, v) [...]: (landing point on the plane y = a_y
    minus a's foot [..., 2], ok [...], s [..., 3], outgoing direction [..., 3])."""
    a = cfg.a if a is None else np.asarray(a, float)
    b = cfg.b if b is None else np.asarray(b, float)
    u, v = np.asarray(u, float), np.asarray(v, float)
    h, hx, hz = heightfield(cfg.waves, cfg.level, u, v)
    s = np.stack(np.broadcast_arrays(u, h, v), -1)
    n = _unit(np.stack([-hx, np.ones_like(hx), -hz], -1))
    d = np.broadcast_to(_unit(b), s.shape) if cfg.b_dir else _unit(s - b)
    dn = np.sum(d * n, -1)
    # light from b's side: from above it travels against n, from below along n
    ok = dn > 0 if cfg.b_below else dn < 0
    ns = n * np.where(dn < 0, 1.0, -1.0)[..., None]  # normal on the incidence side
    ci = np.abs(dn)
    eta_a, eta_b = cfg.etas
    if cfg.refract:
        eta = eta_a / eta_b  # n_t / n_i
        sin2t = (1.0 - ci * ci) / eta**2
        ok &= sin2t < 1.0
        ct = np.sqrt(np.maximum(0.0, 1.0 - sin2t))
        t = d / eta + ns * (ci / eta - ct)[..., None]
    else:
        t = d + 2.0 * ci[..., None] * ns
    t = _unit(t)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (a[1] - s[..., 1]) / t[..., 1]
    ok &= np.isfinite(lam) & (lam > 0)
    lam = np.where(ok, lam, 0.0)
    land = s[..., [0, 2]] + t[..., [0, 2]] * lam[..., None] - a[[0, 2]]
    return land, ok, s, t


def refine(cfg: Config, uv, a=None, b=None, iters=60, tol=1e-11):
    """Newton on the landing map from starting points uv [M, 2] (central-difference
    Jacobian, step 1e-7): (roots [M, 2], converged [M])."""
    uv = np.array(uv, float).reshape(-1, 2)
    hstep = 1e-7
    conv = np.zeros(len(uv), bool)
    for _ in range(iters):
        F, ok, _, _ = trace(cfg, uv[:, 0], uv[:, 1], a, b)
        Fx1 = trace(cfg, uv[:, 0] + hstep, uv[:, 1], a, b)[0]
        Fx0 = trace(cfg, uv[:, 0] - hstep, uv[:, 1], a, b)[0]
        Fz1 = trace(cfg, uv[:, 0], uv[:, 1] + hstep, a, b)[0]
        Fz0 = trace(cfg, uv[:, 0], uv[:, 1] - hstep, a, b)[0]
        J = np.stack([(Fx1 - Fx0) / (2 * hstep), (Fz1 - Fz0) / (2 * hstep)], -1)  # [M,2,2]
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        du = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        dv = (-J[:, 1, 0] * F[:, 0] + J[:, 0, 0] * F[:, 1]) / det
        step = np.stack([du, dv], -1)
        n = np.linalg.norm(step, axis=-1, keepdims=True)
        step = step * np.minimum(1.0, 0.05 / np.maximum(n, 1e-300))  # trust region 5 cm
        uv = uv - step
        F, ok, _, _ = trace(cfg, uv[:, 0], uv[:, 1], a, b)
        done = conv
        conv = ok & (np.linalg.norm(F, axis=-1) < tol)
        if np.all(conv & done & (np.linalg.norm(step, axis=-1) < 1e-15)):
            break  # converged, and the last step was below float64 resolution
    return uv, conv


def brute_roots(cfg: Config, spacing=None, dedup=1e-7):
    """Every solution in the footprint: [M, 2] (u, v), sorted by u."""
    x0, x1, z0, z1 = cfg.footprint
    k = np.hypot(cfg.waves[:, 1], cfg.waves[:, 2])
    kmax = np.max(np.where(cfg.waves[:, 0] != 0, k, 0.0)) if len(k) else 0.0
    if spacing is None:
        spacing = min(0.01, (2 * np.pi / kmax) / 60) if kmax > 0 else 0.01
    nx = int(np.ceil((x1 - x0) / spacing)) + 1
    nz = int(np.ceil((z1 - z0) / spacing)) + 1
    U, V = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(z0, z1, nz), indexing="ij")
    F, ok, _, _ = trace(cfg, U, V)
    cands = []
    corners = [((0, 0), (1, 0), (1, 1)), ((0, 0), (1, 1), (0, 1))]
    for tri in corners:
        P = [F[i:nx - 1 + i, j:nz - 1 + j] for i, j in tri]
        O = [ok[i:nx - 1 + i, j:nz - 1 + j] for i, j in tri]
        Q = [np.stack([U[i:nx - 1 + i, j:nz - 1 + j], V[i:nx - 1 + i, j:nz - 1 + j]], -1)
             for i, j in tri]
        e1, e2 = P[1] - P[0], P[2] - P[0]
        det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            l1 = (-P[0][..., 0] * e2[..., 1] + P[0][..., 1] * e2[..., 0]) / det
            l2 = (-e1[..., 0] * P[0][..., 1] + e1[..., 1] * P[0][..., 0]) / det
        t = 1e-6
        hit = O[0] & O[1] & O[2] & (det != 0) & (l1 >= -t) & (l2 >= -t) & (l1 + l2 <= 1 + t)
        ii = np.nonzero(hit)
        q = (Q[0][ii] + l1[ii][:, None] * (Q[1][ii] - Q[0][ii])
             + l2[ii][:, None] * (Q[2][ii] - Q[0][ii]))
        cands.append(q)
    # ... and every local minimum of the landing distance |F| below 5 cm (near a fold the
    # image triangles degenerate, and a point just inside the caustic can fall between them)
    dist = np.where(ok, np.linalg.norm(F, axis=-1), np.inf)
    inner = dist[1:-1, 1:-1]
    is_min = inner < 0.05
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                is_min &= inner <= dist[1 + di:nx - 1 + di, 1 + dj:nz - 1 + dj]
    ii = np.nonzero(is_min)
    cands.append(np.stack([U[1:-1, 1:-1][ii], V[1:-1, 1:-1][ii]], -1))
    cands = np.concatenate(cands, 0)
    if not len(cands):
        return np.zeros((0, 2))
    roots, conv = refine(cfg, cands)
    roots = roots[conv]
    # near a fold (landing Jacobian nearly singular) roots come in close pairs that one
    # triangle can hold both of: search around such roots from rings of starting points
    folds = [r for r in roots if abs(landing_det(cfg, r)) < 0.05]
    if folds:
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = np.concatenate([rad * np.stack([np.cos(ang), np.sin(ang)], -1)
                               for rad in (3e-4, 1e-3, 3e-3, 1e-2)])
        more, conv = refine(cfg, np.concatenate([r + ring for r in folds]))
        roots = np.concatenate([roots, more[conv]])
    roots = roots[(roots[:, 0] > x0) & (roots[:, 0] < x1) & (roots[:, 1] > z0) & (roots[:, 1] < z1)]
    out = []
    for r in roots[np.argsort(roots[:, 0])]:
        if all(np.linalg.norm(r - o) > dedup for o in out):
            out.append(r)
    return np.array(out).reshape(-1, 2)


def landing_det(cfg: Config, uv, h=1e-7):
    """det of the landing map's Jacobian at uv (0 on a fold: the caustic)."""
    uv = np.asarray(uv, float)
    F = lambda p: trace(cfg, p[0], p[1])[0]
    J = np.stack([(F(uv + [h, 0]) - F(uv - [h, 0])) / (2 * h),
                  (F(uv + [0, h]) - F(uv - [0, h])) / (2 * h)], -1)
    return float(np.linalg.det(J))


def root_near(cfg: Config, uv, a=None, b=None):
    r, conv = refine(cfg, np.asarray(uv, float)[None], a, b)
    assert conv[0], "reference root did not converge"
    return r[0]


def point(cfg: Config, uv):
    h = heightfield(cfg.waves, cfg.level, uv[0], uv[1])[0]
    return np.array([uv[0], h, uv[1]])


def g_area_fd(cfg: Config, uv, n_b, n_a=None, delta=1e-5):
    """|cos theta_a| |d w_a / d A_b| by central differences of the float64 root as b moves
    in its tangent plane."""
    t1, t2 = (x[0] for x in tangent_frame(_unit(np.asarray(n_b, float))[None]))
    ws = []
    for t in (t1, t2):
        pair = []
        for sgn in (1.0, -1.0):
            r = root_near(cfg, uv, b=cfg.b + sgn * delta * t)
            pair.append(_unit(point(cfg, r) - cfg.a))
        ws.append((pair[0] - pair[1]) / (2 * delta))
    dw = np.linalg.norm(np.cross(ws[0], ws[1]))
    w_a = _unit(point(cfg, uv) - cfg.a)
    cos_a = 1.0 if n_a is None else abs(np.dot(_unit(np.asarray(n_a, float)), w_a))
    return cos_a * dw


def g_point_fd(cfg: Config, uv, n_a, delta=1e-5):
    """d omega_b / d A_a by central differences of the float64 root as a moves on its
    surface (normal n_a)."""
    t1, t2 = (x[0] for x in tangent_frame(_unit(np.asarray(n_a, float))[None]))
    ws = []
    for t in (t1, t2):
        pair = []
        for sgn in (1.0, -1.0):
            ap = cfg.a + sgn * delta * t
            r = root_near(cfg, uv, a=ap)
            pair.append(_unit(point(cfg, r) - cfg.b))
        ws.append((pair[0] - pair[1]) / (2 * delta))
    return np.linalg.norm(np.cross(ws[0], ws[1]))
