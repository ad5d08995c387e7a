"""Light tracing and bidirectional path tracing on the one core, checked against analytic
values and against each other (within K standard errors from independent passes)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm import technique_images
from jaxvcm._materials import fresnel_dielectric

from .. import _analytic as A
from .. import _scenes as S

K = 4.5
ALGS = ["pt", "lt", "bdpt"]


def assert_close(m1, s1, m2, s2=0.0, k=K, rel=1e-5, what=""):
    m1, s1, m2, s2 = map(np.asarray, (m1, s1, m2, s2))
    tol = k * np.sqrt(s1**2 + s2**2) + rel * np.abs(m2)
    err = np.abs(m1 - m2)
    assert np.all(err <= tol), f"{what}: {m1} vs {m2}, |err| {err} > tol {tol}"


@functools.partial(jax.jit, static_argnums=2)
def _tech(scene, keys, cfg):
    return jax.lax.map(lambda k: technique_images(scene, k, cfg)[0], keys)  # see A._passes


def technique_stats(scene, cfg, passes, seed=0, batch=8):
    """{Technique: [P, H, W, C]} over `passes` independent passes."""
    out = {}
    for b0 in range(0, passes, batch):
        keys = jnp.stack([jaxvcm.pass_key(seed, b0 + i) for i in range(min(batch, passes - b0))])
        for st, v in _tech(scene, keys, cfg).items():
            out.setdefault(st, []).append(np.asarray(v, np.float64))
    return {st: np.concatenate(v) for st, v in out.items()}


# ---------------------------------------------------------------- furnace, every algorithm
@pytest.mark.parametrize("spp", [1, 4], ids=lambda v: f"spp{v}")
@pytest.mark.parametrize("alg", ALGS)
def test_sphere_furnace_all_algorithms_per_path_length(alg, spp):
    # Closed emitting sphere, albedo a, camera inside (see test_transport): every path of
    # k segments contributes exactly Le a^(k-1), and every algorithm, summed over its
    # techniques for that k, must reproduce it. Checking each k separately catches a
    # wrong MIS weight even where the total would hide it. spp = 4 (8x8 pixels, the same
    # 256 light paths): light-tracing splats carry 1/N_light already and must not be
    # averaged over spp again (doing so would make LT spp times too dark).
    Le, a, D = np.array([0.5, 1.0, 2.0]), np.array([0.3, 0.6, 0.9]), 4
    w = 16 if spp == 1 else 8
    scene = jaxvcm.scene_from_dict(S.sphere_furnace(Le, a, w=w, h=w))
    tech = technique_stats(scene, RenderConfig(algorithm=alg, max_depth=D, rr_depth=100,
                                               spp=spp),
                           passes=24 if alg == "lt" else 8)
    for k in range(1, D + 1):
        per = sum(v for lab, v in tech.items() if lab.s + lab.t - 1 == k)  # [P, H, W, C]
        assert all(lab.kind == "connection" for lab in tech)
        x = per.mean(axis=(1, 2))  # image mean per pass: P i.i.d. samples
        assert np.all(np.isfinite(per))
        assert_close(x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x)), Le * a ** (k - 1),
                     what=f"{alg} k={k}")


@pytest.mark.parametrize("alg", ["pt", "bdpt"])
def test_medium_furnace_bidirectional(alg):
    # Pure-scattering chromatic water box with emitting walls: radiance Le everywhere
    # (truncation at D = 16: P(no wall within 16 segments) <= 0.58^16 = 1.7e-4 relative,
    # a fifth of the standard error here; the test tolerates it via rel=3e-4).
    # Light tracing alone is not used here: from medium vertices next to the camera its
    # splats carry 1/d^2 with infinite variance (standard errors are not trustworthy);
    # inside BDPT the MIS weights tame that term.
    Le = np.array([1.0, 2.0, 0.5])
    scene = jaxvcm.scene_from_dict(S.medium_furnace(Le, (0.1, 0.25, 0.5), w=12, h=12))
    _, _, imgs, bad = A.render_stats(scene, RenderConfig(algorithm=alg, max_depth=16,
                                                         rr_depth=100), passes=8)
    assert bad == 0
    m, s = A.pooled(imgs)
    assert_close(m, s, Le, rel=3e-4, what=f"medium furnace {alg}")


def test_technique_images_sum_to_the_bdpt_image():
    scene = jaxvcm.load_scene("scenes/pool.toml", width=12, height=12)
    cfg = RenderConfig(algorithm="bdpt", max_depth=5)
    key = jax.random.key(3)
    # both in one program (one compile; XLA shares the common work)
    tech, (img, diag) = jax.jit(lambda s, k: (technique_images(s, k, cfg)[0],
                                              jaxvcm.render_pass(s, k, cfg)))(scene, key)
    D = cfg.max_depth
    # every technique with k = s + t - 1 <= D is present: s = 0..D, t = 1..D+1
    expected = {(s, t) for s in range(0, D + 1) for t in range(1, D + 2)
                if 1 <= s + t - 1 <= D and not (s == 0 and t == 1)}
    assert all(lab.kind == "connection" for lab in tech.labels)
    assert {(lab.s, lab.t) for lab in tech.labels} == expected
    assert len(tech.labels) == len(expected)
    total = sum(np.asarray(v, np.float64) for _, v in tech.items())
    for _, v in tech.items():
        assert np.all(np.isfinite(np.asarray(v)))
    np.testing.assert_allclose(np.asarray(img), total, rtol=1e-5, atol=1e-6)
    assert int(diag.nonfinite) == 0


# ---------------------------------------------------------------- shipped scenes
def block_means(imgs, b=4):
    P, H, W, C = imgs.shape
    return imgs.reshape(P, b, H // b, b, W // b, C).mean(axis=(2, 4))  # [P, b, b, C]


def assert_algorithms_agree(scene, algs, max_depth, seed, passes=24, blocks=4, what="",
                            spp=16, heavy=()):
    """Independent renders of each algorithm (different seeds); block means agree within K
    combined standard errors, and so do the image means (per channel), whose combined
    standard error must be below 1.25 % of the value: a 5 % difference between two
    algorithms is then K = 4 standard errors away and fails. `heavy`: algorithms whose
    estimate, or the first's, is heavy-tailed on this scene (the standard error of their
    difference is then not a measure of its error): compared the same way, without the 5 %
    assertion. Returns the first algorithm's block means."""
    res, means = [], []
    for n, alg in enumerate(algs):
        _, _, imgs, bad = A.render_stats(scene, RenderConfig(algorithm=alg, max_depth=max_depth,
                                                             spp=spp),
                                         passes=passes, seed=seed + n)
        assert bad == 0
        bm = block_means(imgs, blocks)
        res.append((bm.mean(0), bm.std(0, ddof=1) / np.sqrt(bm.shape[0])))
        x = imgs.mean(axis=(1, 2))  # image mean per pass: i.i.d. samples
        means.append((x.mean(0), x.std(0, ddof=1) / np.sqrt(x.shape[0])))
    for n, other in enumerate(res[1:], 1):
        assert_close(*res[0], *other, rel=1e-3, what=f"{what} {algs[0]} vs {algs[n]}")
        (m0, s0), (m1, s1) = means[0], means[n]
        se = np.sqrt(s0**2 + s1**2)
        assert algs[n] in heavy or np.all(se < 0.0125 * m0), (
            f"{what}: SE of the image-mean difference {algs[0]} - {algs[n]} is "
            f"{se / m0} of the value: cannot see a 5 % difference at 4 SE")
        assert np.all(np.abs(m1 - m0) <= 4 * se), (
            f"{what}: image means {algs[n]} {m1} vs {algs[0]} {m0} (SE {se})")
    return res[0][0]


