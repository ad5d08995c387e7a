"""Structure-of-arrays 3-vectors.

A `Vec3` holds three arrays of equal shape (x, y, z). Kernels are written for one
ray, where each component is a scalar, and `jax.vmap` turns every component into
a length-N array: the batch is then structure-of-arrays by construction, which the
CPU backend runs as plain elementwise loops rather than as reductions over a short last
axis of `(N, 3)` arrays (docs/design/performance.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


class Vec3(NamedTuple):
    x: Array
    y: Array
    z: Array

    # tuple's own + and * mean concatenation/repetition; redefine them as vector ops.
    def __add__(self, o: "Vec3") -> "Vec3":  # type: ignore[override]
        return Vec3(self.x + o.x, self.y + o.y, self.z + o.z)

    def __sub__(self, o: "Vec3") -> "Vec3":
        return Vec3(self.x - o.x, self.y - o.y, self.z - o.z)

    def __mul__(self, s: ArrayLike) -> "Vec3":  # type: ignore[override]
        return Vec3(self.x * s, self.y * s, self.z * s)

    __rmul__ = __mul__  # type: ignore[assignment]

    def __neg__(self) -> "Vec3":
        return Vec3(-self.x, -self.y, -self.z)

    def __truediv__(self, s: ArrayLike) -> "Vec3":
        return Vec3(self.x / s, self.y / s, self.z / s)


def from_array(a) -> Vec3:
    """`(..., 3)` array -> Vec3 of `(...)` arrays."""
    a = jnp.asarray(a)
    return Vec3(a[..., 0], a[..., 1], a[..., 2])


def dot(a: Vec3, b: Vec3) -> Array:
    return a.x * b.x + a.y * b.y + a.z * b.z


def cross(a: Vec3, b: Vec3) -> Vec3:
    return Vec3(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x)


def length(a: Vec3) -> Array:
    return jnp.sqrt(dot(a, a))


def normalize(a: Vec3) -> Vec3:
    inv = 1.0 / jnp.maximum(length(a), 1e-30)
    return a * inv


def where(c, a: Vec3, b: Vec3) -> Vec3:
    return Vec3(jnp.where(c, a.x, b.x), jnp.where(c, a.y, b.y), jnp.where(c, a.z, b.z))


def onb(n: Vec3) -> tuple[Vec3, Vec3]:
    """Orthonormal tangent frame (s, t) around unit n (Duff et al. 2017, branchless)."""
    sign = jnp.where(n.z >= 0, 1.0, -1.0).astype(n.z.dtype)
    a = -1.0 / (sign + n.z)
    b = n.x * n.y * a
    s = Vec3(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x)
    t = Vec3(b, sign + n.y * n.y * a, -n.y)
    return s, t


def to_world(local: Vec3, n: Vec3) -> Vec3:
    s, t = onb(n)
    return s * local.x + t * local.y + n * local.z


def reflect(wo: Vec3, n: Vec3) -> Vec3:
    """Mirror direction of wo (pointing away from the surface) about n."""
    return n * (2.0 * dot(wo, n)) - wo
