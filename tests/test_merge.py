"""Progressive photon mapping (`ppm`) on the bidirectional core: the floor under flat
water lit by the sun, seen from ABOVE the water (sun -> refraction -> floor -> refraction
-> camera: a specular-diffuse-specular path no connection technique can sample)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._materials import fresnel_dielectric
from jaxvcm._render import _render_pass_jit, render_pass_host

from . import _analytic as A
from .test_bidir import flat_water_sun

K = 4.5
D_, A_, ETA, E_ = 1.0, 0.7, 1.33, 3.0
SIGMA_A = np.array([0.3, 0.1, 0.05])
SUN = np.array([-0.25, -1.0, 0.2]) / np.linalg.norm([-0.25, -1.0, 0.2])


def scene(w=16, h=16):
    # camera 0.6 m above the water (1.6 m above the floor), looking straight down, fov 20
    return jaxvcm.scene_from_dict(flat_water_sun(D_, SIGMA_A, ETA, A_, 1.6, SUN, E_, fov=20.0,
                                                 w=w, h=h))


def expected():
    # Floor radiance as in test_bidir (flat water, sun): L_f = a/pi E cos_i T(i) e^{-sa d/cos_t}.
    # Seen from above through the surface at near-normal incidence (|pixel angle| < 14 deg,
    # Fresnel and path-length changes < 0.6%): camera paths refract with probability T0 and
    # carry 1/eta^2 (water -> air radiance) and e^{-sigma_a d}:
    #   E[L] = T0 / eta^2 e^{-sigma_a d} L_f.
    # The floor is uniformly lit, so the density estimate has no radius bias here.
    cos_i = -SUN[1]
    T = 1.0 - float(fresnel_dielectric(cos_i, ETA)[0])
    cos_t = np.sqrt(1 - (1 - cos_i**2) / ETA**2)
    L_f = A_ / np.pi * E_ * cos_i * T * np.exp(-SIGMA_A * D_ / cos_t)
    T0 = 1 - ((ETA - 1) / (ETA + 1)) ** 2
    return T0 / ETA**2 * np.exp(-SIGMA_A * D_) * L_f


@pytest.mark.parametrize("alg", ["ppm", "vcm"])
def test_merging_renders_refracted_sun_seen_from_above(alg):
    # vcm: merging is the only technique that can make these paths, so its MIS weight
    # must come out exactly 1 and the result must equal the analytic value as for ppm
    sc = scene()
    cfg = RenderConfig(algorithm=alg, max_depth=4, radius=0.05)
    imgs = []
    for i in range(48):
        img, diag, cfg = render_pass_host(sc, jaxvcm.pass_key(0, i), cfg, i)
        assert int(diag.nonfinite) == 0
        imgs.append(np.asarray(img, np.float64))
    x = np.array(imgs).mean(axis=(1, 2))
    m, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))
    ex = expected()
    assert np.all(np.abs(m - ex) <= K * se + 1e-3 * ex), (m, se, ex)
    assert np.all(se < 0.08 * ex)  # the comparison has teeth
    # ... which neither PT nor BDPT can render at all (their image is black here)
    if alg == "ppm":
        for other in ("pt", "bdpt"):
            _, _, im, _ = A.render_stats(sc, RenderConfig(algorithm=other, max_depth=4), passes=2)
            assert np.all(im == 0.0)


def test_merge_overflow_flag_and_host_rerun_is_exact():
    sc = scene(8, 8)
    key = jax.random.key(5)
    small = RenderConfig(algorithm="ppm", max_depth=4, radius=0.2, merge_capacity=2)
    img_s, diag_s = _render_pass_jit(sc, key, small, 0)
    assert bool(diag_s.merge_overflow)  # far more than 2 candidates per gather point
    img_h, diag_h, used = render_pass_host(sc, key, small, 0)
    assert not bool(diag_h.merge_overflow) and used.merge_capacity > 2
    big = dataclasses.replace(small, merge_capacity=used.merge_capacity * 4)
    img_b, diag_b = _render_pass_jit(sc, key, big, 0)
    assert not bool(diag_b.merge_overflow)
    # the re-run with enough room is the exact result (no silently dropped photons)
    np.testing.assert_allclose(np.asarray(img_h), np.asarray(img_b), rtol=1e-6, atol=1e-9)
    assert not np.allclose(np.asarray(img_s), np.asarray(img_b))


@pytest.mark.parametrize("alg", ["ppm", "vcm"])
@pytest.mark.parametrize("r", [1e-6, 0.5])
def test_merging_extreme_radii_are_finite(r, alg):
    sc = jaxvcm.load_scene("scenes/pool_sun.toml", width=8, height=8)
    img, diag, _ = render_pass_host(sc, jax.random.key(0),
                                    RenderConfig(algorithm=alg, max_depth=4, radius=r), 0)
    assert int(diag.nonfinite) == 0 and np.all(np.isfinite(np.asarray(img)))


@pytest.mark.parametrize("alg", ["bpm", "vcm"])
def test_sphere_furnace_merging_per_path_length(alg):
    # Emitting diffuse sphere (test_transport): each path length k carries Le a^(k-1). With
    # merging the photon density on the sphere is uniform, so the disk kernel's bias is
    # only the curvature term O((r/R)^2) ~ 1e-4 for r = 0.01 R_bound; the sum over all
    # connection and merging techniques of each k must reproduce the analytic value.
    from .test_bidir import technique_stats

    Le, a, D = np.array([0.5, 1.0, 2.0]), np.array([0.3, 0.6, 0.9]), 4
    sc = jaxvcm.scene_from_dict(A.sphere_furnace(Le, a, w=12, h=12))
    tech = technique_stats(sc, RenderConfig(algorithm=alg, max_depth=D, rr_depth=100,
                                            radius=0.01), passes=8)
    for k in range(1, D + 1):
        per = 0
        for key, v in tech.items():
            if key[0] == -1:
                # merges at z_j have path lengths j + i for photons y_i: not separable per k
                continue
            if key[0] + key[1] - 1 == k:
                per = per + v
        if k == 1:  # no merging technique for k = 1 (x_0 on the light, x_1 the camera)
            x = per.mean(axis=(1, 2))
            assert np.all(np.abs(x.mean(0) - Le) <= K * x.std(0, ddof=1) / np.sqrt(len(x)) + 1e-4 * Le)
    total = sum(v for v in tech.values()).mean(axis=(1, 2))
    ex = Le * (1 - a**D) / (1 - a)
    se = total.std(0, ddof=1) / np.sqrt(len(total))
    assert np.all(np.abs(total.mean(0) - ex) <= K * se + 3e-4 * ex), (total.mean(0), se, ex)


def test_vcm_agrees_with_bdpt_on_pool_sky():
    # pool_sky has no caustic the connection techniques miss (the sky is hit by camera
    # paths through the surface), so VCM and BDPT converge to the same image up to the
    # merging bias, which at r = 0.002 R_bound (~6 mm) is far below the noise.
    from .test_bidir import block_means, pool_scene

    sc = pool_scene("pool_sky", 16, 16)
    res = {}
    for alg in ("bdpt", "vcm"):
        cfg = RenderConfig(algorithm=alg, max_depth=4, radius=0.002)
        imgs = []
        for i in range(16):
            img, diag, cfg = render_pass_host(sc, jaxvcm.pass_key(40 if alg == "vcm" else 41, i),
                                              cfg, i)
            assert int(diag.nonfinite) == 0
            imgs.append(np.asarray(img, np.float64))
        bm = block_means(np.array(imgs))
        res[alg] = (bm.mean(0), bm.std(0, ddof=1) / np.sqrt(bm.shape[0]))
    (m1, s1), (m2, s2) = res["vcm"], res["bdpt"]
    assert np.all(np.abs(m1 - m2) <= K * np.sqrt(s1**2 + s2**2) + 1e-3 * np.abs(m2))
