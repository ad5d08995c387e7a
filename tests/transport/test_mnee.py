"""Manifold next-event estimation (`jaxvcm._mnee`): the light that reaches the floor of a
pool through its surface, against the closed form of a flat surface and against the
techniques it competes with.

Scene: flat water at level 0 over a white floor 1 m down (footprint [-1, 1]^2, no walls),
lit from above by a point light, a small downward-facing rect light and the sun; the
camera 0.5 m above the floor, under the water, looking straight down. With max_depth 3
the only light is pinhole -> floor -> surface (refraction) -> light, so every pixel has a
closed form:

    L(X) = exp(-sigma_a |c - X|) albedo / pi E(X),
    E(X) = sum over light points y of I_y T(theta_a) exp(-sigma_a D / cos theta_w)
           sin theta_a / (rho d rho / d theta_a)
           + E_sun cos theta_i T(theta_i) exp(-sigma_a D / cos theta_t)

(rho(theta_a) = H tan theta_a + D tan theta_w, sin theta_a = eta sin theta_w: the
horizontal distance from y's foot at which light leaving y at theta_a lands at depth D;
d omega = sin theta_a d theta_a d phi over the floor's d A = rho d rho d phi; T the
Fresnel transmittance; the rect light as a 16 x 16 grid of points of intensity
L cos theta_a dA; the sun's parallel beam keeps its horizontal footprint: its flux
E cos theta_i per unit floor), averaged over each pixel's footprint (8 x 8 film points).

Who makes these paths: for the point light and the sun only light tracing (s = 3, t = 1;
bdpt, vcm) and merging (vcm), never PT (its emitter hit cannot hit a point or the sun,
its next-event estimation is blocked by the surface); for the rect light also the
emitter hit. So PT alone renders their share of the floor black (a planted blindness);
with the technique, PT (against the emitter hits), BDPT (and light tracing) and VCM (and
merging at the floor) each give the closed form, every weight of the explicit sums in
play.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from tests import _analytic as A
from tests._scenes import camera

N = 8  # image side
DEPTH, CAM_H, ETA = 1.0, 0.5, 1.33
ALBEDO = 0.8
SIGMA_A = np.array([0.3, 0.1, 0.05])
POINT = np.array([0.25, 1.4, -0.15])
I_POINT = 6.0
RECT_C, RECT_SIZE, RECT_L = np.array([-0.3, 1.1, 0.2]), 0.3, 40.0
SUN = np.array([-0.25, -1.0, 0.2]) / np.linalg.norm([-0.25, -1.0, 0.2])
E_SUN = 3.0


def _scene_doc():
    return {
        "camera": camera((0.0, -DEPTH + CAM_H, 0.0), (0.0, -DEPTH - 1.0, 0.0), 50.0, N, N,
                         up=(0.0, 0.0, -1.0)),
        "materials": {"floor": {"type": "diffuse", "albedo": ALBEDO}},
        "shapes": [{"type": "rect", "center": [0.0, -DEPTH, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [2.0, 2.0], "material": "floor"}],
        "water": {"level": 0.0, "sigma_a": SIGMA_A.tolist(), "sigma_s": 0.0, "ior": ETA,
                  "footprint": [-1.0, 1.0, -1.0, 1.0], "floor": -DEPTH - 0.01},
        "lights": [{"type": "point", "position": POINT.tolist(), "intensity": I_POINT},
                   {"type": "rect", "center": RECT_C.tolist(), "normal": [0.0, -1.0, 0.0],
                    "size": [RECT_SIZE, RECT_SIZE], "radiance": RECT_L},
                   {"type": "sun", "direction": SUN.tolist(), "irradiance": E_SUN}],
    }


def _irradiance(X, y, I_of_cos):
    """Floor irradiance [M, C] at the floor points X [M, 3] from a point y above the flat
    water whose intensity towards the direction at theta_a from the vertical is
    I_of_cos(cos theta_a) (rho inverted by bisection: it increases with theta_a)."""
    H, D = y[1], DEPTH
    P = np.hypot(X[:, 0] - y[0], X[:, 2] - y[2])

    def rho(ta):
        return H * np.tan(ta) + D * np.tan(np.arcsin(np.sin(ta) / ETA))

    lo, hi = np.zeros_like(P), np.full_like(P, 1.5)
    for _ in range(60):
        m = 0.5 * (lo + hi)
        big = rho(m) > P
        lo, hi = np.where(big, lo, m), np.where(big, m, hi)
    ta = 0.5 * (lo + hi)
    tw = np.arcsin(np.sin(ta) / ETA)
    drho = H / np.cos(ta) ** 2 + D / np.cos(tw) ** 2 * np.cos(ta) / (ETA * np.cos(tw))
    T = 1.0 - np.asarray(jaxvcm.fresnel_unpolarised(np.cos(ta), ETA))
    g = I_of_cos(np.cos(ta)) * T * np.sin(ta) / (P * drho)
    return g[:, None] * np.exp(-SIGMA_A[None] * D / np.cos(tw)[:, None])


def _closed_form(scene, lights=("point", "rect", "sun")):
    """[N, N, C] per-pixel means of the module doc's closed form."""
    cam = scene.camera
    f, r, u = (np.asarray(a, float) for a in (cam.forward, cam.right, cam.up))
    t = float(cam.tan_half_fov)
    aspect = cam.width / cam.height
    c = np.asarray(cam.origin, float)
    S = 8  # film points per pixel side
    fx = (np.arange(N * S) + 0.5) / (N * S)
    xf = (2 * fx - 1) * aspect * t
    yf = (1 - 2 * fx) * t
    w = f + xf[None, :, None] * r + yf[:, None, None] * u  # [rows, cols, 3]
    w = (w / np.linalg.norm(w, axis=-1, keepdims=True)).reshape(-1, 3)
    s = (-DEPTH - c[1]) / w[:, 1]
    X = c + s[:, None] * w
    E = np.zeros((len(X), 3))
    if "point" in lights:
        E += _irradiance(X, POINT, lambda ca: I_POINT)
    if "rect" in lights:
        g = (np.arange(16) + 0.5) / 16 - 0.5
        dA = (RECT_SIZE / 16) ** 2
        for a in g:
            for b in g:
                y = RECT_C + np.array([a * RECT_SIZE, 0.0, b * RECT_SIZE])
                E += _irradiance(X, y, lambda ca: RECT_L * ca * dA)
    if "sun" in lights:
        cos_i = -SUN[1]
        cos_t = np.sqrt(1 - (1 - cos_i**2) / ETA**2)
        T = 1.0 - float(jaxvcm.fresnel_unpolarised(cos_i, ETA))
        E += E_SUN * cos_i * T * np.exp(-SIGMA_A * DEPTH / cos_t)[None]
    L = np.exp(-SIGMA_A[None] * s[:, None]) * ALBEDO / np.pi * E
    return L.reshape(N, S, N, S, 3).mean((1, 3))


