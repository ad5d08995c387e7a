"""Test scenes, as dicts for `jaxvcm.scene_from_dict`: analytic scenes with closed forms
(furnaces, flat water under an emitter, a sky or the sun) and the shipped scenes of
scenes/ with test overrides (`shipped_doc`)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

import jaxvcm

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def camera(pos, target, fov=30.0, w=16, h=16, up=(0.0, 1.0, 0.0)):
    return {"position": list(pos), "target": list(target), "up": list(up), "fov": fov,
            "width": w, "height": h}


# ---------------------------------------------------------------- shipped scenes
def shipped_doc(name: str, width: int | None = None, height: int | None = None, **over) -> dict:
    """scenes/NAME.toml as a dict, the camera's `width` and `height` set where given, with
    overrides: a keyword `SECTION__KEY=value` sets doc[SECTION][KEY] (any depth:
    `materials__wall__albedo=0.0`), a plain `SECTION=value` replaces the section
    (`camera=camera(...)`)."""
    with open(SCENES / f"{name}.toml", "rb") as f:
        d = tomllib.load(f)
    for key, v in (("width", width), ("height", height)):
        if v is not None:
            d["camera"][key] = v
    for k, v in over.items():
        *path, key = k.split("__")
        t = d
        for p in path:
            t = t[p]
        t[key] = v
    return d


def radius_fraction(scene, metres: float) -> float:
    """`RenderConfig.radius` for a first merging radius of `metres` in `scene` (the config
    takes a fraction of the scene's view radius, the size of what its camera sees)."""
    return metres / float(scene.view_radius)


def shipped_scene(name: str, width: int | None = None, height: int | None = None, **over):
    """`shipped_doc(name, width, height, **over)` loaded (the scene's name: `name`)."""
    return jaxvcm.scene_from_dict(shipped_doc(name, width, height, **over), name)


# ---------------------------------------------------------------- closed boxes
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


# ---------------------------------------------------------------- flat water
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


def flat_water_sun(depth, sigma_a, ior, albedo, cam_height, sun_dir, E, fov=70.0, w=16, h=16):
    """A flat pool (footprint [-1, 1]^2, floor `depth` below the surface, floor rect 2 m x
    2 m of `albedo`) lit by the sun (direction `sun_dir`, irradiance E); camera
    `cam_height` above the floor, looking straight down."""
    return {
        "camera": camera((0.0, -depth + cam_height, 0.0), (0.0, -depth - 1.0, 0.0), fov, w, h,
                         up=(0.0, 0.0, -1.0)),
        "materials": {"floor": {"type": "diffuse", "albedo": albedo}},
        "shapes": [{"type": "rect", "center": [0.0, -depth, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [2.0, 2.0], "material": "floor"}],
        "water": {"level": 0.0, "sigma_a": list(sigma_a), "sigma_s": 0.0, "ior": ior,
                  "footprint": [-1.0, 1.0, -1.0, 1.0], "floor": -depth - 0.01},
        "lights": [{"type": "sun", "direction": list(sun_dir), "irradiance": E}],
    }
