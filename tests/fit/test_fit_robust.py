"""Losses under caustic-firefly noise (`fits/caustic_robustness/robust.py`), on toy images
whose noise is planted by hand so that every expected value follows in closed form (no
renderer: < 1 s).

Toy model (the structure of a fixed-key render, see the module docstring): pixel p of a
render is R_p(sigma) = n_p exp(-sigma l) (one water path length l = 2 m, unit expected
brightness at sigma = 0), n_p a fixed noise factor; the converged target is
t_p = exp(-sigma* l). With s = exp(-(sigma - sigma*) l), a fitted scale s corresponds to
sigma = sigma* - ln(s) / l.
"""

from __future__ import annotations

import numpy as np
import pytest

from fits.caustic_robustness import robust as fr

L = 2.0  # water path length (m)
SIGMA_TRUE = 0.3  # 1/m
H = W = 10  # 100 pixels, one channel


def toy_model(n):
    """theta = ln sigma [1] -> (image [H, W, 1], d image / d theta [H, W, 1, 1])."""
    n = np.asarray(n, np.float64).reshape(H, W, 1)

    def model(theta):
        sigma = np.exp(theta[0])
        img = n * np.exp(-sigma * L)
        return img, (img * (-L * sigma))[..., None]

    return model


def target():
    return np.full((H, W, 1), np.exp(-SIGMA_TRUE * L))


def pixel_loss():
    return fr.LinearLoss.from_target(fr.pixel_operator(H, W, (0, 0, W, H)), target(), 0.01)


def region_loss():
    return fr.LinearLoss.from_target(fr.region_operator(H, W, [(0, 0, W, H)]), target(), 0.01)


# 80 pixels n = 0.5, 20 "fireflies" n = 3: mean n = (40 + 60) / 100 = 1 (an unbiased
# estimator), sum n^2 = 80 * 0.25 + 20 * 9 = 200
N_FIREFLY = np.where(np.arange(100) % 5 == 0, 3.0, 0.5)


def test_robust_weights_downweight_a_planted_firefly():
    rng = np.random.default_rng(0)
    r = rng.standard_normal(100)
    r[17] = 50.0
    # MAD scale of 99 standard normals (+ one outlier) ~ 1 (1.4826 MAD = sd for a
    # Gaussian); allow the sampling spread of the median
    s = fr.mad_scale(r)
    assert 0.8 < s < 1.25
    w = fr.robust_weights(r, "cauchy")
    # Cauchy: w = 1 / (1 + (r / (2.385 s))^2): at r = 50, s <= 1.25: (50/2.98)^2 = 281 ->
    # w <= 1/282 = 0.0035; an inlier |r| <= 2 at s >= 0.8: (2/1.91)^2 = 1.10 -> w >= 0.48
    assert w[17] < 0.004
    assert np.all(w[np.abs(r) <= 2] > 0.47)
    # Huber: w = k s / |r| = 1.345 s / 50 <= 0.034 beyond k s; 1 inside
    wh = fr.robust_weights(r, "huber")
    assert wh[17] < 0.035
    assert np.all(wh[np.abs(r) <= 1.345 * 0.8] == 1.0)
    # per-channel scales: a channel 100x brighter gets its own MAD (same weights)
    w2 = fr.robust_weights(np.stack([r, 100 * r], 1).reshape(-1), "cauchy", channels=2)
    np.testing.assert_allclose(w2.reshape(-1, 2), np.stack([w, w], 1), rtol=1e-12)


def test_pixel_l2_drifts_by_the_predicted_amount_region_average_recovers_truth():
    model = toy_model(N_FIREFLY)
    th0 = np.log([0.1])
    # per-pixel L2: argmin_s sum (n s - 1)^2 = sum n / sum n^2 = 100 / 200 = 0.5, i.e.
    # sigma = sigma* + ln 2 / l = 0.3 + 0.34657 (the 1 / (1 + var n) law: var n = 1)
    pix = fr.lm_fit(model, pixel_loss(), th0, rtol=1e-10, max_steps=100)
    drift = np.log(2.0) / L
    assert np.exp(pix["theta"][0]) == pytest.approx(SIGMA_TRUE + drift, abs=1e-6)
    # the same from the noise at the truth alone: ls_scale and the exponential surrogate
    R = model(np.log([SIGMA_TRUE]))[0].reshape(-1, 1)
    assert fr.ls_scale(R, target().reshape(-1, 1)) == pytest.approx(0.5, rel=1e-12)
    pred = fr.predict_exp(pixel_loss().A, R, np.full_like(R, L), pixel_loss().b, 0.01,
                          np.array([SIGMA_TRUE]))
    assert pred[0] == pytest.approx(SIGMA_TRUE + drift, abs=1e-6)
    # one region average: mean(n) s = 1 with mean(n) = 1 -> s = 1: the truth exactly
    reg = fr.lm_fit(model, region_loss(), th0, rtol=1e-10, max_steps=100)
    assert np.exp(reg["theta"][0]) == pytest.approx(SIGMA_TRUE, abs=1e-6)


