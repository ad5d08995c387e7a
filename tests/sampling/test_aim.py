"""Aimed emission: sun and sky photons aimed at the water's footprint.

`[[lights]] aim = P` sends a fraction P of a sun's or sky's photons through the water's
footprint (the caustic caster: the line crosses the plane y = level at a point drawn from
`Lights.aim_map`, uniform by default) and the rest over the scene's bounding disk as without aiming.
The emission's perpendicular-area pdf is the mixture
    p(line) = (1 - P) / (pi R^2) + P [crossing in F] G^2 w_ij / (sum w A_F |d_y|),
and every technique's MIS reads it through `_lights.emission_pdf_dir` (light tracing's and
the merges' stored y_0 pdfs, next-event estimation's A(z_j), emitter hits' A(z_{j-1})), so
the estimators stay unbiased whatever P is. Light that never meets the water is still
emitted (the disk part covers every line through the scene), so it is accounted for, and
`test_light_beside_the_pool_is_the_same_aimed_or_not` checks it where it matters.

Tests: (1) the sampler draws the density the pdf states (chi-square of the crossing points
on the water's plane, the sun) and the Monte Carlo identities E[1 / p] = pi R^2 and
E[[in F] / p] = A_F |d_y| per direction (sun and sky); (2) closed forms with aiming on:
the refracted sun on the floor seen from above (ppm, vcm: merging is the only technique;
tests/merge/test_merge.py's value) and from under the water (lt:
tests/transport/test_bidir.py's value);
(3) the ground beside the pool, lit by the sun outside the footprint, renders the same
aimed or not (vcm, ppm). Every comparison asserts a standard error small enough to see 5 %
at 4 standard errors.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jaxvcm
from jaxvcm import RenderConfig, SceneError
from jaxvcm import _lights
from jaxvcm._render import render_pass_host
from jaxvcm._scene import bounding_sphere

from .. import _analytic as A
from .. import _scenes as S
from ..merge.test_merge import D_, E_, ETA, SIGMA_A, SUN, A_
from ..merge.test_merge import expected as expected_from_above

K = 4.0


def _aimed(doc, aim, dtype=jnp.float32):
    doc["lights"][0]["aim"] = aim
    return jaxvcm.scene_from_dict(doc, dtype=dtype)


def _sky_pool(aim):
    return _aimed({
        "camera": S.camera((0.0, 0.5, 0.0), (0.0, -1.0, 0.0), 40.0, 8, 8, up=(0.0, 0.0, -1.0)),
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [{"type": "rect", "center": [0.0, -1.0, 0.0], "normal": [0.0, 1.0, 0.0],
                    "size": [6.0, 6.0], "material": "floor"}],
        "water": {"level": 0.0, "sigma_a": 0.1, "sigma_s": 0.0, "ior": 1.33,
                  "footprint": [-1.0, 1.5, -0.5, 1.0], "floor": -1.01},
        "lights": [{"type": "sky", "radiance": 1.0}]}, aim)


def _emissions(scene, n, seed):
    u = jax.random.uniform(jax.random.key(seed), (n, 5), jnp.float32)
    return jax.jit(jax.vmap(lambda uu: _lights.sample_emission(scene, uu)))(u)


def _crossings(scene, e):
    o, d = (np.stack([np.asarray(c, np.float64) for c in v], -1) for v in (e.o, e.d))
    s = (float(scene.water.level) - o[:, 1]) / d[:, 1]
    return o + d * s[:, None], d


# ---------------------------------------------------------------- (1) the sampler and its pdf
def test_aimed_sun_crossings_follow_the_stated_density():
    # Crossing points of the sun's lines on the plane y = level, counted on a 12 x 12 grid
    # of cells over the footprint [-1, 1]^2 widened by 0.5 m. Expected count of a cell of
    # area a: N a |d_y| p, with p the mixture above: (1 - P) / (pi R^2) on the lines
    # through the bounding disk (cells whose 16 x 16 grid of points all have lines within R
    # of the sphere's centre; the rim's cells are left out), + P / (A_F |d_y|) inside the
    # footprint.
    P, N = 0.7, 400_000
    sc = _aimed(S.flat_water_sun(D_, SIGMA_A, ETA, A_, 1.6, SUN, E_), P)
    c, _ = _crossings(sc, _emissions(sc, N, 0))
    cb, rb = (np.asarray(v, np.float64) for v in bounding_sphere(sc))
    edges = np.linspace(-1.5, 1.5, 13)
    h, _, _ = np.histogram2d(c[:, 0], c[:, 2], bins=[edges, edges])
    mid = 0.5 * (edges[1:] + edges[:-1])
    a = (edges[1] - edges[0]) ** 2
    inside = (np.abs(mid)[:, None] < 1.0) & (np.abs(mid)[None, :] < 1.0)
    sub = edges[0] + (np.arange(12 * 16) + 0.5) * (edges[1] - edges[0]) / 16
    X, Z = np.meshgrid(sub, sub, indexing="ij")
    q = np.stack([X, np.zeros_like(X), Z], -1) - cb  # points on the plane, from the centre
    perp = q - (q @ SUN)[..., None] * SUN
    f = (np.linalg.norm(perp, axis=-1) <= rb).reshape(12, 16, 12, 16).mean(axis=(1, 3))
    dy = abs(SUN[1])
    want = N * a * (f * dy * (1 - P) / (math.pi * rb**2) + inside * P / 4.0)
    # cells whose every line passes through the disk (the rim's f is coarse): the disk of
    # the pool's box (R = 1.50 m) crosses the plane in an ellipse of pi R^2 / |d_y| =
    # 7.4 m^2, the area of 119 cells of 0.0625 m^2, of which 97 lie whole inside it
    ok = f == 1.0
    assert ok.sum() > 90 and np.all(want[ok] > 500)
    chi2 = float(np.sum((h - want)[ok] ** 2 / want[ok]))
    p_value = stats.chi2.sf(chi2, ok.sum())
    assert p_value > 1e-4, f"chi2 {chi2:.0f} over {ok.sum()} cells (p = {p_value:.1e})"
    # ... with power: the footprint's density 10 % off is rejected
    bad = N * a * (f * dy * (1 - P) / (math.pi * rb**2) + inside * P / 4.0 * 1.1)
    assert stats.chi2.sf(float(np.sum((h - bad)[ok] ** 2 / bad[ok])), ok.sum()) < 1e-6


@pytest.mark.parametrize("light", ["sun", "sky"])
def test_aimed_pdf_integrates_to_the_right_areas(light):
    # For each direction the perpendicular density p integrates to 1 over the lines through
    # the bounding disk, so E[1 / p] = pi R^2 (every sampled line is in the disk), and the
    # lines crossing the footprint F have perpendicular area A_F |d_y|: E[[in F] / p] =
    # A_F |d_y|, i.e. E[[in F] / (p A_F |d_y|)] = 1. Both per sample, averaged; a pdf that
    # forgot |d_y| or mis-weighted the mixture moves them by far more than the 4 SE allowed.
    P, N = 0.6, 200_000
    sc = (_aimed(S.flat_water_sun(D_, SIGMA_A, ETA, A_, 1.6, SUN, E_), P) if light == "sun"
          else _sky_pool(P))
    e = _emissions(sc, N, 1)
    c, d = _crossings(sc, e)
    pdf = np.asarray(e.pdf_dir, np.float64)
    _, rb = bounding_sphere(sc)
    x0, x1, z0, z1 = np.asarray(sc.water.footprint, np.float64)
    inF = (c[:, 0] >= x0) & (c[:, 0] < x1) & (c[:, 2] >= z0) & (c[:, 2] < z1)
    for name, g in (("disk", 1.0 / (pdf * math.pi * float(rb) ** 2)),
                    ("footprint", inF / (pdf * (x1 - x0) * (z1 - z0) * np.abs(d[:, 1])))):
        m, se = g.mean(), g.std(ddof=1) / math.sqrt(N)
        assert se < 0.0125, f"{name}: SE {se:.3f} cannot see 5 %"
        assert abs(m - 1.0) < K * se, f"{light} {name}: E = {m:.4f} (SE {se:.4f}), want 1"


def test_aim_bad_input_names_the_field():
    doc = S.flat_water_sun(D_, SIGMA_A, ETA, A_, 1.6, SUN, E_)
    for aim, msg in ((1.0, "below 1"), (-0.1, ">= 0"), ("x", "number")):
        with pytest.raises(SceneError, match=r"lights\[0\]\.aim"):
            _aimed(dict(doc, lights=[dict(doc["lights"][0])]), aim)
    dry = dict(doc, lights=[dict(doc["lights"][0], aim=0.5)])
    dry.pop("water")
    with pytest.raises(SceneError, match=r"lights\[0\]\.aim.*no \[water\]"):
        jaxvcm.scene_from_dict(dry)
    up = dict(doc, lights=[dict(doc["lights"][0], aim=0.5, direction=[0.0, 1.0, 0.0])])
    with pytest.raises(SceneError, match=r"lights\[0\]\.aim.*downwards"):
        jaxvcm.scene_from_dict(up)


# ---------------------------------------------------------------- (2) closed forms, aimed
@pytest.mark.parametrize("alg", ["ppm", "vcm"])
def test_aimed_merging_renders_the_refracted_sun_seen_from_above(alg):
    # tests/merge/test_merge.py's scene and value (camera 0.6 m above flat water looking down at
    # the sunlit floor: E[L] = T0 / eta^2 e^{-sigma_a d} L_f), 90 % of the photons aimed at
    # the footprint (the same standard-error bar as the unaimed twin there, which needs 4x the
    # paths at this narrower field of view).
    # First radius 7.5 cm (the camera sees ~0.3 m of floor: r / R_v = 0.23).
    sc = _aimed(S.flat_water_sun(D_, SIGMA_A, ETA, A_, 1.6, SUN, E_, fov=20.0), 0.9)
    cfg = RenderConfig(algorithm=alg, max_depth=4, radius=S.radius_fraction(sc, 0.075), spp=8)
    imgs = []
    for i in range(64):
        img, diag, cfg = render_pass_host(sc, jaxvcm.pass_key(0, i), cfg, i)
        assert int(diag.nonfinite) == 0
        imgs.append(np.asarray(img, np.float64))
    x = np.array(imgs).mean(axis=(1, 2))
    m, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))
    ex = expected_from_above()
    assert np.all(se < 0.0125 * ex), f"SE {se / ex} cannot see 5 % at 4 SE"
    assert np.all(np.abs(m - ex) <= K * se + 1e-3 * ex), f"{alg}: {m} vs {ex} (SE {se})"


def test_aimed_light_tracing_sees_the_refracted_sun_from_under_water():
    # tests/transport/test_bidir.py's scene and closed form (camera under flat water, 0.6 m
    # above the floor; only light tracing makes sun -> surface -> floor -> camera): the image
    # mean is L_f E[exp(-sigma_a h / cos phi)] over the pinhole's rays.
    from jaxvcm._materials import fresnel_dielectric
    d, h, a, eta, E = 1.0, 0.6, 0.7, 1.33, 3.0
    sigma_a = np.array([0.3, 0.1, 0.05])
    cos_i = -SUN[1]
    T = 1.0 - float(fresnel_dielectric(cos_i, eta)[0])
    cos_t = np.sqrt(1 - (1 - cos_i**2) / eta**2)
    L_f = a / np.pi * E * cos_i * T * np.exp(-sigma_a * d / cos_t)
    rng = np.random.default_rng(0)
    th = np.tan(np.radians(70.0) / 2)
    sx, sy = rng.uniform(-th, th, 400_000), rng.uniform(-th, th, 400_000)
    cos_phi = 1.0 / np.sqrt(1 + sx**2 + sy**2)
    want = L_f * np.exp(-np.outer(h / cos_phi, sigma_a)).mean(0)
    sc = _aimed(S.flat_water_sun(d, sigma_a, eta, a, h, SUN, E), 0.9)
    _, _, imgs, bad = A.render_stats(sc, RenderConfig(algorithm="lt", max_depth=3, spp=8),
                                     passes=40)
    assert bad == 0
    x = imgs.mean(axis=(1, 2))
    m, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))
    assert np.all(se < 0.0125 * want), f"SE {se / want} cannot see 5 % at 4 SE"
    assert np.all(np.abs(m - want) <= K * se + 1e-3 * want), f"lt: {m} vs {want} (SE {se})"


# ---------------------------------------------------------------- (3) light outside the aim
def _pool_and_ground(aim):
    # The flat sunlit pool of tests/transport/test_bidir.py (footprint [-1, 1]^2, floor 1 m
    # down) and, beside it, dry white ground at the water's level (x in [1, 2.5]) that the
    # sun lights directly: lines that never cross the footprint. The camera, 2 m up, sees the pool's
    # floor through the surface (left half, merging only) and the ground (right half).
    doc = S.flat_water_sun(1.0, (0.3, 0.1, 0.05), 1.33, 0.7, 3.0, SUN, 3.0, fov=50.0, w=8, h=8)
    doc["camera"].update(position=[1.0, 2.0, 0.0], target=[1.0, -1.0, 0.0])
    doc["materials"]["ground"] = {"type": "diffuse", "albedo": 0.5}
    doc["shapes"].append({"type": "rect", "center": [1.75, 0.0, 0.0], "normal": [0.0, 1.0, 0.0],
                          "size": [1.5, 2.0], "material": "ground"})
    return _aimed(doc, aim)


@pytest.mark.parametrize("alg", ["bdpt", "ppm"])
def test_light_beside_the_pool_is_the_same_aimed_or_not(alg):
    # Aimed or not, the same image: halves (pool | ground) compared within 4 combined SE.
    # The ground's light starts outside the footprint, on the disk part of the mixture: a
    # mixture without it (or a pdf that forgot it) would lose the ground's light. bdpt is
    # unbiased and weighs next-event estimation against light tracing with the emission
    # pdf on both sides (the ground; the pool's floor is merging's); ppm's gather has no
    # MIS and its kernel estimate's expectation does not depend on where the photons come
    # from, so even its radius bias is the same aimed or not (a large radius for few
    # samples). (vcm is not compared here: at a finite radius its merges' weights use the
    # photon's pdfs for the gather point's path, so near the footprint's edge, where the
    # aimed pdf jumps, its bias moves with the aim; it vanishes with the radius and the
    # closed forms above hold vcm aimed where the floor is lit uniformly.)
    cfg = RenderConfig(algorithm=alg, max_depth=4, radius=0.15, spp=16).tuned(merge_capacity=2048)
    res = []
    for aim, seed in ((0.0, 5), (0.9, 6)):
        _, _, imgs, bad = A.render_stats(_pool_and_ground(aim), cfg,
                                         passes=96 if alg == "ppm" else 48, seed=seed)
        assert bad == 0
        halves = imgs.reshape(imgs.shape[0], imgs.shape[1], 2, -1, 3).mean(axis=(1, 3))
        res.append((halves.mean(0), halves.std(0, ddof=1) / math.sqrt(halves.shape[0])))
    (m0, s0), (m1, s1) = res
    # bdpt: the ground half (the pool's floor seen through the surface is merging's); ppm:
    # the pool half (the aimed photons are 1/10 as dense on the ground: its standard error
    # there would need 10x the passes)
    use = slice(1, 2) if alg == "bdpt" else slice(0, 1)
    m0, m1, se = m0[use], m1[use], np.sqrt(s0**2 + s1**2)[use]
    assert np.all(m0 > 0)
    assert np.all(se < 0.0125 * m0), f"SE {se / m0} cannot see 5 % at 4 SE"
    assert np.all(np.abs(m1 - m0) <= K * se), f"{alg}: aimed {m1} vs not {m0} (SE {se})"


# ---------------------------------------------------------------- (4) aimed where the camera looks
def _flat_pool(width, aim, dtype=jnp.float32):
    # benchmarks/aim_sweep.py's pool: width x width, 1.2 m deep, black walls, sun 14 deg
    # from the zenith, camera 3 m above the centre looking down, 2 deg, 8 x 8 pixels
    h, th = 0.5 * width, math.radians(14.0)
    return _aimed({
        "camera": {"position": [0.0, 3.0, 0.0], "target": [0.0, -1.0, 0.0],
                   "up": [0.0, 0.0, -1.0], "fov": 2.0, "width": 8, "height": 8},
        "materials": {"floor": {"type": "diffuse", "albedo": A_},
                      "wall": {"type": "diffuse", "albedo": 0.0}},
        "shapes": [{"type": "basin", "min": [-h, -1.2, -h], "max": [h, 0.0, h],
                    "floor_material": "floor", "wall_material": "wall"}],
        "water": {"level": 0.0, "sigma_a": list(SIGMA_A), "sigma_s": 0.0, "ior": ETA},
        "lights": [{"type": "sun", "direction": [-math.sin(th), -math.cos(th), 0.0],
                    "irradiance": E_}]}, aim, dtype)


def test_view_guide_aims_at_the_caster_and_sizes_the_radius():
    # The camera sees the floor straight below through 4.2 m of path: one pixel's footprint
    # is 4.2 x 2 tan(1 deg) / 8 = 1.833 cm (refraction at normal incidence does not change
    # it to first order), the first-pass radius that (radius_pixels = 1) as a fraction of
    # the view radius (`Scene.view_radius`, what RenderConfig.radius multiplies), unless the
    # grid's precision needs more (below). The sun's refracted ray comes down to the floor's
    # centre from
    # x = 1.2 tan(theta_t) (sin theta_t = sin 14 deg / 1.33) on the plane, z = 0: the map
    # aims there, inside a box of a few decimetres (the seen spot is ~15 cm wide), and not
    # at the mirrored point x < 0 a symmetric guess would also take.
    # The radius is not below what a float32 hash grid resolves at the pool's extent
    # (|x| 60 m + 120 m = 180 m: cells >= 180 / (2^12 - 2) / (1 + 2^-7) m, i.e. radii
    # >= 2.18 cm) for 10^4 passes of the schedule (x 1.01 x 10^4^(0.25 / 3) = 2.154):
    # 4.75 cm here; a float64 scene takes the footprint.
    sc = _flat_pool(120.0, 0.9)
    sc2, cfg, g = jaxvcm.aim_at_view(sc, RenderConfig(algorithm="vcm", max_depth=4))
    fp = 4.2 * 2.0 * math.tan(math.radians(1.0)) / 8
    assert abs(g.footprint / fp - 1.0) < 0.01, (g.footprint, fp)
    floor = 180.0 / (4094 * 2 * (1 + 2**-7)) * 1.01 * 1e4 ** (0.25 / 3)
    assert abs(cfg.radius * float(sc.view_radius) / floor - 1.0) < 0.01
    sc64 = _flat_pool(120.0, 0.9, dtype=jnp.float64)
    _, cfg64, _ = jaxvcm.aim_at_view(sc64, RenderConfig(algorithm="vcm", max_depth=4))
    assert abs(cfg64.radius * float(sc64.view_radius) / fp - 1.0) < 0.01
    x0, x1, z0, z1 = g.aim_rect
    assert (x1 - x0) * (z1 - z0) < 0.25, g.aim_rect  # of a 14400 m^2 footprint
    s_t = math.sin(math.radians(14.0)) / ETA
    xc = 1.2 * s_t / math.sqrt(1 - s_t**2)
    G = g.aim_map.shape[0]
    col = lambda x: int((x - x0) / (x1 - x0) * G)  # noqa: E731
    row0 = int((0.0 - z0) / (z1 - z0) * G)
    assert x0 < xc < x1 and g.aim_map[row0, col(xc)] > 0
    assert not (x0 < -xc < x1 and g.aim_map[row0, col(-xc)] > 0)
    np.testing.assert_array_equal(np.asarray(sc2.lights.aim_map), g.aim_map)


@pytest.mark.parametrize("alg", ["ppm", "vcm"])
def test_view_guided_flat_pool_equals_the_closed_form(alg):
    # The 120 m pool of the scale sweep: the camera sees only the refracted sun on the
    # floor (merging's), E[L] = T0 / eta^2 e^{-sigma_a d} L_f as in tests/merge/test_merge.py at
    # depth d = 1.2 m, sun 14 deg. Aimed at the view and at the pixel-footprint radius,
    # 1500 passes of 64 paths bring the standard error of the image mean below 1.25 %;
    # the bounding-disk emission would leave it at tens of percent
    # (docs/benchmarks.md, "Aimed emission").
    from jaxvcm._materials import fresnel_dielectric
    th = math.radians(14.0)
    cos_i = math.cos(th)
    T = 1.0 - float(fresnel_dielectric(cos_i, ETA)[0])
    cos_t = math.sqrt(1 - (1 - cos_i**2) / ETA**2)
    L_f = A_ / math.pi * E_ * cos_i * T * np.exp(-SIGMA_A * 1.2 / cos_t)
    T0 = 1 - ((ETA - 1) / (ETA + 1)) ** 2
    want = T0 / ETA**2 * np.exp(-SIGMA_A * 1.2) * L_f
    sc, cfg, _ = jaxvcm.aim_at_view(_flat_pool(120.0, 0.9),
                                    RenderConfig(algorithm=alg, max_depth=4))
    _, _, imgs, bad = A.render_stats(sc, cfg, passes=1536, batch=256)
    assert bad == 0
    x = imgs.mean(axis=(1, 2))
    m, se = x.mean(0), x.std(0, ddof=1) / math.sqrt(len(x))
    assert np.all(se < 0.0125 * want), f"SE {se / want} cannot see 5 % at 4 SE"
    assert np.all(np.abs(m - want) <= K * se + 1e-3 * want), f"{alg}: {m} vs {want} (SE {se})"


def test_cli_aim_view(tmp_path, capsys):
    # scenes/pool_wide.toml (the wide pool) renders with --aim-view; a scene without
    # an aimed light is refused in one line with exit status 2
    from jaxvcm.cli import main
    out = str(tmp_path / "wide.exr")
    rc = main(["render", "scenes/pool_wide.toml", "--aim-view", "--passes", "2", "--width",
               "8", "--height", "8", "--out", out])
    err = capsys.readouterr().err
    assert rc == 0 and "aimed at" in err, err
    assert main(["render", "scenes/pool_sky.toml", "--aim-view", "--passes", "1",
                 "--out", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--aim-view" in err[0], err