@pytest.fixture(scope="module")
def setup():
    scene = jaxvcm.scene_from_dict(_scene_doc(), "flat_pool_lights")
    return scene, _closed_form(scene)


def _pooled_ratio(mean, se, ref):
    """Image-wide ratio to the closed form per channel and its standard error (pixels
    summed: their errors are independent)."""
    tot, ref_tot = mean.sum((0, 1)), ref.sum((0, 1))
    return tot / ref_tot, np.sqrt((se**2).sum((0, 1))) / ref_tot


@pytest.mark.parametrize("alg", ["pt", "bdpt", "vcm"])
def test_floor_through_flat_water_matches_the_closed_form(setup, alg):
    # every pixel sees the floor lit only through the surface (max_depth 3): the closed
    # form of the module doc; 96 passes of 64 paths, pooled over the image: the standard
    # error is below 1.25 % per channel (a 5 % error is 4 standard errors). pt: the
    # technique against the rect light's emitter hits; bdpt: and light tracing; vcm: and
    # merging at the floor
    scene, ref = setup
    cfg = RenderConfig(algorithm=alg, max_depth=3, rr_depth=100, manifold_nee=True,
                       radius=0.002)
    mean, se, _, bad = A.render_stats(scene, cfg, passes=96)
    assert bad == 0
    ratio, err = _pooled_ratio(mean, se, ref)
    assert np.all(err < 0.0125), err
    np.testing.assert_array_less(np.abs(ratio - 1.0), 4 * err + 2e-3, err_msg=str(ratio))


def test_pt_alone_leaves_the_point_light_and_the_sun_dark(setup):
    # the planted blindness: without the technique PT's only path to these lights is the
    # emitter hit of the rect light; the point light's and the sun's share never arrives
    scene, ref = setup
    cfg = RenderConfig(algorithm="pt", max_depth=3, rr_depth=100)
    mean, se, _, _ = A.render_stats(scene, cfg, passes=16)
    ratio, _ = _pooled_ratio(mean, se, ref)
    dark = _closed_form(scene, ("point", "sun")).sum((0, 1)) / ref.sum((0, 1))
    assert np.all(dark > 0.3)  # a fair part of the closed form
    assert np.all(ratio < 1.0 - 0.5 * dark), (ratio, dark)


