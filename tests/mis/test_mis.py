"""Explicit-sum MIS weights (`jaxvcm._mis.mis_weight`, the function the renderer calls).

Property tests over random full paths: the weights of every technique that can produce a
path sum to one (1e-5 in float32, 1e-10 in float64), impossible techniques get exactly 0,
and each weight equals an independent high-precision oracle that enumerates the
techniques from their definition (products of pdfs, no log-space trick).
"""

from __future__ import annotations

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


# ---------------------------------------------------------------- the renderer's assembly
from jaxvcm import RenderConfig  # noqa: E402
from .._mis_oracle import Pdfs, weight  # noqa: E402


@st.composite
def full_paths(draw):
    k = draw(st.integers(1, LMAX - 1))
    logs = st.floats(-6.0, 6.0, allow_nan=False)
    A = [10.0 ** draw(logs) for _ in range(k + 1)]
    B = [10.0 ** draw(logs) for _ in range(k + 1)]
    B[k] = 1.0
    q = [draw(st.floats(0.05, 1.0)) for _ in range(k + 1)]
    delta = [False] + [draw(st.booleans()) for _ in range(k - 1)] + [False]
    return k, A, B, q, delta, draw(st.booleans()), draw(st.booleans())


@pytest.mark.parametrize("mis", ["balance", "power"])
@settings(max_examples=40, deadline=None)
@given(path=full_paths(), garbage=st.floats(1e-3, 1e3))
def test_renderer_assembly_from_subpaths_sums_to_one(path, garbage, mis):
    # For each technique s the renderer sees two subpaths, each with stored pdfs that are
    # only right away from the join (the last two vertices of each side are re-evaluated
    # at the join, `_path.path_pdfs`). Fill those stored slots with garbage, pass the
    # true values as the join overrides, and the weights over all s must sum to one and
    # equal the oracle built from the true full-path pdfs with each direction's roulette.
    k, A, B, q, delta, dl, inf = path
    cfg = RenderConfig(algorithm="bdpt", max_depth=LMAX - 1, rr_depth=2, mis=mis)
    beta = 2 if mis == "power" else 1
    f64 = jnp.float64

    def rr(index, qq):
        return 1.0 if index < cfg.rr_depth else qq

    a_true = [A[i] * (rr(i - 1, q[i - 1]) if i >= 1 else 1.0) for i in range(k + 1)]
    b_true = [B[i] * (rr(k - i - 1, q[i + 1]) if i < k else 1.0) for i in range(k + 1)]
    ref = oracle(a_true, b_true, delta, k, dl, inf, 1, "bdpt", beta)
    ws = []
    for s in range(0, k + 2):
        t = k + 1 - s
        # light subpath y_0..y_{s-1} = x_0..x_{s-1}: A right, B right except the last two
        lA = [A[i] for i in range(s)] or [1.0]
        lB = [B[i] if i < s - 2 else garbage for i in range(s)] or [1.0]
        lq = [q[i] for i in range(s)] or [1.0]
        ld = [delta[i] for i in range(s)] or [False]
        # camera subpath z_0..z_{t-1} = x_k..x_s: B right, A right except the last two
        cA = [A[k - j] if j < t - 2 else garbage for j in range(t)] or [1.0]
        cB = [B[k - j] for j in range(t)] or [1.0]
        cq = [q[k - j] for j in range(t)] or [1.0]
        cd = [delta[k - j] for j in range(t)] or [False]
        lig = Pdfs(jnp.asarray(lA, f64), jnp.asarray(lB, f64), jnp.asarray(lq, f64), jnp.asarray(ld),
                   jnp.zeros(len(ld), bool))
        cam = Pdfs(jnp.asarray(cA, f64), jnp.asarray(cB, f64), jnp.asarray(cq, f64), jnp.asarray(cd),
                   jnp.zeros(len(cd), bool))
        ov = lambda i, arr: jnp.asarray(arr[i] if 0 <= i <= k else 1.0, f64)  # noqa: E731
        w = weight(cfg, jnp.int32(s), jnp.int32(t), lig, cam, ov(s, A), ov(s + 1, A),
                   ov(s - 1, B), ov(s - 2, B), jnp.asarray(dl), jnp.asarray(inf),
                   jnp.log(jnp.asarray(1.0, f64)))
        ws.append(float(w) if t >= 1 else 0.0)
    ws = np.array(ws)
    np.testing.assert_allclose(ws, ref, rtol=1e-9, atol=1e-12)
    if sum(ref) > 0:
        assert abs(ws.sum() - 1.0) < 1e-10


