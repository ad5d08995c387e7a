"""SmallVCM's Cornell box (scenes/cornell*.toml): the files load with SmallVCM's numbers,
and two algorithms that share no estimator for most of its light agree on it.

bdpt and vcm on cornell_spheres (glossy floor, mirror and glass spheres, the light box):
vcm adds merging, which carries most of the caustic under the glass sphere and the
glossy floor's reflections, and reweights every connection, so a wrong glossy pdf in any
technique (NEE, light tracing, connections, merges) would part them. Image means per
channel over 32 passes (16 x 16 pixels, 8 spp, depth 10): measured rel. SE 0.64 % each,
agreement to 0.2 % (independent seeds: the same seed made their pass means correlate at
0.98, and the combined SE overstate the difference's). pt agrees with both at the same
5 % bar, and in 2 x 2 block means, from 128 x 128 pixels at 1 spp (see its test: what makes
pt noisy here is the light's silhouette, not the caustic)."""

from __future__ import annotations

import functools
import os

import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._scene import (LIGHT_BACKGROUND, LIGHT_POINT, LIGHT_RECT, LIGHT_SUN, MAT_DIELECTRIC,
                           MAT_GLOSSY)

from .. import _analytic as A

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENES = os.path.join(ROOT, "scenes")
VARIANTS = {"cornell": LIGHT_RECT, "cornell_spheres": LIGHT_RECT, "cornell_sun": LIGHT_SUN,
            "cornell_background": LIGHT_BACKGROUND, "cornell_point": LIGHT_POINT}


def _load(name, size=16):
    return jaxvcm.load_scene(os.path.join(SCENES, f"{name}.toml"), width=size, height=size)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_cornell_files_carry_smallvcm_numbers(name):
    sc = _load(name)
    assert sc.lights.kind == (VARIANTS[name],)
    mats = sc.materials
    g = mats.kind.index(MAT_GLOSSY)  # SmallVCM's kGlossyFloor: 0.1 diffuse + 0.7 Phong, n = 90
    np.testing.assert_allclose(np.asarray(mats.albedo[g]), 0.1, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(mats.glossy[g]), 0.7, rtol=1e-6)
    assert float(mats.exponent[g]) == 90.0
    if name != "cornell":
        assert float(mats.ior[mats.kind.index(MAT_DIELECTRIC)]) == pytest.approx(1.6)
    # the box's corners: x [-1.27029, 1.28975], z [-1.28002, 1.28002], back wall y = 1.30455
    b = np.asarray(sc.bounds, np.float64)
    np.testing.assert_allclose(b[:, 0], [-1.27029, 1.28975], atol=1e-5)
    np.testing.assert_allclose(b[:, 2], [-1.28002, 1.28002], atol=1e-5)
    assert b[1, 1] == pytest.approx(1.30455, abs=1e-5)
    if VARIANTS[name] == LIGHT_POINT:  # 70 W / (4 pi) at (0, -0.5, 1)
        np.testing.assert_allclose(np.asarray(sc.lights.radiance[0]), 70 / (4 * np.pi),
                                   rtol=1e-6)
        np.testing.assert_allclose(np.asarray(sc.lights.position[0]), [0.0, -0.5, 1.0])
    if VARIANTS[name] == LIGHT_RECT:  # the light box: 25.0333 over 0.5 x 0.5 m
        np.testing.assert_allclose(np.asarray(sc.lights.radiance[0]), 25.03329895614464,
                                   rtol=1e-6)


@functools.lru_cache(maxsize=None)
def _block_means(alg, size=16, spp=8, passes=32, seed=0):
    """cornell_spheres at depth 10: [passes, 2, 2, C] means of the image's 2 x 2 blocks, one
    row per independent pass (their mean over the blocks is the pass's image mean). Cached:
    bdpt's and vcm's renders serve both tests below."""
    from .test_bidir import block_means
    cfg = RenderConfig(algorithm=alg, max_depth=10, spp=spp, radius=0.01)
    _, _, imgs, bad = A.render_stats(_load("cornell_spheres", size), cfg, passes, seed=seed)
    assert bad == 0
    out = block_means(imgs, 2)
    out.setflags(write=False)
    return out


def _mean_se(x):
    return x.mean(0), x.std(0, ddof=1) / np.sqrt(x.shape[0])