@pytest.mark.parametrize("name", ["pool_sky", "pool"])
def test_pt_bdpt_and_vcm_agree_on_pool(name):
    # All three estimate the same (depth-truncated) image; compare 4x4 block means. VCM adds
    # the merging bias, which at the default radius (0.005 R_v ~ 13 mm on the pool, R_v the
    # view radius, shrinking with the passes) is far below these standard errors
    # (tests/merge/test_merge.py measures the bias against radius on a scene built to show
    # it; on the pool see test_vcm_and_ppm_agree_on_pool). max_depth 4: every technique
    # family of paths up to 4 segments (camera -> surface -> floor -> surface -> light
    # included).
    # pool_sky: 32 passes of 16 spp, SE of the image-mean difference ~1.0 % of the value.
    # pool (a small light above the water): the floor seen through the surface is lit only
    # by paths camera -> surface -> floor -> surface -> light, which pt and bdpt sample only
    # by hitting the light through two refractions (rare, huge samples: their standard
    # error says nothing; measured 5 % at 16 x 1 spp, 44-50 % at 24 x 16). Both comparisons
    # here have pt on one side, so the pool keeps the block comparison within the standard
    # errors (16 passes of 1 spp), without the 5 % assertion (`heavy`). vcm itself merges
    # those paths and is not heavy-tailed there (given the pdfs after delta vertices of
    # jaxvcm/_subpath.py, "Delta vertices"); it is checked at the 5 % bar against ppm,
    # paired, by test_vcm_and_ppm_agree_on_pool, and the pool's geometry and water by
    # pool_sky here and the caustic reference (tests/transport/test_caustics.py).
    scene = S.shipped_scene(name, 16, 16)
    if name == "pool_sky":
        assert_algorithms_agree(scene, ("pt", "bdpt", "vcm"), 4, seed=11, passes=32, what=name)
    else:
        assert_algorithms_agree(scene, ("pt", "bdpt", "vcm"), 4, seed=11, passes=16, spp=1,
                                what=name, heavy=("bdpt", "vcm"))