# ---------------------------------------------------------------- merging (VM) techniques
def oracle_vcm(a, b, delta, k, delta_light, infinite_light, n_lt, eta, algorithm, beta):
    """(VC weights j = 0..k+1, VM weights i = 0..k) by exact enumeration:
    n_VM p_VM,i = eta_i a_i p_VC,i (eta_i = kernel area/volume times N), merging at
    1 <= i <= k-1 on non-delta vertices (ppm: the first non-delta vertex from the camera)."""
    base = oracle_terms(a, b, delta, k, delta_light, infinite_light, n_lt, algorithm)

    def p(j):
        out = Fraction(1)
        for i in range(k + 1):
            out *= Fraction(a[i]) if i < j else Fraction(b[i])
        return out

    nd = [i for i in range(1, k) if not delta[i]]
    vm = []
    for i in range(k + 1):
        ok = 1 <= i <= k - 1 and not delta[i] and a[i] > 0 and p(i) > 0
        if algorithm == "ppm":
            ok = ok and all(delta[m] for m in range(i + 1, k))
        vm.append(Fraction(eta[i]) * Fraction(a[i]) * p(i) if ok else Fraction(0))
    if algorithm == "ppm" and nd:
        base = [Fraction(0)] * len(base)
    tv = [x ** beta for x in base]
    tm = [x ** beta for x in vm]
    total = sum(tv) + sum(tm)
    f = (lambda x: float(x / total)) if total > 0 else (lambda x: 0.0)
    return [f(x) for x in tv], [f(x) for x in tm]


def oracle_terms(a, b, delta, k, delta_light, infinite_light, n_lt, algorithm):
    """n_j p_j of the valid connection techniques (0 for invalid), j = 0..k+1."""
    def p(j):
        out = Fraction(1)
        for i in range(k + 1):
            out *= Fraction(a[i]) if i < j else Fraction(b[i])
        return out

    out = []
    for j in range(k + 2):
        if algorithm in ("ppm", "bpm"):
            ok = j == 0 and not delta_light
        else:
            if j == 0:
                ok = not delta_light
            elif j == k + 1:
                ok = False
            else:
                ok = not (j > 1 and delta[j - 1]) and not (j < k and delta[j])
                ok = ok and not (j == 1 and k == 1 and infinite_light)
        ok = ok and p(j) > 0
        out.append((Fraction(n_lt) if j == k else Fraction(1)) * p(j) if ok else Fraction(0))
    return out


@jax.jit
def _vcm_weights(A, B, Dl, k, dl, inf, log_n, beta, log_eta):
    out = {}
    for alg in ("ppm", "bpm", "vcm"):
        f = lambda s, m: mis_weight(A, B, Dl, k, s, dl, inf, log_n, alg, beta, log_eta, m)  # noqa: E731
        js = jnp.arange(LMAX + 1)
        out[alg] = (jax.vmap(lambda s: f(s, False))(js), jax.vmap(lambda s: f(s, True))(js[:LMAX]))
    return out


@pytest.mark.parametrize("dtype,tol", [("float32", 1e-5), ("float64", 1e-10)])
@pytest.mark.parametrize("algorithm", ["vcm", "bpm", "ppm"])
@pytest.mark.parametrize("beta", [1, 2], ids=["balance", "power"])
@settings(max_examples=40, deadline=None)
@given(path=paths(-8.0, 8.0), log_eta=st.floats(-12.0, 12.0))
def test_vcm_weights_sum_to_one_and_match_oracle(path, log_eta, dtype, tol, algorithm, beta):
    # tiny and huge merging radii: eta = pi r^2 N from 1e-12 to 1e12
    a, b, delta, k, dl, inf, n_lt = path
    dt = getattr(jnp, dtype)
    eta = [10.0 ** log_eta * (1.7 if i % 2 else 1.0) for i in range(k + 1)]  # surface / medium
    pad = LMAX - len(a)
    A = jnp.asarray(list(a) + [1.0] * pad, dt)
    B = jnp.asarray(list(b) + [1.0] * pad, dt)
    Dl = jnp.asarray(list(delta) + [False] * pad)
    le = jnp.log(jnp.asarray(eta + [1.0] * pad, dt))
    vc, vm = _vcm_weights(A, B, Dl, jnp.int32(k), jnp.asarray(dl), jnp.asarray(inf),
                          jnp.log(jnp.asarray(n_lt, dt)), jnp.asarray(beta, dt), le)[algorithm]
    vc = np.asarray(vc, np.float64)[: k + 2]
    vm = np.asarray(vm, np.float64)[: k + 1]
    rvc, rvm = oracle_vcm(a, b, delta, k, dl, inf, n_lt, eta, algorithm, beta)
    assert np.all(np.isfinite(vc)) and np.all(np.isfinite(vm))
    for got, ref in ((vc, rvc), (vm, rvm)):
        for g, r in zip(got, ref):
            if r == 0.0:
                assert g == 0.0
        np.testing.assert_allclose(got, ref, rtol=50 * tol, atol=tol)
    if sum(rvc) + sum(rvm) > 0:
        assert abs(vc.sum() + vm.sum() - 1.0) <= tol


