"""The disk that the sun's (sky's, background's) photons start on, and the merging radius's
reference length, come from the surfaces light can reach, never from the camera.

`Scene.bounds` is the box of the shapes and the water (`_io._scene_file._geometry`): every
line that meets a surface passes through the sphere around that box, so the bounding disk
covers every photon that can land (unbiased by construction), and a camera further back no
longer thins the photons that land or widens the default merging radius.
"""

from __future__ import annotations

import numpy as np

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._scene import bounding_sphere

from .. import _analytic as A
from .. import _scenes as S

E, ALBEDO = 3.0, 0.6
SUN = np.array([-0.3, -1.0, 0.2]) / np.linalg.norm([-0.3, -1.0, 0.2])


def _plane(cam_height: float) -> dict:
    """A 2 m x 2 m Lambertian plane at y = 0 under the sun, the camera `cam_height` above
    its centre looking straight down with a field of view that stays on the plane."""
    fov = float(np.degrees(2 * np.arctan(0.5 / cam_height)))  # the central 1 m x 1 m
    return {
        "camera": S.camera((0.0, cam_height, 0.0), (0.0, 0.0, 0.0), fov, 4, 4,
                           up=(0.0, 0.0, -1.0)),
        "materials": {"plane": {"type": "diffuse", "albedo": ALBEDO}},
        "shapes": [{"type": "rect", "center": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [2.0, 2.0], "material": "plane"}],
        "lights": [{"type": "sun", "direction": SUN.tolist(), "irradiance": E}],
    }


def test_bounds_hold_the_surfaces_not_the_camera():
    near = jaxvcm.scene_from_dict(_plane(3.0))
    far = jaxvcm.scene_from_dict(_plane(40.0))
    # the plane's box: [-1, 1] x [0, 0] x [-1, 1] whatever the camera's height
    for s in (near, far):
        np.testing.assert_array_equal(np.asarray(s.bounds), [[-1, 0, -1], [1, 0, 1]])
    # bounding radius sqrt(2): the sun's disk is pi R^2 = 2 pi m^2, of which the plane's
    # projection |cos| x 4 m^2 is what lands
    assert float(bounding_sphere(far)[1]) == np.float32(np.sqrt(2.0))
    # the pool: its camera (3.5 m up) stood above its light (3.0 m): the box's top is the
    # light's rect now
    pool = S.shipped_scene("pool", 4, 4)
    assert float(pool.bounds[1, 1]) == 3.0 and float(pool.camera.origin[1]) == 3.5


def test_light_tracing_from_far_away_sees_the_sunlit_plane():
    # Light tracing (every photon from the sun's disk, connected to the camera) of the
    # plane seen from 40 m: L = albedo E cos(theta) / pi, cos(theta) = -SUN_y.
    # With the camera in the box (its old bounds) the disk's radius was ~20 m and 0.3 %
    # of the photons landed on the plane (|cos| 4 m^2 / (pi 20^2)); from the surfaces'
    # box, 61 % do (|cos| 4 / (2 pi)): the same estimator, its standard error 14x lower.
    # The bound below (SE < 2 % of the value after 16 passes) needs the tight disk: with
    # 0.3 % of the photons landing, 1,024 photons a pass put ~3 on the plane, far too few.
    scene = jaxvcm.scene_from_dict(_plane(40.0))
    expected = ALBEDO * E * float(-SUN[1]) / np.pi
    _, _, imgs, bad = A.render_stats(scene, RenderConfig(algorithm="lt", max_depth=2, spp=64),
                                     passes=16)
    assert bad == 0
    x = imgs.mean(axis=(1, 2))  # [passes, C] image means
    mean, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))
    assert np.all(np.abs(mean - expected) < 4 * se + 1e-4 * expected), (mean, se, expected)
    assert np.all(se < 0.02 * expected), f"SE {se / expected}: the photons do not land"