def test_gradients_through_the_root():
    # the point light alone over one small wave, PT with the technique, max_depth 3: every
    # pixel is pinhole -> floor -> the root -> light, a smooth function of the wave's
    # amplitude (the root by the implicit function theorem, G_perp by its derivative), of
    # sigma_a (both segments in the water) and linear in the intensity; reverse mode
    # against central differences of the same fixed-key pass
    import equinox as eqx

    doc = _scene_doc()
    doc["lights"] = doc["lights"][:1]
    doc["water"]["waves"] = [[0.02, 5.0, 3.0, 0.4]]  # focal length ~ 6 m: a 17 % modulation
    scene = jaxvcm.scene_from_dict(doc, "flat_pool_point_wave")
    cfg = RenderConfig(algorithm="pt", max_depth=3, rr_depth=100, manifold_nee=True)
    key = jax.random.key(3)
    # a ramp across the image: the wave moves light between pixels (the image's sum barely
    # changes), the ramp sees the move
    wgt = jnp.asarray(np.linspace(-1.0, 1.0, N)[None, :, None] * np.ones((N, 1, 1)), jnp.float32)

    def total(amp, sig, inten, w):
        s = eqx.tree_at(lambda t: t.water.amp, scene, amp)
        s = eqx.tree_at(lambda t: t.water.sigma_a, s, sig)
        s = eqx.tree_at(lambda t: t.lights.radiance, s, inten)
        return (jaxvcm.render_pass(s, key, cfg)[0] * w).sum()

    p0 = (scene.water.amp, scene.water.sigma_a, scene.lights.radiance)
    # one program for the gradient and the differences: its value is the forward pass (the
    # weights an argument: the ramp and the image's sum alike)
    vg = jax.jit(jax.value_and_grad(total, argnums=(0, 1, 2)))

    def f(*args):
        return vg(*args)[0]

    v0, g = vg(*p0, wgt)
    v0 = float(v0)
    scale = float(f(*p0, jnp.ones_like(wgt)))  # the image's sum
    assert scale > 0
    # the amplitude (h = 1 mm of 20 mm)
    h = 1e-3
    fd = (float(f(p0[0] + h, *p0[1:], wgt)) - float(f(p0[0] - h, *p0[1:], wgt))) / (2 * h)
    assert abs(fd) * 0.02 > 0.02 * scale  # the amplitude matters
    np.testing.assert_allclose(float(g[0][0]), fd, rtol=0.03)
    # sigma_a of the green channel
    e = jnp.array([0.0, 0.02, 0.0], jnp.float32)
    fd = (float(f(p0[0], p0[1] + e, p0[2], wgt)) - float(f(p0[0], p0[1] - e, p0[2], wgt))) / 0.04
    np.testing.assert_allclose(float(g[1][1]), fd, rtol=0.02)
    # linear in the intensity: sum_c I_c d total / d I_c = total
    np.testing.assert_allclose(float(jnp.sum(g[2] * p0[2])), v0, rtol=1e-4)


@pytest.mark.parametrize("kw", [dict(algorithm="ppm"), dict(algorithm="lt"),
                                dict(algorithm="vcm", mis_form="recursive")],
                         ids=["ppm", "lt", "recursive"])
def test_configurations_without_the_technique_are_refused(kw):
    # ppm takes no weights, lt has no camera vertices, and the recursive form has no term
    # for a technique through a delta vertex: each refused in one line naming the field
    with pytest.raises(ValueError, match=r"^config\.manifold_nee: [^\n]*$"):
        RenderConfig(manifold_nee=True, **kw)
    assert RenderConfig(algorithm="bpm", manifold_nee=True).record()["manifold_nee"] is True



def test_wide_sunlit_pool_with_interreflection_matches_the_closed_form():
    # benchmarks/wide_pool.py's pool (120 m wide, 1.2 m deep, the sun 14 degrees from the
    # zenith, camera 3 m above looking straight down, 8 x 8 pixels) at max depth 6: the
    # floor's direct sunlight and one floor -> surface -> floor round trip of light that
    # entered the water metres away (6.9 / 18.4 / 24.3 % of the R / G / B value:
    # jaxvcm.sun_floor_radiance with 1 round trip against 0), E[L] = T0 / eta^2
    # exp(-sigma_a d) L_f. PT with the technique: every floor vertex connects to the sun
    # through the flat surface (one root, deterministic), so only the bounce directions are
    # random. 32 passes of 64 pixels, pooled (every pixel has the same value within 2e-4,
    # and PT's pixels are independent): SE 0.4-0.6 % per channel, below 1.25 %; the direct
    # light alone (a technique blind to the round trip) is 27-31 SE away in G and B (the
    # bench's 60 s of depth 10: within 0.03 %, SE 0.02-0.03 %)
    from benchmarks import wide_pool as W
    from benchmarks.aim_sweep import pool

    scene = jaxvcm.scene_from_dict(pool(W.WIDTH), "wide_sunlit_pool")
    cfg = RenderConfig(algorithm="pt", max_depth=6, manifold_nee=True)
    _, _, imgs, bad = A.render_stats(scene, cfg, passes=32)
    assert bad == 0
    m, se = A.pooled(imgs)
    ref, direct = W.expected(6), W.expected(4)
    assert np.all(se < 0.0125 * ref), se / ref
    np.testing.assert_array_less(np.abs(m - ref), 4 * se, err_msg=f"{m / ref - 1}")
    assert np.all(np.abs(m - direct)[1:] > 4 * se[1:])  # the round trip is seen