def test_vcm_and_ppm_agree_on_pool():
    # The default pool at the 5 % bar: vcm against ppm, which merges the floor's
    # specular-diffuse-specular light too (pt and bdpt cannot: see above). Paired: both
    # render the same passes (seed 41: the same keys, so the same camera paths, the same
    # glints and largely the same photons); the per-pass difference of the (glint-free, see
    # below) image means has an SD of 0.3-0.9 % of the value, against ~3.5 % for either
    # image alone (30-70 % with the glints; unpaired, the SE at 12 passes would be ~1.4 %).
    # Valid: each pass gives the difference of two estimators of the same (depth-truncated)
    # image, unbiased up to their merging biases, and the passes have independent keys and
    # the same radius (pass_index 0), so the 12 differences are i.i.d. and SD / sqrt(12) is
    # the standard error of their mean, whatever the correlation of the two images inside a
    # pass.
    # Glints: a camera sample that the water reflects into the light (the Fresnel reflection
    # is chosen with probability F: throughput 1) carries the light's whole radiance, Le / spp
    # on its pixel, ~5 times in 12 passes (~30 % of the image mean, 40 % in red). Both
    # algorithms add it by the same code with weight 1 (no other technique samples it), so
    # it cancels in every pair; but it makes the value itself noisy, and would hide a 5 %
    # error of one image in its variance. Pixels where both images are above Le / (2 spp)
    # are left out of both (all others stay below Le / (25 spp)): the mask depends on that
    # one camera sample, independent of the pixel's other samples and of the photons, so it
    # scales both expectations alike. The value is the glint-free image mean.
    # Bias: r = 0.02 R_v (~5.1 cm). The disk kernel near a surface's edge (the basin's
    # rim, its corners: the kernel takes only its own surface's photons) loses the disk's
    # part beyond the edge, (2 / (3 pi)) r of radiance per unit edge length; ppm merges at
    # every first diffuse vertex, vcm with a merging weight that grows with eta = pi r^2 N,
    # so vcm - ppm ~ |B_ppm(r)| (1 - w(eta)): positive, below ppm's own bias, shrinking
    # with r (at fixed eta) and as N grows (at fixed r). Measured (% of the value, R/G/B,
    # 64 passes over 4 seeds): ppm(0.02) - ppm(0.01) = -2.5/-1.5/-1.4 (+-0.3-0.4), vcm - ppm =
    # +1.1/+0.6/+0.5 (+-0.09/0.05/0.05) here, +2.0/+1.1/+1.0 at 32 spp (smaller eta), 95 %
    # of it on the pixels of the walls' rims and corners. Allowance: 2 % of the value, the
    # measured red value + 10 of its SE; with 4 SE (0.5-1 %) the tolerance is 2.5-3 %, so a
    # 5 % error of either image, either way, fails (planted, 4 seeds: beyond the tolerance
    # by 3-27 SE in red, >= 10 SE in green and blue).
    scene = S.shipped_scene("pool", 16, 16)
    Le = float(np.max(S.shipped_doc("pool")["lights"][0]["radiance"]))
    spp, bias = 64, 0.02
    imgs = {}
    for alg in ("vcm", "ppm"):
        _, _, imgs[alg], bad = A.render_stats(
            scene, RenderConfig(algorithm=alg, max_depth=4, spp=spp, radius=0.02), passes=12,
            seed=41, batch=12)
        assert bad == 0
    glint = np.minimum(imgs["vcm"], imgs["ppm"]).max(-1, keepdims=True) > 0.5 * Le / spp
    x = {alg: np.where(glint, 0.0, v).mean(axis=(1, 2)) for alg, v in imgs.items()}  # [P, C]
    d = x["vcm"] - x["ppm"]  # per pass: i.i.d.
    m = 0.5 * (x["vcm"].mean(0) + x["ppm"].mean(0))
    diff, se = d.mean(0), d.std(0, ddof=1) / np.sqrt(len(d))
    assert np.all(se < 0.0125 * m), (
        f"pool vcm - ppm (paired): SE {se / m} of the value: a 5 % difference would not be "
        f"4 standard errors away")
    tol = 4 * se + bias * m
    assert np.all(np.abs(diff) <= tol), (
        f"pool vcm - ppm (paired): image means differ by {diff / m} of the value, beyond "
        f"4 SE ({4 * se / m}) + the merging-bias allowance ({bias})")


