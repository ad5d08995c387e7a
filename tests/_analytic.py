"""Analytic test scenes (as dicts for `jaxvcm.scene_from_dict`) and statistics helpers."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import jaxvcm
from jaxvcm._render import render_pass


def camera(pos, target, fov=30.0, w=16, h=16, up=(0.0, 1.0, 0.0)):
    return {"position": list(pos), "target": list(target), "up": list(up), "fov": fov,
            "width": w, "height": h}


def sphere_furnace(Le, albedo, w=16, h=16):
    """Camera at the centre of a closed, two-sided emitting Lambertian sphere."""
    return {
        "camera": camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), 60.0, w, h),
        "lights": [{"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0,
                    "radiance": list(Le), "albedo": list(albedo)}],
    }


def box_lights(lo, hi, Le):
    """Six inward-facing rect lights (albedo 0) closing the box [lo, hi]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, s = 0.5 * (lo + hi), hi - lo
    out = []
    for ax in range(3):
        for side, sign in ((lo, 1.0), (hi, -1.0)):
            center = c.copy()
            center[ax] = side[ax]
            n = np.zeros(3)
            n[ax] = sign
            others = [i for i in range(3) if i != ax]
            out.append({"type": "rect", "center": center.tolist(), "normal": n.tolist(),
                        "size": [float(s[others[0]]), float(s[others[1]])],
                        "radiance": list(Le)})
    return out


def medium_furnace(Le, sigma_s, sigma_a=(0.0, 0.0, 0.0), phase="isotropic", g=0.0,
                   w=16, h=16, camera_pos=(0.1, -0.05, 0.2)):
    """Box [-0.5, 0.5]^3 of emitting walls filled with water (surface above the lid, so the
    whole box is one medium, index-matched by construction)."""
    lo, hi = (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)
    return {
        "camera": camera(camera_pos, (0.3, -0.4, -0.5), 60.0, w, h),
        "lights": box_lights(lo, hi, Le),
        "water": {"level": 0.8, "sigma_a": list(sigma_a), "sigma_s": list(sigma_s),
                  "phase": phase, "g": g, "ior": 1.0, "footprint": [-0.5, 0.5, -0.5, 0.5],
                  "floor": -0.5},
    }


def flat_water_slab(depth, sigma_a, ior, Le, fov=1.0, w=4, h=4):
    """Camera 1 m above flat water looking straight down at an upward-facing emitter lying
    on the floor `depth` below the surface; no scattering, nothing else in the scene."""
    return {
        "camera": camera((0.0, 1.0, 0.0), (0.0, -1.0, 0.0), fov, w, h, up=(0.0, 0.0, -1.0)),
        "lights": [{"type": "rect", "center": [0.0, -depth, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [4.0, 4.0], "radiance": list(Le)}],
        "water": {"level": 0.0, "sigma_a": list(sigma_a), "sigma_s": 0.0, "ior": ior,
                  "footprint": [-2.0, 2.0, -2.0, 2.0], "floor": -depth - 0.01},
    }


def flat_water_sky(depth, sigma_a, ior, albedo, cam_height, half=60.0, fov=2.0, w=4, h=4):
    """A wide flat pool (half-width `half`) of depth `depth` under a uniform sky of radiance 1;
    camera under water, `cam_height` above the white floor, looking straight down."""
    return {
        "camera": camera((0.0, -depth + cam_height, 0.0), (0.0, -depth - 1.0, 0.0), fov, w, h,
                         up=(0.0, 0.0, -1.0)),
        "materials": {"floor": {"type": "diffuse", "albedo": albedo}},
        "shapes": [{"type": "rect", "center": [0.0, -depth, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [2 * half, 2 * half], "material": "floor"}],
        "water": {"level": 0.0, "sigma_a": list(sigma_a), "sigma_s": 0.0, "ior": ior,
                  "footprint": [-half, half, -half, half], "floor": -depth - 0.01},
        "lights": [{"type": "sky", "radiance": 1.0}],
    }


@functools.partial(jax.jit, static_argnums=(2, 3))
def _passes(scene, keys, config, _n):
    # lax.map, not vmap: a batched predicate would turn the renderer's lax.cond work-queue
    # skips into selects (every round runs, and the program compiles ~25 % longer)
    return jax.lax.map(lambda k: render_pass(scene, k, config), keys)


def render_stats(scene, config, passes, seed=0, batch=8):
    """Per-pixel samples of `passes` independent passes -> (mean image, per-pixel standard
    error of the mean, images [P, H, W, C], total non-finite count)."""
    imgs, bad = [], 0
    for b0 in range(0, passes, batch):
        n = min(batch, passes - b0)
        keys = jnp.stack([jaxvcm.pass_key(seed, b0 + i) for i in range(n)])
        img, diag = _passes(scene, keys, config, n)
        # merging results with an overflowed hash-grid gather are not estimates: refuse them
        # (raise config.merge_capacity; the host driver render_pass_host does that itself)
        assert not np.any(np.asarray(diag.merge_overflow)), "merge capacity overflow"
        imgs.append(np.asarray(img, np.float64))
        bad += int(np.sum(np.asarray(diag.nonfinite)))
    imgs = np.concatenate(imgs)
    mean = imgs.mean(0)
    se = imgs.std(0, ddof=1) / np.sqrt(imgs.shape[0])
    return mean, se, imgs, bad


def pooled(imgs):
    """Treat every pixel of every pass as one i.i.d. sample (valid when all pixels share the
    same expectation): (per-channel mean, per-channel standard error)."""
    x = imgs.reshape(-1, imgs.shape[-1])
    return x.mean(0), x.std(0, ddof=1) / np.sqrt(x.shape[0])
