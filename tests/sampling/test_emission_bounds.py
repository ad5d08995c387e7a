"""The disk that the sun's (sky's, background's) photons start on comes from the surfaces
light can reach, the merging radius's reference length from the surfaces the camera sees;
neither from where the camera stands.

`Scene.bounds` is the box of the shapes and the water (`_io._scene_file._geometry`): every
line that meets a surface passes through the sphere around that box, so the bounding disk
covers every photon that can land (unbiased by construction), and a camera further back no
longer thins the photons that land. `Scene.view_radius` is half the diagonal of the box of
the non-specular points a fixed grid of camera rays sees, through and in flat water
(`_io._view`): the length `RenderConfig.radius` multiplies.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._io._view import VIEW_RAYS
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


# ---------------------------------------------------------------- the view radius
def test_view_radius_of_a_plane_seen_straight_down():
    # The plane's central 1 m x 1 m fills the view from any height (fov = 2 atan(0.5 / h)),
    # and the outermost of the VIEW_RAYS x VIEW_RAYS rays through pixel centres meet it
    # (1 - 1 / VIEW_RAYS) x 0.5 m from the centre: the view's box is a square of that
    # half-side on the plane, its half diagonal sqrt(2) of it, at 3 m and at 40 m alike
    # (float32 storage: 1e-6). The bounding radius stays sqrt(2) (the whole plane).
    a = 0.5 * (1.0 - 1.0 / VIEW_RAYS)
    for h in (3.0, 40.0):
        s = jaxvcm.scene_from_dict(_plane(h))
        assert float(s.view_radius) == pytest.approx(np.sqrt(2.0) * a, rel=1e-6)
        assert float(bounding_sphere(s)[1]) == pytest.approx(np.sqrt(2.0), rel=1e-6)


def test_view_radius_through_flat_water():
    # flat_water_sky's wide flat pool (no shapes above it), the camera h = 2 m above the surface
    # looking straight down, the floor d = 1 m below it. The film's rays have tangents
    # (sx, sy) on a grid of VIEW_RAYS x VIEW_RAYS pixel centres; the one (sx, sy) meets the
    # surface h (sx, sy) from the axis and refracts towards the floor at sin(theta) =
    # sin(phi) / eta, q = |(sx, sy)| = tan(phi), landing at h (sx, sy) + d tan(theta) (sx,
    # sy) / q; reflected, it leaves (no point). The largest x is that of sx = t_max (the
    # outermost column) with the smallest |sy| = tan(fov / 2) / VIEW_RAYS (the refraction
    # bends the diagonal rays a little more), so the view's box is the floor's square of
    # that half-side and its radius sqrt(2) x that. A camera 10x higher with a 10x narrower
    # view sees nearly the same box; the bounding radius (the 120 m pool) is 3 orders of
    # magnitude larger: the old reference length.
    d, eta = 1.0, 1.33

    def scene(h, tan_half):
        doc = S.flat_water_sky(d, (0.1, 0.1, 0.1), eta, 0.5, d + h)
        doc["camera"]["fov"] = float(np.degrees(2 * np.arctan(tan_half)))
        return jaxvcm.scene_from_dict(doc)

    for h, th in ((2.0, 0.1), (20.0, 0.01)):
        sx, sy = th * (1.0 - 1.0 / VIEW_RAYS), th / VIEW_RAYS
        q = np.hypot(sx, sy)
        sin_t = q / np.sqrt(1.0 + q * q) / eta
        x_max = h * sx + d * sin_t / np.sqrt(1.0 - sin_t**2) * sx / q
        s = scene(h, th)
        assert float(s.view_radius) == pytest.approx(np.sqrt(2.0) * x_max, rel=1e-6)
        assert float(bounding_sphere(s)[1]) > 80.0


def test_default_radius_follows_the_view():
    # The first pass's merging radius is RenderConfig.radius x the view radius, not below
    # what the float32 hash grid resolves at the scene's extent (`_merge.pass_radius`). On
    # the wide pool (the 120 m basin seen through 2 degrees from 3 m: ~10 cm of floor) that
    # is the grid's floor, 2.2 cm, where the bounding radius gave 0.42 m, a blur four times
    # wider than the whole view (merging's bias grows as r^2). On the default pool the
    # camera sees the whole basin and its walls: the view radius equals the bounding radius
    # (the view's box reaches the box's corners within a ray's spacing, and is capped
    # there), and so does the radius.
    from jaxvcm._merge import FLOOR_MARGIN, pass_radius, precise_radius

    wide = jaxvcm.load_scene("scenes/pool_wide.toml", width=8, height=8)
    r = float(pass_radius(RenderConfig(algorithm="vcm"), wide, 0).surface)
    assert 0.09 < float(wide.view_radius) < 0.11
    floor = FLOOR_MARGIN * precise_radius(wide)[0]
    assert r == pytest.approx(max(0.005 * float(wide.view_radius), floor), rel=1e-5)
    assert r < 0.03 and 0.005 * float(bounding_sphere(wide)[1]) > 0.4
    pool = S.shipped_scene("pool", 8, 8)
    assert float(pool.view_radius) == pytest.approx(float(bounding_sphere(pool)[1]), rel=1e-6)
    r = float(pass_radius(RenderConfig(algorithm="vcm"), pool, 0).surface)
    assert r == pytest.approx(0.005 * float(bounding_sphere(pool)[1]), rel=1e-6)