def test_cauchy_irls_removes_rare_fireflies_but_a_skewed_bulk_biases_it():
    # 95 bulk pixels n = 0.9 +- 0.02 (alternating, sum of deviations 0.02 * (48 - 47)
    # = 0.02) and 5 fireflies n = 2.9: sum n = 85.5 + 0.02 + 14.5 = 100.02 (mean ~1)
    n = np.empty(100)
    n[:95] = 0.9 + 0.02 * np.where(np.arange(95) % 2 == 0, 1.0, -1.0)
    n[95:] = 2.9
    model = toy_model(n)
    th0 = np.log([0.1])
    # per-pixel L2: s = sum n / sum n^2 = 100.02 / (95 * 0.8104 + 5 * 8.41) = 0.8422
    bulk = n[:95]
    s_l2 = n.sum() / np.sum(n ** 2)
    pix = fr.lm_fit(model, pixel_loss(), th0, rtol=1e-10, max_steps=100)
    assert np.exp(pix["theta"][0]) == pytest.approx(SIGMA_TRUE - np.log(s_l2) / L, abs=1e-6)
    assert s_l2 < 0.85  # darkened by ~16%: sigma up by ~0.09 / m
    # Cauchy IRLS: residuals 0.92 s - 1 (48 px), 0.88 s - 1 (47), 2.9 s - 1 (5); median
    # 0.92 s - 1, absolute deviations 0 (48), 0.04 s (47), ...: MAD scale 1.4826 * 0.04 s
    # ~ 0.065 at s ~ 1.1; a firefly's residual 2.9 s - 1 ~ 2.2 gets the weight
    # 1 / (1 + (2.2 / (2.385 * 0.065))^2) ~ 0.005, the bulk (|r| < 0.04) ~ 0.99: the
    # fireflies drop out and s -> sum_bulk n / sum_bulk n^2 = 85.52 / 76.99 = 1.111 > 1:
    # the fit now *brightens* the model (sigma below the truth), because the bulk of a
    # skewed unbiased estimator lies below its mean
    s_bulk = bulk.sum() / np.sum(bulk ** 2)
    rob = fr.irls_fit(model, pixel_loss(), th0, kind="cauchy", outer=30, tol=1e-9,
                      rtol=1e-10, max_steps=100)
    sig = np.exp(rob["theta"][0])
    # (the fireflies' leftover weight ~0.005 pulls s to ~1.109: sigma ~0.001 higher)
    assert sig == pytest.approx(SIGMA_TRUE - np.log(s_bulk) / L, abs=2e-3)
    assert sig < SIGMA_TRUE - 0.04
    assert np.all(rob["weights"][95:] < 0.01) and np.all(rob["weights"][:95] > 0.5)
    # the host-side prediction agrees with the fit
    s_pred, _ = fr.irls_scale(model(np.log([SIGMA_TRUE]))[0].reshape(-1, 1),
                              target().reshape(-1, 1), 0.01)
    assert sig == pytest.approx(SIGMA_TRUE - np.log(s_pred[0]) / L, abs=1e-4)


def test_decorrelated_jacobian_removes_the_bias():
    # two independent halves of the pass budget: n_A = 2 on even pixels, n_B = 2 on
    # pixels p % 4 in {0, 1} (0 elsewhere): sum n_A = sum n_B = 100 and n_A n_B = 4 on
    # p % 4 == 0 only: sum n_A n_B = 25 * 4 = 100. Estimating equation
    # sum n_B (n_A s - 1) + n_A (n_B s - 1) = 0 -> s = 200 / (2 * 100) = 1: the truth;
    # per-pixel L2 on A alone: s = sum n_A / sum n_A^2 = 100 / 200 = 0.5 (sigma + ln 2 / l)
    p = np.arange(100)
    nA = np.where(p % 2 == 0, 2.0, 0.0)
    nB = np.where(p % 4 < 2, 2.0, 0.0)
    th0 = np.log([0.1])
    dec = fr.decorrelated_fit(toy_model(nA), toy_model(nB), pixel_loss(), th0, rtol=1e-10)
    assert np.exp(dec["theta"][0]) == pytest.approx(SIGMA_TRUE, abs=1e-6)
    pix = fr.lm_fit(toy_model(nA), pixel_loss(), th0, rtol=1e-10, max_steps=100)
    assert np.exp(pix["theta"][0]) == pytest.approx(SIGMA_TRUE + np.log(2.0) / L, abs=1e-6)
