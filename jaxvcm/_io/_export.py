"""Tessellate a scene's analytic geometry into triangle meshes for a mesh viewer.

Rectangles become two triangles (wound so that the face normal is e1 x e2, the renderer's
geometric normal), spheres icospheres, and the water surface a regular grid of its
heightfield over the footprint. One named geometry per shape, colored by material.
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from .._geometry import water_height
from .._scene import MAT_DIELECTRIC, MAT_MIRROR, Scene
from ._images import atomic_path

FORMATS = (".glb", ".ply", ".obj")


def _rgba(scene: Scene, mat: int, light: int) -> np.ndarray:
    if light >= 0:
        return np.array([255, 244, 214, 255], np.uint8)
    kind = scene.materials.kind[mat]
    if kind == MAT_DIELECTRIC:
        return np.array([90, 160, 220, 160], np.uint8)
    a = np.clip(np.asarray(scene.materials.albedo[mat], np.float64)[:3], 0.0, 1.0)
    if a.size < 3:
        a = np.resize(a, 3)
    if kind == MAT_MIRROR:
        a = 0.5 + 0.5 * a
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)
    return np.append(np.round(srgb * 255).astype(np.uint8), np.uint8(255))


def scene_meshes(scene: Scene, water_resolution: int = 128, sphere_subdivisions: int = 3):
    """[(name, trimesh.Trimesh)] for every rectangle, sphere and the water surface."""
    import trimesh

    meshes = []
    r = scene.rects
    p0, e1, e2 = (np.asarray(x, np.float64) for x in (r.p0, r.e1, r.e2))
    rmat, rlight = np.asarray(r.mat), np.asarray(r.light)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    for i in range(p0.shape[0]):
        v = np.stack([p0[i], p0[i] + e1[i], p0[i] + e1[i] + e2[i], p0[i] + e2[i]])
        m = trimesh.Trimesh(v, faces, process=False)
        m.visual.face_colors = _rgba(scene, int(rmat[i]), int(rlight[i]))
        name = f"light_rect_{int(rlight[i])}" if rlight[i] >= 0 else f"rect_{i}"
        meshes.append((name, m))

    s = scene.spheres
    c, rad = np.asarray(s.center, np.float64), np.asarray(s.radius, np.float64)
    smat, slight = np.asarray(s.mat), np.asarray(s.light)
    for i in range(c.shape[0]):
        m = trimesh.creation.icosphere(subdivisions=sphere_subdivisions, radius=float(rad[i]))
        m.apply_translation(c[i])
        m.visual.face_colors = _rgba(scene, int(smat[i]), int(slight[i]))
        name = f"light_sphere_{int(slight[i])}" if slight[i] >= 0 else f"sphere_{i}"
        meshes.append((name, m))

    w = scene.water
    if w.enabled:
        meshes.append(("water", water_mesh(scene, water_resolution)))
    return meshes


def water_grid(scene: Scene, n: int = 128):
    """The water heightfield tessellated as an n x n vertex grid over the footprint:
    (vertices [n*n, 3], analytic unit normals [n*n, 3], triangles [2 (n-1)^2, 3]) as NumPy
    float64 / int64 arrays. Vertex (i, j) = row i * n + j sits at x = linspace(xmin, xmax,
    n)[i], z = linspace(zmin, zmax, n)[j], y = the surface height there; its normal is the
    heightfield's exact normal normalize(-dh/dx, 1, -dh/dz) (pointing into the air), and
    every triangle is wound so that its face normal points up (+y) too."""
    w = scene.water
    if n < 2:
        raise ValueError(f"water_resolution: must be >= 2, got {n}")
    fp = np.asarray(w.footprint, np.float64)
    dt = w.level.dtype
    xs = np.linspace(fp[0], fp[1], n)
    zs = np.linspace(fp[2], fp[3], n)
    X, Z = np.meshgrid(xs, zs, indexing="ij")  # X[i, j] = xs[i], Z[i, j] = zs[j]
    h, hx, hz = water_height(w, jnp.asarray(X, dt), jnp.asarray(Z, dt))
    V = np.stack([X, np.asarray(h, np.float64), Z], axis=-1).reshape(-1, 3)
    N = np.stack([-np.asarray(hx, np.float64), np.ones_like(X), -np.asarray(hz, np.float64)],
                 axis=-1).reshape(-1, 3)
    N /= np.linalg.norm(N, axis=-1, keepdims=True)
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()  # (i, j), (i, j+1)
    cc, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()  # (i+1, j), (i+1, j+1)
    # (0, 0, dz) x (dx, 0, 0) = +y: triangles (i,j),(i,j+1),(i+1,j) and (i+1,j),(i,j+1),(i+1,j+1)
    F = np.concatenate([np.stack([a, b, cc], 1), np.stack([cc, b, d], 1)]).astype(np.int64)
    return V, N, F


def water_mesh(scene: Scene, n: int = 128):
    """The water heightfield as an n x n vertex grid over the footprint, normals up
    (`water_grid`'s vertices and triangles; the viewer's own smooth normals)."""
    import trimesh

    V, _, F = water_grid(scene, n)
    m = trimesh.Trimesh(V, F, process=False)
    m.visual.face_colors = _rgba(scene, scene.water.mat, -1)
    return m


def export_scene(scene: Scene, path, water_resolution: int = 128) -> str:
    """Write the tessellated scene to `path`; the format follows the extension
    (.glb: one named node per shape, .obj: one object per shape, .ply: one merged mesh).
    The file is written atomically. Returns the path."""
    import trimesh

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in FORMATS:
        raise ValueError(f"export: unknown format {ext or '(none)'!r} of {path!r}; "
                         f"use one of {', '.join(FORMATS)}")
    meshes = scene_meshes(scene, water_resolution)
    if not meshes:
        raise ValueError(f"export: scene {scene.name!r} has no finite geometry to export")
    if ext == ".ply":
        data = trimesh.util.concatenate([m for _, m in meshes]).export(file_type="ply")
    else:
        ts = trimesh.Scene()
        for name, m in meshes:
            ts.add_geometry(m, geom_name=name, node_name=name)
        data = ts.export(file_type=ext[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return path