def test_lt_and_bdpt_agree_on_directly_lit_wall():
    # pool_wall: camera above the water looking at the tall wall lit by the low sun, both
    # directly and by light reflected off the water (a caustic path sun -> water -> wall ->
    # camera that only light tracing can sample). Crop to the wall above the water line.
    scene = S.shipped_scene("pool_wall", 16, 16, camera__target=[0.0, 0.9, -1.0],
                             camera__fov=30)
    assert_algorithms_agree(scene, ("lt", "bdpt"), 4, seed=21, what="pool_wall")


def test_lt_and_bdpt_agree_on_sun_caustics_from_under_water():
    # pool_sun seen from under the water: the floor's caustics (sun -> wavy surface ->
    # floor -> camera) are made by light tracing alone; BDPT must match it.
    scene = S.shipped_scene("pool_sun", 16, 16, camera__position=[0.3, -0.6, 0.5],
                            camera__target=[-0.2, -1.2, -0.4], camera__fov=60)
    # light tracing's caustics are noisy: 24 passes of 64 spp for an SE near 1 %
    lt = assert_algorithms_agree(scene, ("lt", "bdpt", "vcm"), 4, seed=31, blocks=2,
                                 passes=24, spp=64, what="pool_sun under water")
    assert np.all(lt > 0)


