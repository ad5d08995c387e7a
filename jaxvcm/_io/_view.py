"""The merging radius's reference length: the size of what the camera sees.

A progressive photon-mapping radius is a length in the scene, and what it must resolve is
the image: a pixel's footprint and the detail of the lighting on the surfaces the camera
sees. So the reference length that `RenderConfig.radius` multiplies is the radius of the
box around the non-specular surface points that the camera sees (`view_radius`), found on
the host when the scene is loaded, in float64, by tracing a fixed grid of
`VIEW_RAYS` x `VIEW_RAYS` rays through the film:

- each ray's first hit on a rectangle or a sphere is a point of the view;
- a ray that first meets the water's surface (its mean plane, inside the footprint) goes
  on both ways, refracted and reflected by the flat surface, and the first hit of each is
  a point of the view (what the camera sees through and in the water; merging happens at
  those vertices, never at the specular surface itself);
- rays that leave the scene add nothing.

The box of all surfaces (`Scene.bounds`) still bounds the emission of the infinite lights
(what light can reach); the view box lies inside it (its points are on the surfaces), so
the radius is never larger than one from the whole scene. A view of one corner of a wide
pool gets a radius fitted to that corner (merging's bias, which grows as r^2, shrinks with
it), a view of the whole scene the same radius as before. Deterministic (the same grid
every time), independent of the passes, and cheap (NumPy, a few hundred rays). A camera
that sees nothing (every ray leaves the scene) keeps the whole scene's radius."""

from __future__ import annotations

import numpy as np

VIEW_RAYS = 32  # rays per side of the film


def _rects(p0, e1, e2, o, d):
    """[R, N] distances from the rays (o [N, 3], d [N, 3]) to the parallelograms (inf: no
    hit), the dual-basis test of `_geometry.intersect_rects`."""
    n = np.cross(e1, e2)  # [R, 3]
    denom = d @ n.T  # [N, R]
    num = np.einsum("rk,rk->r", p0, n)[None, :] - o @ n.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
    q = o[:, None, :] + d[:, None, :] * t[..., None] - p0[None]  # [N, R, 3]
    nn = np.einsum("rk,rk->r", n, n)
    u = np.einsum("nrk,rk->nr", np.cross(q, e2[None]), n) / nn
    v = np.einsum("nrk,rk->nr", np.cross(e1[None], q), n) / nn
    ok = (denom != 0) & (t > 1e-9) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    return np.where(ok, t, np.inf)


def _spheres(c, r, o, d):
    """[N, S] distances to the spheres (the nearer root in front of the origin)."""
    oc = o[:, None, :] - c[None]  # [N, S, 3]
    b = np.einsum("nsk,nk->ns", oc, d)
    cc = np.einsum("nsk,nsk->ns", oc, oc) - r[None] ** 2
    disc = b * b - cc
    s = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = -b - s, -b + s
    t = np.where(t0 > 1e-9, t0, np.where(t1 > 1e-9, t1, np.inf))
    return np.where(disc >= 0, t, np.inf)


def _first_hit(parts, o, d):
    """The first hit of each ray on a rectangle or a sphere: (distance [N], inf: none)."""
    t = np.full(len(o), np.inf)
    if parts.rect_p0:
        t = np.minimum(t, _rects(*(np.asarray(x, float) for x in
                                   (parts.rect_p0, parts.rect_e1, parts.rect_e2)), o, d).min(1))
    if parts.sph_c:
        t = np.minimum(t, _spheres(np.asarray(parts.sph_c, float), np.asarray(parts.sph_r, float),
                                   o, d).min(1))
    return t


def _film_rays(cam: dict):
    """Directions [N, 3] of the grid of rays through the film (pixel-centre convention of
    `_camera.generate_ray`)."""
    n = VIEW_RAYS
    aspect = cam["width"] / cam["height"]
    s = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    sx, sy = np.meshgrid(s * aspect * cam["tan_half_fov"], -s * cam["tan_half_fov"])
    d = (np.asarray(cam["fwd"], float)[None] + sx.reshape(-1, 1) * np.asarray(cam["right"], float)
         + sy.reshape(-1, 1) * np.asarray(cam["up"], float))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def view_points(cam: dict, parts, water: dict) -> np.ndarray:
    """[M, 3] non-specular surface points that the grid of camera rays sees (module doc)."""
    d = _film_rays(cam)
    o = np.broadcast_to(np.asarray(cam["pos"], float), d.shape)
    t = _first_hit(parts, o, d)
    on = np.zeros(len(d), bool)  # rays that meet the water's surface first
    if water["enabled"]:
        fp, level = water["fp"], float(water["level"])
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = (level - o[:, 1]) / d[:, 1]
        p = o + d * ts[:, None]
        on = ((ts > 1e-9) & (ts < t) & (p[:, 0] >= fp[0]) & (p[:, 0] <= fp[1])
              & (p[:, 2] >= fp[2]) & (p[:, 2] <= fp[3]))
    hit = np.isfinite(t) & ~on
    pts = [o[hit] + d[hit] * t[hit, None]]
    if np.any(on):
        p, dw = p[on], d[on]
        above = o[on][:, 1] > level  # the camera's side of the surface
        eta = np.where(above, 1.0 / float(water["ior"]), float(water["ior"]))
        ny = np.where(above, 1.0, -1.0)  # the normal on the incoming side
        cos_i = np.abs(dw[:, 1])
        reflected = dw * np.array([1.0, -1.0, 1.0])
        sin2_t = eta**2 * (1.0 - cos_i**2)
        cos_t = np.sqrt(np.maximum(1.0 - sin2_t, 0.0))
        refracted = eta[:, None] * dw + ((eta * cos_i - cos_t) * ny)[:, None] * np.array(
            [0.0, 1.0, 0.0])
        total = sin2_t >= 1.0  # total internal reflection: no refracted ray
        for dirs, keep in ((reflected, np.ones(len(p), bool)), (refracted, ~total)):
            dirs = dirs[keep] / np.linalg.norm(dirs[keep], axis=1, keepdims=True)
            o2 = p[keep] + 1e-9 * dirs
            t2 = _first_hit(parts, o2, dirs)
            f = np.isfinite(t2)
            pts.append(o2[f] + dirs[f] * t2[f, None])
    return np.concatenate(pts)


def view_radius(cam: dict, parts, water: dict, bounds: np.ndarray) -> float:
    """Half the diagonal of the box around `view_points`, at most the whole scene's
    (`bounds`: half its diagonal; also the answer when the camera sees no surface)."""
    rb = 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
    pts = view_points(cam, parts, water)
    if len(pts) == 0:
        return rb
    pts = np.clip(pts, bounds[0], bounds[1])  # rounding at the box's faces
    return min(rb, 0.5 * float(np.linalg.norm(pts.max(0) - pts.min(0))))
