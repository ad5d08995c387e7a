"""Pinhole camera: pixel -> primary ray."""

from __future__ import annotations

import jax.numpy as jnp

from . import _vec as V
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
    f = V.from_array(cam.forward)
    r = V.from_array(cam.right)
    u = V.from_array(cam.up)
    d = V.normalize(f + r * sx + u * sy)
    return V.from_array(cam.origin), d


def camera_frame(origin, target, up):
    """(forward, right, up) orthonormal frame looking from origin at target (NumPy/JAX)."""
    f = jnp.asarray(target) - jnp.asarray(origin)
    f = f / jnp.linalg.norm(f)
    r = jnp.cross(f, jnp.asarray(up))
    r = r / jnp.linalg.norm(r)
    u = jnp.cross(r, f)
    return f, r, u