# ---------------------------------------------------------------- flat water, sun, camera under water
@pytest.mark.parametrize("alg", ["lt", "bdpt"])
def test_flat_water_sun_floor_seen_from_under_water(alg):
    # Sun (irradiance E on a plane normal to it) over flat water; camera under water,
    # h = 0.6 m above a Lambertian floor (albedo a) at depth d = 1 m, looking down.
    # Flux through the surface per horizontal area: E cos(theta_i); the fraction T(theta_i)
    # is refracted to theta_t (sin theta_t = sin theta_i / eta) and crosses d / cos theta_t
    # of water, and the parallel beam keeps its horizontal footprint, so
    #   E_floor = E cos(theta_i) T(theta_i) exp(-sigma_a d / cos theta_t),  L_f = a E_floor / pi.
    # The camera sees L_f exp(-sigma_a s), s = h / cos(phi) for the pixel ray at angle phi
    # from the vertical; the expected image mean is computed from the exact pinhole ray
    # distribution below. max_depth = 3 keeps only sun -> surface -> floor -> camera (the
    # floor's light returned by the surface needs >= 5 segments). Only light tracing can
    # make this path (the surface is a delta vertex next to the delta sun), so BDPT's
    # weight for it is 1, and PT renders black.
    d, h, a, eta, E = 1.0, 0.6, 0.7, 1.33, 3.0
    sigma_a = np.array([0.3, 0.1, 0.05])
    sun = np.array([-0.25, -1.0, 0.2])
    sun = sun / np.linalg.norm(sun)
    cos_i = -sun[1]
    T = 1.0 - float(fresnel_dielectric(cos_i, eta)[0])
    cos_t = np.sqrt(1 - (1 - cos_i**2) / eta**2)
    L_f = a / np.pi * E * cos_i * T * np.exp(-sigma_a * d / cos_t)
    scene = jaxvcm.scene_from_dict(S.flat_water_sun(d, sigma_a, eta, a, h, sun, E))
    # expected image mean: pinhole directions uniform over the film (jittered pixels)
    rng = np.random.default_rng(0)
    th = np.tan(np.radians(70.0) / 2)
    sx, sy = rng.uniform(-th, th, 400_000), rng.uniform(-th, th, 400_000)
    cos_phi = 1.0 / np.sqrt(1 + sx**2 + sy**2)
    expected = L_f * np.exp(-np.outer(h / cos_phi, sigma_a)).mean(0)
    _, _, imgs, bad = A.render_stats(scene, RenderConfig(algorithm=alg, max_depth=3, spp=16),
                                     passes=48)
    assert bad == 0
    x = imgs.mean(axis=(1, 2))
    assert_close(x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x)), expected, rel=1e-3,
                 what=f"flat water sun {alg}")
    # and the comparison has teeth: its standard error is below 1.25 % of the value, so a
    # 5 % error (a missing Fresnel factor, 1/eta^2 applied to importance: 16 %) is beyond
    # 4 standard errors
    se = x.std(0, ddof=1) / np.sqrt(len(x))
    assert np.all(se < 0.0125 * expected), f"SE {se / expected} cannot see 5 % at 4 SE"


def test_pt_cannot_render_the_refracted_sun():
    d = S.flat_water_sun(1.0, (0.3, 0.1, 0.05), 1.33, 0.7, 0.6, (-0.25, -1.0, 0.2), 3.0, w=8, h=8)
    scene = jaxvcm.scene_from_dict(d)
    _, _, imgs, _ = A.render_stats(scene, RenderConfig(algorithm="pt", max_depth=3), passes=2)
    assert np.all(imgs == 0.0)


# ---------------------------------------------------------------- hard cases
HARD = {
    "grazing": dict(camera__position=[0.0, 0.03, 0.95], camera__target=[0.0, 0.02, -1.0]),
    "under_water": dict(camera__position=[0.3, -0.5, 0.4], camera__target=[-0.5, -1.2, -0.6]),
    "optical_depth_100": dict(water__sigma_a=[80.0, 90.0, 100.0], water__sigma_s=[50.0, 60.0, 70.0]),
    "sigma_s_zero": dict(water__sigma_s=0.0),
    # camera on the floor looking at it: connection vertices nearly coincide
    "coincident": dict(camera__position=[0.2, -1.1995, 0.1], camera__target=[0.2, -1.2, 0.0]),
    # light just above the water and almost parallel to it: connections graze the surface
    "grazing_connections": dict(camera__position=[0.0, 0.2, 0.9], camera__target=[0.0, 0.0, -0.9]),
}


@pytest.mark.parametrize("alg", ["lt", "bdpt", "vcm-r0.5"])
@pytest.mark.parametrize("case", sorted(HARD))
def test_hard_cases_finite_bidirectional(case, alg):
    # vcm at a huge (0.5 R_v) merging radius: every camera vertex merges with most
    # photons and eta is large, pushing the MIS weights to their limit; every value stays
    # finite (a vanishing radius is tested in test_merge::test_merging_extreme_radii).
    d = S.shipped_doc("pool", 10, 10, **HARD[case])
    if case == "grazing_connections":
        d["lights"][0].update(center=[0.0, 0.11, -0.9], normal=[0.0, -0.05, 1.0])
    scene = jaxvcm.scene_from_dict(d, case)
    alg, _, r = alg.partition("-r")
    cfg = RenderConfig(algorithm=alg, max_depth=5, **({"radius": float(r)} if r else {}))
    _, _, imgs, bad = A.render_stats(scene, cfg, passes=2)
    assert bad == 0
    assert np.all(np.isfinite(imgs)) and np.all(imgs >= 0)
