"""SmallVCM's background light (constant radiance from every direction) and glass on a
shape (the smooth dielectric of the water surface, as a `glass` material), against closed
forms. A convex object under a uniform background of radiance L sees L over the whole
hemisphere of every surface point, with nothing occluding it:
- a Lambertian sphere of albedo a leaves a L towards the camera (one bounce, exactly:
  L_o = a/pi * integral of L cos over the hemisphere = a L);
- a lossless glass sphere is invisible: every camera path leaves it again (inside a
  sphere the angle of incidence equals the refraction angle at entry, so no total internal
  reflection traps it), refraction scales radiance by 1/eta^2 going in and eta^2 coming
  out, and Fresnel reflection and transmission are sampled by their probabilities, so
  every pixel is L (truncation at max_depth 8 loses ~R^7 < 1e-9).
The camera sees only the sphere (20 degree field of view from 4 radii away: the image's
corners are 14.0 degrees off axis, the sphere's silhouette 14.5), so every pixel of every
pass is one sample of the same expectation (pooled)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig, SceneError

from .. import _analytic as A
from .. import _scenes as S

L = np.array([1.0, 0.5, 0.25])
ALBEDO = 0.6


def _scene(material):
    return jaxvcm.scene_from_dict({
        "camera": S.camera((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), 20.0, 16, 16),
        "materials": {"ball": material},
        "shapes": [{"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0,
                    "material": "ball"}],
        "lights": [{"type": "background", "radiance": L.tolist()}]})


def _check(scene, cfg, want, passes=8):
    _, _, imgs, bad = A.render_stats(scene, cfg, passes)
    assert bad == 0
    m, se = A.pooled(imgs)
    # the standard error must be small enough that a 5 % error fails at 4 SE
    assert np.all(se < 0.0125 * want), f"standard error {se} too large for 5 % of {want}"
    z = np.abs(m - want) / se
    assert np.all(z < 4.0), f"mean {m} vs {want}: {z} standard errors"


# radius 0.01 of the scene's view radius (0.86 m): merging blurs over r / R = 0.86 % of the
# sphere's radius (at 5 % of the bounding radius, r / R = 8.7 %, vcm and bpm measured 5-6 %
# high on this sphere and exact on a flat plane: the consistent estimator's bias on curved surfaces,
# docs/design/pass.md, "Materials and lights")
@pytest.mark.parametrize("alg", ["pt", "vcm"])  # vcm holds every bdpt technique
def test_background_lights_a_diffuse_sphere_to_albedo_times_radiance(alg):
    # measured (8 passes, 4 spp): pt, bdpt 1.0008 x a L (SE 0.28 %)
    cfg = RenderConfig(algorithm=alg, max_depth=8, spp=4, radius=0.01)
    _check(_scene({"type": "diffuse", "albedo": ALBEDO}), cfg, ALBEDO * L)


@pytest.mark.parametrize("alg", ["pt", "vcm"])
def test_glass_sphere_in_a_uniform_background_is_invisible(alg):
    # measured: 1.00007 x L (SE 0.013 %, Russian roulette's 1/q at the glass vertices)
    cfg = RenderConfig(algorithm=alg, max_depth=8, spp=4, radius=0.01)
    _check(_scene({"type": "glass", "ior": 1.5}), cfg, L)


def test_light_tracing_cannot_see_glass():
    # every vertex of a path through glass is delta: no light vertex can be joined to the
    # pinhole, so light tracing renders the glass sphere black (and nothing is non-finite)
    img, diag = jax.jit(jaxvcm.render_pass, static_argnums=2)(
        _scene({"type": "glass", "ior": 1.5}), jaxvcm.pass_key(0, 0),
        RenderConfig(algorithm="lt", max_depth=8))
    assert int(diag.nonfinite) == 0 and float(np.max(np.asarray(img))) == 0.0


@pytest.mark.parametrize("lights,field", [
    ([{"type": "sky", "radiance": 1.0}, {"type": "background", "radiance": 1.0}],
     "lights[1].type"),
    ([{"type": "background", "radiance": 0.0}], "lights[0].radiance"),
], ids=["sky-and-background", "dark-background"])
def test_background_bad_input(lights, field):
    d = {"camera": S.camera((0.0, 0.0, 4.0), (0.0, 0.0, 0.0)), "lights": lights}
    with pytest.raises(SceneError, match=field.replace("[", r"\[").replace("]", r"\]")):
        jaxvcm.scene_from_dict(d)


@pytest.mark.parametrize("mat,field", [
    ({"type": "glass"}, "materials.ball.ior"),
    ({"type": "glass", "ior": 0.5}, "materials.ball.ior"),
    ({"type": "glass", "ior": 1.5, "albedo": 0.5}, "materials.ball.albedo"),
], ids=["no-ior", "ior-below-1", "albedo"])
def test_glass_bad_input(mat, field):
    with pytest.raises(SceneError, match=field):
        _scene(mat)
