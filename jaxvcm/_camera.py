"""Pinhole camera: pixel -> primary ray."""

from __future__ import annotations

import jax.numpy as jnp

from . import _vec as vec
from ._scene import Camera
from ._vec import Vec3


def generate_ray(cam: Camera, pixel, u1, u2) -> tuple[Vec3, Vec3]:
    """Ray through a uniformly jittered point of `pixel` (row-major, row 0 at the top)."""
    W, H = cam.width, cam.height
    dt = u1.dtype
    px = (pixel % W).astype(dt) + u1
    py = (pixel // W).astype(dt) + u2
    aspect = W / H
    sx = (2.0 * px / W - 1.0) * aspect * cam.tan_half_fov
    sy = (1.0 - 2.0 * py / H) * cam.tan_half_fov
    f = vec.from_array(cam.forward)
    r = vec.from_array(cam.right)
    u = vec.from_array(cam.up)
    d = vec.normalize(f + r * sx + u * sy)
    return vec.from_array(cam.origin), d


def camera_frame(origin, target, up):
    """(forward, right, up) orthonormal frame looking from origin at target (NumPy/JAX)."""
    f = jnp.asarray(target) - jnp.asarray(origin)
    f = f / jnp.linalg.norm(f)
    r = jnp.cross(f, jnp.asarray(up))
    r = r / jnp.linalg.norm(r)
    u = jnp.cross(r, f)
    return f, r, u


def camera_importance(scene, w: Vec3):
    """(pixel index, 1 / (A_pix cos^3), inside) for a unit direction w leaving the pinhole;
    the film is the image plane at distance 1 with pixels of area A_pix, so a camera
    subpath samples w with this solid-angle pdf, and W_e G = 1 / (A_pix cos^3 d^2)."""
    cam = scene.camera
    W, H = cam.width, cam.height
    f = vec.from_array(cam.forward)
    r = vec.from_array(cam.right)
    u = vec.from_array(cam.up)
    cos = vec.dot(w, f)
    safe = jnp.where(cos > 0, cos, 1.0)
    sx = vec.dot(w, r) / safe
    sy = vec.dot(w, u) / safe
    aspect = W / H
    px = (sx / (aspect * cam.tan_half_fov) + 1.0) * 0.5 * W
    py = (1.0 - sy / cam.tan_half_fov) * 0.5 * H
    inside = (cos > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H)
    ix = jnp.clip(px.astype(jnp.int32), 0, W - 1)
    iy = jnp.clip(py.astype(jnp.int32), 0, H - 1)
    a_pix = (2.0 * cam.tan_half_fov * aspect / W) * (2.0 * cam.tan_half_fov / H)
    imp = 1.0 / (a_pix * safe * safe * safe)
    return iy * W + ix, jnp.where(inside, imp, 0.0), inside
