"""Explicit-sum MIS weights (`jaxvcm._mis.mis_weight`, the function the renderer calls).

Property tests over random full paths: the weights of every technique that can produce a
path sum to one (1e-5 in float32, 1e-10 in float64), impossible techniques get exactly 0,
and each weight equals an independent high-precision oracle that enumerates the
techniques from their definition (products of pdfs, no log-space trick).
"""

from __future__ import annotations

import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxvcm._mis import mis_weight

LMAX = 9  # max_depth 8 -> at most 9 vertices


def oracle(a, b, delta, k, delta_light, infinite_light, n_lt, algorithm, beta):
    """Weights of all techniques by direct enumeration with exact rational arithmetic."""
    def p(j):
        out = Fraction(1)
        for i in range(k + 1):
            out *= Fraction(a[i]) if i < j else Fraction(b[i])
        return out

    def valid(j):
        if algorithm == "pt" and not (j == 0 or (j == 1 and k >= 2)):
            return False
        if algorithm == "lt" and j != k:
            return False
        if j == 0:
            ok = not delta_light
        elif j == k + 1:
            ok = False
        else:
            left = False if j == 1 else delta[j - 1]
            right = False if j == k else delta[j]
            ok = not left and not right
            if j == 1 and k == 1 and infinite_light:
                ok = False
        return ok and p(j) > 0

    def n(j):
        return Fraction(n_lt) if j == k else Fraction(1)

    terms = [(n(j) * p(j)) ** beta if valid(j) else Fraction(0) for j in range(k + 2)]
    total = sum(terms)
    return [float(tj / total) if total > 0 else 0.0 for tj in terms]


@jax.jit
def _all_weights(A, B, Dl, k, dl, inf, log_n, beta):
    return {alg: jax.vmap(lambda s: mis_weight(A, B, Dl, k, s, dl, inf, log_n, alg, beta))(
        jnp.arange(LMAX + 1)) for alg in ("bdpt", "pt", "lt")}


def weights(a, b, delta, k, delta_light, infinite_light, n_lt, algorithm, beta, dtype):
    """Weights of techniques 0..k+1 from the renderer's `mis_weight` (k, s traced)."""
    pad = LMAX - len(a)
    A = jnp.asarray(list(a) + [1.0] * pad, dtype)
    B = jnp.asarray(list(b) + [1.0] * pad, dtype)
    Dl = jnp.asarray(list(delta) + [False] * pad)
    out = _all_weights(A, B, Dl, jnp.int32(k), jnp.asarray(delta_light), jnp.asarray(infinite_light),
                       jnp.log(jnp.asarray(n_lt, dtype)), jnp.asarray(beta, dtype))
    return np.asarray(out[algorithm], np.float64)[: k + 2]


@st.composite
def paths(draw, lo=-12.0, hi=12.0):
    k = draw(st.integers(1, LMAX - 1))
    logs = st.floats(lo, hi, allow_nan=False)
    a = [10.0 ** draw(logs) for _ in range(k + 1)]
    b = [10.0 ** draw(logs) for _ in range(k + 1)]
    b[k] = 1.0  # the pinhole camera vertex
    # interior vertices may be delta (mirror / dielectric); the two ends are not
    delta = [False] + [draw(st.booleans()) for _ in range(k - 1)] + [False]
    # a zero pdf now and then (e.g. the back of a one-sided light)
    if draw(st.integers(0, 9)) == 0:
        i = draw(st.integers(0, k))
        (a if draw(st.booleans()) else b)[i] = 0.0
    delta_light = draw(st.booleans())
    infinite_light = delta_light or draw(st.booleans())
    n_lt = draw(st.sampled_from([1, 64, 65536]))
    return a, b, delta, k, delta_light, infinite_light, n_lt


@pytest.mark.parametrize("dtype,tol", [("float32", 1e-5), ("float64", 1e-10)])
@pytest.mark.parametrize("algorithm", ["bdpt", "pt", "lt"])
@pytest.mark.parametrize("beta", [1, 2], ids=["balance", "power"])
@settings(max_examples=60, deadline=None)
@given(path=paths())
def test_weights_sum_to_one_and_match_oracle(path, dtype, tol, algorithm, beta):
    a, b, delta, k, dl, inf, n_lt = path
    w = weights(a, b, delta, k, dl, inf, n_lt, algorithm, float(beta), getattr(jnp, dtype))
    ref = oracle(a, b, delta, k, dl, inf, n_lt, algorithm, beta)
    assert np.all(np.isfinite(w))
    assert np.all(w >= 0)
    # impossible techniques: exactly zero
    for j, r in enumerate(ref):
        if r == 0.0:
            assert w[j] == 0.0, (j, w, ref)
    if sum(ref) > 0:
        assert abs(w.sum() - 1.0) <= tol, (w, w.sum())
    np.testing.assert_allclose(w, ref, rtol=50 * tol, atol=tol)


@settings(max_examples=40, deadline=None)
@given(path=paths(lo=-35.0, hi=35.0))
def test_float32_stable_for_extreme_pdfs(path):
    # pdfs over 70 orders of magnitude: products of 9 such overflow float32 (~3e38) and
    # underflow it many times over; log-space keeps every weight finite and normalised.
    a, b, delta, k, dl, inf, n_lt = path
    a = [min(x, 1e37) for x in a]
    b = [min(x, 1e37) for x in b]
    w = weights(a, b, delta, k, dl, inf, n_lt, "bdpt", 2.0, jnp.float32)
    ref = oracle(a, b, delta, k, dl, inf, n_lt, "bdpt", 2)
    assert np.all(np.isfinite(w))
    if sum(ref) > 0:
        assert abs(w.sum() - 1.0) <= 1e-5
    np.testing.assert_allclose(w, ref, rtol=1e-3, atol=1e-5)


def test_delta_vertices_never_count_and_never_zero_the_rest():
    # x_0 light, x_1 diffuse, x_2 mirror, x_3 diffuse, x_4 camera (k = 4). Techniques that
    # join at the mirror (j = 2, 3) and the impossible j = 5 get 0; j = 0, 1, 4 share 1.
    k = 4
    a = [0.5, 0.2, 1.0, 1.0, 1.0]
    b = [0.3, 1.0, 0.4, 0.7, 1.0]  # b_1 = 1: the delta-remapped pdf after the mirror
    delta = [False, False, True, False, False]
    w = weights(a, b, delta, k, False, False, 1, "bdpt", 1.0, jnp.float64)
    assert w[2] == 0 and w[3] == 0 and w[5] == 0
    # balance heuristic by hand: p_0 = b0 b1 b2 b3 b4 = 0.084, p_1 = a0 b1.. = 0.14,
    # p_4 = a0 a1 a2 a3 b4 = 0.1 -> weights 0.084/0.324, 0.14/0.324, 0.1/0.324
    np.testing.assert_allclose(w[[0, 1, 4]], np.array([0.084, 0.14, 0.1]) / 0.324, rtol=1e-12)


def test_sun_paths_are_not_hit_by_camera_rays():
    # delta light: j = 0 is impossible, NEE (j = 1) takes its share
    a, b = [1.0, 0.5, 0.5], [0.7, 0.2, 1.0]
    w = weights(a, b, [False, False, False], 2, True, True, 1, "bdpt", 1.0, jnp.float64)
    assert w[0] == 0.0
    assert abs(w.sum() - 1) < 1e-12