def _assert_image_means_agree(ref, other, what):
    # image means per channel (x.mean(axis=(1, 2)): [passes, C], i.i.d. samples); the SE of
    # the difference must be below 1.25 %, so that a 5 % difference is 4 SE away and fails
    (m0, s0), (m1, s1) = _mean_se(ref.mean(axis=(1, 2))), _mean_se(other.mean(axis=(1, 2)))
    se = np.sqrt(s0 ** 2 + s1 ** 2)
    assert np.all(se < 0.0125 * m0), f"{what}: SE of the difference {se / m0} cannot see 5 %"
    z = np.abs(m1 - m0) / se
    assert np.all(z < 4.0), f"{what}: {m0} vs {m1}: {z} standard errors"


def test_cornell_bdpt_and_vcm_agree():
    _assert_image_means_agree(_block_means("bdpt"), _block_means("vcm", seed=2), "bdpt vs vcm")


# pt: 128 x 128 pixels at 1 spp (16384 camera paths a pass, as many as bdpt's 16 x 16 x 8),
# 32 passes, its own seed: one new compiled program (pt's; it compiles as fast at any film).
PT = dict(size=128, spp=1, passes=32, seed=1)


def test_cornell_pt_agrees_with_bdpt_and_vcm():
    # Why pt converges here: the light is an area light of finite radiance, and each pt
    # sample (camera hits of the light, NEE, BSDF-sampled hits, power-heuristic weights
    # <= 1, roulette survival = the largest reflectance channel) is bounded by about
    # Le = 25: finite variance, so the passes' standard error measures pt's error. The
    # caustic of the glass sphere, which pt reaches only by BSDF-sampled hits of the light
    # through it, is not rare: pt's variance outside the light's own pixels, per path
    # (G channel, per-pixel variances pooled, times a pass's paths), is 0.40-0.41 against
    # bdpt's 0.22. What makes pt noisy is the light's silhouette: a camera ray hits the
    # 25-radiance face or the dim ceiling beside it, and pt takes that hit at weight 1 (bdpt
    # weights it against light tracing): Le^2 c (1 - c) per sample in each pixel that the
    # light covers a part c of. Only the ~W edge pixels carry it, each 1 / W^2 of the mean,
    # so at N paths a pass it adds ~1 / (W N) to the image mean's variance, and a finer film
    # stratifies it (the same film: box pixels, uniform jitter, so the expected image mean
    # and 2 x 2 block means do not depend on W). pt's per-path variance at N = 16384:
    # 16 x 16 x 8 spp 3.0-3.4 (86-88 % in the light's 8 pixels), 32 x 32 x 16 2.0,
    # 64 x 64 x 4 1.05, 128 x 128 x 1 0.65. Per pass the image mean's rel. SD is 17-21 % at
    # 16 x 16 x 8 (2048 paths: ~1800 passes, ~2 min here, for 0.45 %) and 2.3 % at 128 x
    # 128 x 1. Measured over these passes (rel. SE R, G, B): pt 0.45, 0.52, 0.47 %; bdpt
    # 0.65, 0.63, 0.56 % and vcm 0.64, 0.62, 0.55 % (vcm measured at seed 0);
    # differences' SE 0.72-0.82 %, pt within 0.8 SE (0.3-0.7 %) of both. A 5 % error
    # (pt or bdpt scaled by 1.05 or 0.95) fails at 5.2-7.5 SE. 2 x 2 block means (bdpt's
    # sphere blocks: SE 1.7-4.3 %) within 4 SE.
    from .test_bidir import assert_close
    pt = _block_means("pt", **PT)
    for name, seed in (("bdpt", 0), ("vcm", 2)):
        ref = _block_means(name, seed=seed)
        _assert_image_means_agree(ref, pt, f"{name} vs pt")
        assert_close(*_mean_se(ref), *_mean_se(pt), k=4.0, rel=1e-3,
                     what=f"2 x 2 block means, {name} vs pt")


def test_cornell_background_pt_bdpt_and_vcm_agree():
    # SmallVCM's scene 3 (the background light through the open front, glossy floor,
    # mirror and glass spheres): a large light, so pt converges too. pt (NEE + BSDF hits),
    # bdpt and vcm (merging at the default radius) estimate the same image
    # (depth 4): 2 x 2 block means within 4 combined standard errors, and image means
    # whose combined standard error is below 1.25 % (a 5 % difference would fail;
    # test_bidir.assert_algorithms_agree).
    from .test_bidir import assert_algorithms_agree
    assert_algorithms_agree(_load("cornell_background"), ("bdpt", "pt", "vcm"), 4, seed=41,
                            passes=16, spp=16, blocks=2, what="cornell_background")
