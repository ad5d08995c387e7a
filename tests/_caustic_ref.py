"""Independent float64 NumPy ray-mapping reference for the sun caustics of a pool.

No jaxvcm kernel is used here: the surface, Fresnel, refraction, occlusion by the basin
walls and the pinhole camera are written out again in NumPy float64.

Scene model (scenes/pool_sun.toml with the test simplifications): an open box (floor at
y = floor, four walls up to y = wall_top, footprint [x0, x1] x [z0, z1]) holding purely
absorbing water (sigma_t = sigma_a, sigma_s = 0) under the heightfield
    y = level + sum_i A_i sin(kx_i x + kz_i z + phase_i),
a Lambertian floor of albedo a, black walls, and a sun of irradiance E (on a plane
perpendicular to its direction s, the way the light travels). Then the only light that
reaches a camera is
    sun -> refraction at the surface -> floor -> (refraction) -> camera,
and this module computes it in full:

1. `floor_irradiance`: a dense regular grid of parallel sun rays through the opening of
   the basin (the plane y = wall_top; each ray carries the flux E |s_y| dA of its cell),
   dropped if they hit a wall above the water (surface point outside the footprint),
   intersected with the surface to ~1e-13 (Newton inside a bisection bracket; the rays
   are steeper than the steepest surface slope, so the crossing is unique), refracted
   with the exact unpolarised Fresnel transmittance T, attenuated by exp(-sigma_t L) over
   the in-water length L, dropped if they hit a wall in the water (floor point outside
   the footprint) and splatted (flux) into a fine histogram on the floor:
   E_floor = flux / bin area, per channel.
2. `render_under`: pinhole camera in the water, straight rays to the floor:
       L = a / pi * E_floor(hit) * exp(-sigma_t d).
3. `render_above`: pinhole camera in the air: the ray must enter the opening, refracts
   at the surface (transmittance T; the radiance seen in the air is T / eta^2 times the
   radiance in the water, the n^2 law, which the renderer's camera paths carry as the
   1 / eta^2 factor of a radiance-mode refraction), then Beer-Lambert and the floor:
       L = T / eta^2 * exp(-sigma_t L_w) * a / pi * E_floor(hit).
   The Fresnel-reflected part of the camera ray sees black walls or the (delta) sun's
   empty sky: nothing.
Pixels are box filtered (the renderer jitters uniformly inside each pixel,
`jaxvcm/_camera.py`), here by ss x ss stratified sub-pixel rays at the cell centres.

`disk_blur` gives E_floor convolved with the normalised disk kernel of radius r (zero
outside the floor): what vertex merging with radius r estimates on the floor.

A second, histogram-free method checks the first for a camera in the water: the sun rays'
floor hits splatted through the pinhole with the film Jacobian (`floor_irradiance(...,
splat_cams=...)`, `_splat_under`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._oracles import heightfield, heightfield_normal


@dataclasses.dataclass(frozen=True)
class Pool:
    level: float
    waves: np.ndarray  # [W, 4]: A, kx, kz, phase
    ior: float
    sigma_t: np.ndarray  # [C] 1/m (sigma_a + sigma_s; the tests use sigma_s = 0)
    floor: float  # y of the floor
    footprint: tuple  # (x0, x1, z0, z1)
    wall_top: float  # y of the wall tops
    sun: np.ndarray  # unit direction the light travels
    E: np.ndarray  # [C] irradiance on a plane perpendicular to the sun
    albedo: np.ndarray  # [C] floor albedo

    @property
    def max_slope(self) -> float:
        """Upper bound of |grad h|."""
        w = self.waves
        return float(np.sum(np.abs(w[:, 0]) * np.hypot(w[:, 1], w[:, 2])))

    @property
    def amp_sum(self) -> float:
        return float(np.sum(np.abs(self.waves[:, 0])))


def _spec(v):
    return np.asarray(v, float) * np.ones(3)


def pool_from_dict(d: dict, **over) -> Pool:
    basin = next(s for s in d["shapes"] if s["type"] == "basin")
    sun = next(li for li in d["lights"] if li["type"] == "sun")
    w = d["water"]
    s = np.asarray(sun["direction"], float)
    lo, hi = basin["min"], basin["max"]
    kw = dict(
        level=float(w["level"]), waves=np.asarray(w.get("waves", []), float).reshape(-1, 4),
        ior=float(w["ior"]), sigma_t=_spec(w["sigma_a"]) + _spec(w["sigma_s"]),
        floor=float(lo[1]), footprint=(float(lo[0]), float(hi[0]), float(lo[2]), float(hi[2])),
        wall_top=float(hi[1]), sun=s / np.linalg.norm(s), E=_spec(sun["irradiance"]),
        albedo=_spec(d["materials"][basin["floor_material"]].get("albedo", 0.5)),
    )
    kw.update(over)
    return Pool(**kw)


# ---------------------------------------------------------------- surface
def height(pool: Pool, x, z):
    """h, dh/dx, dh/dz (float64, elementwise)."""
    return heightfield(pool.waves, pool.level, x, z)


def intersect_surface(pool: Pool, o, d, tol=1e-13, max_iter=100):
    """Distance along downward rays (o, d) [..., 3] to the surface: Newton steps kept
    inside a bisection bracket [t(y = top of the slab), t(y = bottom)], until the bracket
    or the step is below `tol`. The rays must be steeper than the steepest surface slope
    (checked), so f(t) = y(t) - h(x(t), z(t)) is strictly decreasing: one crossing."""
    o, d = np.asarray(o, float), np.asarray(d, float)
    horiz = np.hypot(d[..., 0], d[..., 2])
    if not np.all(-d[..., 1] > pool.max_slope * horiz * (1 + 1e-9)):
        raise ValueError("ray not steeper than the steepest surface slope")
    pad = pool.amp_sum + 1e-6
    a = (pool.level + pad - o[..., 1]) / d[..., 1]
    b = (pool.level - pad - o[..., 1]) / d[..., 1]

    def f(t):
        h, hx, hz = height(pool, o[..., 0] + t * d[..., 0], o[..., 2] + t * d[..., 2])
        return o[..., 1] + t * d[..., 1] - h, d[..., 1] - hx * d[..., 0] - hz * d[..., 2]

    t = 0.5 * (a + b)
    for _ in range(max_iter):
        ft, dft = f(t)
        pos = ft > 0  # root beyond t
        a = np.where(pos, t, a)
        b = np.where(pos, b, t)
        tn = t - ft / dft
        bad = ~((tn >= a) & (tn <= b))  # outside the bracket: bisect instead
        tn = np.where(bad, 0.5 * (a + b), tn)
        step = np.abs(tn - t)
        t = tn
        if np.all((step < tol) | (b - a < tol)):
            break
    else:
        raise RuntimeError("surface intersection did not converge")
    ft, _ = f(t)
    assert np.max(np.abs(ft)) < 1e-11, np.max(np.abs(ft))
    return t


def surface_normal(pool: Pool, x, z):
    return heightfield_normal(pool.waves, pool.level, x, z)


def fresnel_unpolarised(cos_i, eta):
    """Reflectance of a smooth dielectric, relative IOR eta = n_t / n_i (TIR: 1)."""
    cos_i = np.clip(np.abs(cos_i), 0.0, 1.0)
    sin2_t = (1.0 - cos_i**2) / eta**2
    tir = sin2_t >= 1
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin2_t))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(tir, 1.0, 0.5 * (rs**2 + rp**2)), cos_t


def refract_down(d, n, eta):
    """Air -> water refraction of unit d at unit normal n (pointing up, towards d's origin):
    (transmitted direction, transmittance T)."""
    cos_i = -np.sum(d * n, -1)
    R, cos_t = fresnel_unpolarised(cos_i, eta)
    wt = d / eta + n * (cos_i / eta - cos_t)[..., None]
    return wt / np.linalg.norm(wt, axis=-1, keepdims=True), 1.0 - R


def _inside(pool: Pool, x, z):
    x0, x1, z0, z1 = pool.footprint
    return (x > x0) & (x < x1) & (z > z0) & (z < z1)


# ---------------------------------------------------------------- floor irradiance
@dataclasses.dataclass
class FloorMap:
    E: np.ndarray  # [nz, nx, C] irradiance on the floor (bin averages)
    x_edges: np.ndarray
    z_edges: np.ndarray
    flux_in: np.ndarray  # [C] flux through the opening
    flux_floor: np.ndarray  # [C] flux that reached the floor
    splats: list = dataclasses.field(default_factory=list)  # `splat_under` images

    @property
    def bin_area(self):
        return (self.x_edges[1] - self.x_edges[0]) * (self.z_edges[1] - self.z_edges[0])

    def lookup(self, x, z):
        """E_floor at floor points (nearest bin; 0 outside) -> [..., C]."""
        nx, nz = len(self.x_edges) - 1, len(self.z_edges) - 1
        ix = np.floor((x - self.x_edges[0]) / (self.x_edges[1] - self.x_edges[0])).astype(int)
        iz = np.floor((z - self.z_edges[0]) / (self.z_edges[1] - self.z_edges[0])).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iz >= 0) & (iz < nz)
        v = self.E[np.clip(iz, 0, nz - 1), np.clip(ix, 0, nx - 1)]
        return np.where(ok[..., None], v, 0.0)


def sun_on_floor(pool: Pool, n_rays: int = 2000, chunk: int = 250_000):
    """Trace n_rays x n_rays parallel sun rays through the opening (cell centres of the
    plane y = wall_top over the footprint), in chunks: yields (q [n, 3] floor points,
    flux [n, C] arriving there, zero for dropped rays)."""
    x0, x1, z0, z1 = pool.footprint
    s = pool.sun
    if not s[1] < 0:
        raise ValueError("the sun must shine downwards")
    gx = x0 + (np.arange(n_rays) + 0.5) * (x1 - x0) / n_rays
    gz = z0 + (np.arange(n_rays) + 0.5) * (z1 - z0) / n_rays
    dA = (x1 - x0) * (z1 - z0) / n_rays**2
    phi = pool.E * abs(s[1]) * dA  # [C] flux per ray through the horizontal opening
    X, Z = np.meshgrid(gx, gz)
    X, Z = X.ravel(), Z.ravel()
    for c0 in range(0, X.size, chunk):
        x, z = X[c0:c0 + chunk], Z[c0:c0 + chunk]
        o = np.stack([x, np.full_like(x, pool.wall_top), z], -1)
        d = np.broadcast_to(s, o.shape)
        t = intersect_surface(pool, o, d)
        p = o + d * t[:, None]
        ok = _inside(pool, p[:, 0], p[:, 2])  # else a wall above the water was hit
        n = surface_normal(pool, p[:, 0], p[:, 2])
        wt, T = refract_down(d, n, pool.ior)
        tf = (pool.floor - p[:, 1]) / wt[:, 1]
        q = p + wt * tf[:, None]
        ok &= _inside(pool, q[:, 0], q[:, 2])  # else a wall in the water was hit first
        w = np.where(ok[:, None], T[:, None] * np.exp(-np.outer(tf, pool.sigma_t)), 0.0) * phi
        yield q, w


def floor_irradiance(pool: Pool, n_rays: int = 2000, bins: int = 400, splat_cams=(),
                     chunk: int = 250_000) -> FloorMap:
    """Histogram of the sun's flux on the floor (`sun_on_floor`) in bins x bins cells of
    the footprint: E_floor = flux / bin area. Cameras in the water given in `splat_cams`
    also receive the same rays splatted through the pinhole (`splat_under`), returned in
    `FloorMap.splats`."""
    x0, x1, z0, z1 = pool.footprint
    C = len(pool.E)
    acc = np.zeros((bins * bins, C))
    flux_floor = np.zeros(C)
    splats = [np.zeros((c.height * c.width, C)) for c in splat_cams]
    for q, w in sun_on_floor(pool, n_rays, chunk):
        ix = np.clip(((q[:, 0] - x0) / (x1 - x0) * bins).astype(int), 0, bins - 1)
        iz = np.clip(((q[:, 2] - z0) / (z1 - z0) * bins).astype(int), 0, bins - 1)
        for ch in range(C):
            acc[:, ch] += np.bincount(iz * bins + ix, weights=w[:, ch], minlength=bins * bins)
        flux_floor += w.sum(0)
        for cam, img in zip(splat_cams, splats):
            _splat_under(pool, cam, q, w, img)
    xe = np.linspace(x0, x1, bins + 1)
    ze = np.linspace(z0, z1, bins + 1)
    E = acc.reshape(bins, bins, C) / ((xe[1] - xe[0]) * (ze[1] - ze[0]))
    flux_in = pool.E * abs(pool.sun[1]) * (x1 - x0) * (z1 - z0)
    return FloorMap(E, xe, ze, flux_in, flux_floor,
                    [img.reshape(c.height, c.width, C) for c, img in zip(splat_cams, splats)])


def disk_blur(fm: FloorMap, radii, sub: int = 4) -> FloorMap:
    """The floor map convolved with the normalised disk kernel 1 / (pi r^2), averaged over
    the radii in `radii` (the pass-averaged kernel of a progressive render), with zero
    outside the floor (the disk is cut by the walls, as the renderer's merging only
    accepts photons on the floor itself): what merging on the floor estimates."""
    from scipy.signal import fftconvolve

    h = fm.x_edges[1] - fm.x_edges[0]
    radii = np.atleast_1d(np.asarray(radii, float))
    m = int(math.ceil(radii.max() / h)) + 1
    # coverage of each bin by each disk, by sub x sub point sampling of the bin
    u = (np.arange(-m, m + 1)[:, None] + (np.arange(sub) + 0.5)[None] / sub - 0.5).ravel() * h
    r2 = u[:, None] ** 2 + u[None] ** 2
    k = np.zeros((2 * m + 1, 2 * m + 1))
    for r in radii:
        cover = (r2 < r * r).reshape(2 * m + 1, sub, 2 * m + 1, sub).mean(axis=(1, 3))
        k += cover / (math.pi * r * r / (h * h))  # normalised by the exact disk area
    k /= len(radii)
    E = np.stack([fftconvolve(fm.E[..., c], k, mode="same") for c in range(fm.E.shape[-1])], -1)
    return dataclasses.replace(fm, E=np.maximum(E, 0.0))


# ---------------------------------------------------------------- camera
@dataclasses.dataclass(frozen=True)
class Cam:
    position: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float  # vertical, degrees
    width: int
    height: int


def cam_from_dict(c: dict) -> Cam:
    return Cam(np.asarray(c["position"], float), np.asarray(c["target"], float),
               np.asarray(c.get("up", [0.0, 1.0, 0.0]), float), float(c["fov"]),
               int(c["width"]), int(c["height"]))


def camera_rays(cam: Cam, ss: int = 8):
    """Unit directions [H, W, ss*ss, 3] through the centres of ss x ss sub-pixel cells
    (row 0 at the top; the image plane at distance 1 spans tan(fov/2) vertically)."""
    f, r, u = _camera_frame(cam)
    W, H = cam.width, cam.height
    th = math.tan(math.radians(cam.fov) / 2)
    sub = (np.arange(ss) + 0.5) / ss
    px = (np.arange(W)[:, None] + sub[None]).ravel()  # [W*ss]
    py = (np.arange(H)[:, None] + sub[None]).ravel()
    sx = (2 * px / W - 1) * (W / H) * th
    sy = (1 - 2 * py / H) * th
    SY, SX = np.meshgrid(sy, sx, indexing="ij")  # [H*ss, W*ss]
    d = f + SX[..., None] * r + SY[..., None] * u
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d = d.reshape(H, ss, W, ss, 3).transpose(0, 2, 1, 3, 4).reshape(H, W, ss * ss, 3)
    return d


def render_under(pool: Pool, fm: FloorMap, cam: Cam, ss: int = 8):
    """Camera in the water (below the lowest surface point), every ray going down to the
    floor: L = a / pi E_floor(hit) exp(-sigma_t d), box-filtered. [H, W, C]"""
    o = cam.position
    if not (_inside(pool, o[0], o[2]) and pool.floor < o[1] < pool.level - pool.amp_sum):
        raise ValueError("camera not in the water")
    d = camera_rays(cam, ss)
    down = d[..., 1] < 0
    t = np.where(down, (pool.floor - o[1]) / np.where(down, d[..., 1], -1.0), 0.0)
    q = o + d * t[..., None]
    ok = down & _inside(pool, q[..., 0], q[..., 2])  # else a (black) wall
    L = (pool.albedo / math.pi) * fm.lookup(q[..., 0], q[..., 2]) * np.exp(
        -t[..., None] * pool.sigma_t)
    return np.where(ok[..., None], L, 0.0).mean(axis=2)


def _camera_frame(cam: "Cam"):
    f = cam.target - cam.position
    f = f / np.linalg.norm(f)
    up = cam.up / np.linalg.norm(cam.up)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    return f, r, np.cross(r, f)


def _splat_under(pool: Pool, cam: "Cam", q, w, img):
    """Second, histogram-free method for a camera in the water looking down: every sun
    ray's floor hit q (flux w) is projected through the pinhole into its pixel with the
    film Jacobian
        dA_film / dA_floor = cos(theta_q) / (d^2 cos^3(theta_c))
    (theta_q at the floor, theta_c from the optical axis, film at distance 1), so
        pixel += a / pi * w * exp(-sigma_t d) * dA_film/dA_floor / A_pixel
    is the exact box-filtered pixel integral up to the discretisation of the sun rays
    (nothing lies between the floor and a camera inside the water)."""
    o = cam.position
    f, r, u = _camera_frame(cam)
    W, H = cam.width, cam.height
    th = math.tan(math.radians(cam.fov) / 2)
    a_pix = (2 * th * W / H / W) * (2 * th / H)
    v = q - o
    dist = np.linalg.norm(v, axis=-1)
    vf, vr, vu = v @ f, v @ r, v @ u
    vf_safe = np.where(vf > 0, vf, 1.0)
    px = (vr / vf_safe / (th * W / H) + 1) * W / 2
    py = (1 - vu / vf_safe / th) * H / 2
    ok = (vf > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H) & np.any(w > 0, axis=-1)
    jac = (np.abs(v[:, 1]) / dist) / (dist**2 * (vf_safe / dist) ** 3)  # floor normal +y
    val = (w * (pool.albedo / math.pi)) * (jac / a_pix)[:, None] * np.exp(
        -np.outer(dist, pool.sigma_t))
    val = np.where(ok[:, None], val, 0.0)
    pix = np.clip(py.astype(int), 0, H - 1) * W + np.clip(px.astype(int), 0, W - 1)
    for ch in range(img.shape[-1]):
        img[:, ch] += np.bincount(pix, weights=val[:, ch], minlength=H * W)


def render_above(pool: Pool, fm: FloorMap, cam: Cam, ss: int = 8):
    """Camera in the air above the wall tops looking down through the surface:
    L = T / eta^2 exp(-sigma_t L_w) a / pi E_floor(hit), box-filtered. [H, W, C]"""
    o = cam.position
    if not o[1] > pool.wall_top:
        raise ValueError("camera must be above the wall tops")
    d = camera_rays(cam, ss)
    if not np.all(d[..., 1] < 0):
        raise ValueError("every camera ray must go down")
    t0 = (pool.wall_top - o[1]) / d[..., 1]
    p0 = o + d * t0[..., None]
    ok = _inside(pool, p0[..., 0], p0[..., 2])  # through the opening
    # start the surface search on the opening plane (any point above the slab will do)
    t = intersect_surface(pool, p0, d)
    p = p0 + d * t[..., None]
    ok &= _inside(pool, p[..., 0], p[..., 2])  # else a wall above the water
    n = surface_normal(pool, p[..., 0], p[..., 2])
    wt, T = refract_down(d, n, pool.ior)
    tf = (pool.floor - p[..., 1]) / wt[..., 1]
    q = p + wt * tf[..., None]
    ok &= _inside(pool, q[..., 0], q[..., 2])  # else a wall in the water
    L = ((T / pool.ior**2)[..., None] * np.exp(-tf[..., None] * pool.sigma_t)
         * (pool.albedo / math.pi) * fm.lookup(q[..., 0], q[..., 2]))
    return np.where(ok[..., None], L, 0.0).mean(axis=2)


def tiles(img, t):
    """Tile means of [..., H, W, C] over t x t pixel tiles -> [..., H/t, W/t, C]."""
    *lead, H, W, C = img.shape
    return img.reshape(*lead, H // t, t, W // t, t, C).mean(axis=(-4, -2))