# ---------------------------------------------------------------- geometric random paths
def _geometric_path(rng, k, scene):
    """A random full path x_0..x_k in the pool: x_0 on the area light, interior vertices on
    the floor/walls (diffuse), in the water (medium) or on the water surface (delta),
    x_k the camera. Returns per-vertex (A, B, q, delta, medium) computed with the
    renderer's own pdf helpers (`_subpath.to_area`, `bsdf_pdf`, `_lights` emission and
    light-point pdfs, the pinhole pdf), RR-free, plus light flags."""
    from jaxvcm import _geometry as G
    from jaxvcm import _lights as Lt
    from jaxvcm import _subpath as SP
    from jaxvcm._camera import camera_importance
    from jaxvcm._vec import Vec3

    f64 = jnp.float64
    v3 = lambda a: Vec3(*(jnp.asarray(x, f64) for x in a))  # noqa: E731
    w = scene.water
    verts = []  # (p, n, kind, mat, medium, delta)
    r = scene.rects
    li = scene.lights.shape[0]
    p0, e1, e2 = (np.asarray(x[li], float) for x in (r.p0, r.e1, r.e2))
    nl = np.cross(e1, e2)
    nl /= np.linalg.norm(nl)
    verts.append((p0 + rng.uniform() * e1 + rng.uniform() * e2, nl, 0, int(r.mat[li]), False, False))
    for _ in range(k - 1):
        c = rng.integers(3)
        x, z = rng.uniform(-0.95, 0.95, 2)
        if c == 0:  # floor
            verts.append((np.array([x, -1.2, z]), np.array([0.0, 1.0, 0.0]), 0, 0, False, False))
        elif c == 1:  # water volume
            verts.append((np.array([x, rng.uniform(-1.15, -0.05), z]), np.array([0.0, 1.0, 0.0]),
                          3, 0, True, False))
        else:  # water surface (delta)
            h, _, _ = G.water_height(w, jnp.asarray(x, f64), jnp.asarray(z, f64))
            n = G.water_normal(w, jnp.asarray(x, f64), jnp.asarray(z, f64))
            verts.append((np.array([x, float(h), z]), np.array([float(n.x), float(n.y), float(n.z)]),
                          1, w.mat, False, True))
    cam = np.asarray(scene.camera.origin, float)
    verts.append((cam, np.asarray(scene.camera.forward, float), -1, 0, False, False))
    P = [v[0] for v in verts]

    def unit(a, b):
        d = P[b] - P[a]
        return d / np.linalg.norm(d), float(np.linalg.norm(d))

    def seg_water(a, b):
        mid = 0.5 * (P[a] + P[b])
        return bool(G.inside_water(w, v3(mid)))

    def pdf_w_at(i, frm, to):  # solid-angle pdf at vertex i of sampling towards `to`, from `frm`
        p_, n_, kind, mat, med, dl = verts[i]
        if dl:
            return 1.0
        wo, _ = unit(i, frm)
        wi, _ = unit(i, to)
        return float(SP.bsdf_pdf(scene, jnp.int32(kind), jnp.int32(mat), None, v3(wo), v3(wi), v3(n_)))

    def area(pdf_w, i_src, i_tgt):
        wv, d = unit(i_src, i_tgt)
        _, n_t, _, _, med, _ = verts[i_tgt]
        return float(SP.to_area(jnp.asarray(pdf_w, f64), jnp.asarray(med), v3(n_t), v3(wv),
                                jnp.asarray(d, f64), jnp.asarray(seg_water(i_src, i_tgt)), w))

    A = [0.0] * (k + 1)
    B = [0.0] * (k + 1)
    A[0] = float(Lt.light_point_pdf(scene, jnp.int32(0), v3([0.0, 1.0, 0.0])))
    wv, _ = unit(0, 1)
    A[1] = area(float(Lt.emission_pdf_dir(scene, jnp.int32(0), v3(nl), v3(wv))), 0, 1) if k >= 2 else 1.0
    for i in range(2, k + 1):
        A[i] = 1.0 if verts[i - 1][5] else area(pdf_w_at(i - 1, i - 2, i), i - 1, i)
    B[k] = 1.0
    wc, _ = unit(k, k - 1)
    _, imp, _ = camera_importance(scene, v3(wc))
    B[k - 1] = area(float(imp), k, k - 1)
    for i in range(k - 2, -1, -1):
        B[i] = 1.0 if verts[i + 1][5] else area(pdf_w_at(i + 1, i + 2, i), i + 1, i)
    q = [float(SP.local_q(jnp.int32(v[2]), scene.materials.albedo[v[3]])) if not v[4] else SP.Q_SPECULAR
         for v in verts]
    delta = [v[5] for v in verts]
    return A, B, q, delta


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, LMAX - 1))
def test_geometric_random_paths_in_the_pool(seed, k):
    # Random vertex positions on surfaces, in the water and on the (delta) water surface of
    # scenes/pool.toml, pdfs from the renderer's helpers, assembled by the renderer's
    # `_path.weight` with garbage in the join slots: weights over all techniques sum to 1
    # (1e-10, float64) and equal the exact oracle.
    import jaxvcm

    scene = jaxvcm.load_scene("scenes/pool.toml", dtype=jnp.float64)
    rng = np.random.default_rng(seed)
    A, B, q, delta = _geometric_path(rng, k, scene)
    assert all(np.isfinite(A)) and all(np.isfinite(B)) and min(A + B) >= 0
    cfg = RenderConfig(algorithm="bdpt", max_depth=LMAX - 1, rr_depth=2, mis="power")

    def rr(index, qq):
        return 1.0 if index < cfg.rr_depth else qq

    a_true = [A[i] * (rr(i - 1, q[i - 1]) if i >= 1 else 1.0) for i in range(k + 1)]
    b_true = [B[i] * (rr(k - i - 1, q[i + 1]) if i < k else 1.0) for i in range(k + 1)]
    ref = oracle(a_true, b_true, delta, k, False, False, 1, "bdpt", 2)
    f64 = jnp.float64
    ws = []
    for s in range(0, k + 1):
        t = k + 1 - s
        mk = lambda vals, n: jnp.asarray(vals if vals else [1.0], f64)  # noqa: E731
        lig = Pdfs(mk([A[i] for i in range(s)], s), mk([B[i] if i < s - 2 else 7.0 for i in range(s)], s),
                   mk([q[i] for i in range(s)], s), jnp.asarray([delta[i] for i in range(s)] or [False]),
                   jnp.zeros(max(s, 1), bool))
        cam = Pdfs(mk([A[k - j] if j < t - 2 else 7.0 for j in range(t)], t), mk([B[k - j] for j in range(t)], t),
                   mk([q[k - j] for j in range(t)], t), jnp.asarray([delta[k - j] for j in range(t)]),
                   jnp.zeros(t, bool))
        ov = lambda i, arr: jnp.asarray(arr[i] if 0 <= i <= k else 1.0, f64)  # noqa: E731
        ws.append(float(weight(cfg, jnp.int32(s), jnp.int32(t), lig, cam, ov(s, A), ov(s + 1, A),
                               ov(s - 1, B), ov(s - 2, B), jnp.asarray(False), jnp.asarray(False),
                               jnp.log(jnp.asarray(1.0, f64)))))
    ws.append(0.0)
    np.testing.assert_allclose(ws, ref, rtol=1e-9, atol=1e-12)
    if sum(ref) > 0:
        assert abs(sum(ws) - 1.0) < 1e-10
