"""The recursive dVCM/dVC/dVM MIS form (`jaxvcm._mis_recursive`, Georgiev 2012 tech report)
against the explicit log-space sums (`jaxvcm._mis.mis_weight`).

Property tests over random full paths (delta vertices, delta and infinite lights, zero
pdfs, 1..LMAX-1 segments, per-vertex merging kernels pi r^2 N / 4/3 pi r^3 N for radii
from tiny to huge): for every connection and merging technique, every algorithm and both
heuristics the two forms agree (1e-5 absolute in float32, 1e-10 in float64), impossible
techniques get exactly 0 in both, and the recursive weights of the possible techniques
sum to one. The recursive form works with products of pdf ratios in linear space, so the
float32 ranges are kept moderate (pdfs 1e-2..1e2, radii 1e-3..10); a separate test shows
a path with equal technique pdfs where it fails in float32 and the log-space form does not.
Finally renders: with `mis_form="recursive"` the renderer carries dVCM / dVC / dVM along
each subpath as it is traced (`_mis_recursive.carry_step`) and never reads the stored pdf
records, so every technique image of a fixed-key pass equals the explicit form's (which
is built from those records) to float32 rounding, with Russian roulette inside the paths;
and a planted mistake in the stored records moves the explicit image, not the recursive.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._mis import mis_weight
from jaxvcm._mis import mis_weight_recursive
from jaxvcm import _subpath
from jaxvcm._integrator import technique_images
from jaxvcm._render import render_pass_host

from .. import _scenes as S
from .test_mis import LMAX, paths

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ALGORITHMS = ("pt", "lt", "bdpt", "ppm", "bpm", "vcm")
MERGING = ("ppm", "bpm", "vcm")
# per dtype: tolerance, pdf log10 range, merging radius log10 range
RANGES = {"float32": (1e-5, (-2.0, 2.0), (-3.0, 1.0)),
          "float64": (1e-10, (-12.0, 12.0), (-6.0, 2.0))}


@functools.partial(jax.jit, static_argnames=("algorithm",))
def _weights(A, B, Dl, k, dl, inf, log_n, beta, log_eta, algorithm):
    """{form: [VC s = 0..LMAX, then VM at s = 0..LMAX-1 for the merging algorithms]}."""
    out = {}
    for name, fn in (("explicit", mis_weight), ("recursive", mis_weight_recursive)):
        def f(s, m, fn=fn):
            return fn(A, B, Dl, k, s, dl, inf, log_n, algorithm, beta, log_eta, m)

        w = [jax.vmap(lambda s: f(s, False))(jnp.arange(LMAX + 1))]
        if algorithm in MERGING:
            w.append(jax.vmap(lambda s: f(s, True))(jnp.arange(LMAX)))
        out[name] = jnp.concatenate(w)
    return out


def weights(a, b, delta, k, dl, inf, n_lt, log_eta, algorithm, beta, dtype):
    pad = LMAX - len(a)
    dt = getattr(jnp, dtype)
    out = _weights(jnp.asarray(list(a) + [1.0] * pad, dt), jnp.asarray(list(b) + [1.0] * pad, dt),
                   jnp.asarray(list(delta) + [False] * pad), jnp.int32(k), jnp.asarray(dl),
                   jnp.asarray(inf), jnp.log(jnp.asarray(n_lt, dt)), jnp.asarray(beta, dt),
                   jnp.asarray(list(log_eta) + [0.0] * pad, dt), algorithm)
    return (np.asarray(out["explicit"], np.float64), np.asarray(out["recursive"], np.float64))


def possible(a, b, delta, k, dl, inf, algorithm):
    """Which techniques can make the path (pdfs > 0, joins at non-delta vertices, the
    algorithm's technique set), in the layout of `weights`: a third statement of the rules,
    from the `_mis.mis_weight` docstring."""
    def positive(j):  # p_j > 0
        return all(a[i] > 0 for i in range(j)) and all(b[i] > 0 for i in range(j, k + 1))

    nd = [i for i in range(1, k) if not delta[i]]  # non-delta interior vertices
    vc = []
    for j in range(LMAX + 1):
        if j == 0:
            ok = not dl
        elif j >= k + 1:
            ok = False
        else:
            ok = not (j >= 2 and delta[j - 1]) and not (j <= k - 1 and delta[j])
            ok = ok and not (j == 1 and k == 1 and inf)
        ok = ok and {"pt": j == 0 or (j == 1 and k >= 2), "lt": j == k,
                     "ppm": j == 0 and not nd, "bpm": j == 0}.get(algorithm, True)
        vc.append(ok and positive(j))
    if algorithm not in MERGING:
        return np.array(vc)
    vm = []
    for i in range(LMAX):
        ok = 1 <= i <= k - 1 and not delta[i] and a[i] > 0 and positive(i)
        if algorithm == "ppm":
            ok = ok and i == max(nd)  # the first non-delta vertex seen from the camera
        vm.append(ok)
    return np.array(vc + vm)


@st.composite
def vcm_paths(draw, lo, hi, rho_lo, rho_hi):
    """A `test_mis.paths` path plus per-vertex log(kernel N): surface pi r^2 N or medium
    4/3 pi r^3 N, N the light-path count (= the light-tracing multiplicity)."""
    a, b, delta, k, dl, inf, n_lt = draw(paths(lo, hi))
    r = 10.0 ** draw(st.floats(rho_lo, rho_hi))
    medium = [draw(st.booleans()) for _ in range(k + 1)]
    log_eta = [math.log((4.0 / 3.0 * math.pi * r**3 if m else math.pi * r**2) * n_lt)
               for m in medium]
    return a, b, delta, k, dl, inf, n_lt, log_eta


@pytest.mark.parametrize("dtype", list(RANGES))
@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("beta", [1, 2])
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_recursive_equals_explicit_for_every_technique(data, dtype, algorithm, beta):
    # Expected: the explicit weight of each technique, exp(-logsumexp(beta (c_T - c_s)))
    # (itself checked against exact rational enumeration in test_mis.py); possible
    # techniques sum to 1; impossible ones are exactly 0 in both forms.
    tol, (lo, hi), (rlo, rhi) = RANGES[dtype]
    a, b, delta, k, dl, inf, n_lt, log_eta = data.draw(vcm_paths(lo, hi, rlo, rhi))
    w_exp, w_rec = weights(a, b, delta, k, dl, inf, n_lt, log_eta, algorithm, float(beta), dtype)
    ok = possible(a, b, delta, k, dl, inf, algorithm)
    assert np.all(np.isfinite(w_rec)) and np.all((w_rec >= 0) & (w_rec <= 1 + tol))
    assert np.all(w_rec[~ok] == 0) and np.all(w_exp[~ok] == 0), (w_exp, w_rec, ok)
    np.testing.assert_allclose(w_rec, w_exp, rtol=0, atol=tol)
    if ok.any():
        assert abs(w_rec[ok].sum() - 1.0) <= tol, (w_rec, w_rec[ok].sum())


@pytest.mark.parametrize("beta", [1, 2])
@pytest.mark.parametrize("dtype", list(RANGES))
def test_hand_derived_vcm_path(beta, dtype):
    # x_0 light, x_1 diffuse, x_2 pinhole (k = 2); N = 2 light paths, eta_1 = 0.5:
    #   VC j=0 (emitter hit)  p_0 = b0 b1 b2      = 0.25 * 4 * 1  = 1
    #   VC j=1 (NEE)          p_1 = a0 b1 b2      = 0.5 * 4 * 1   = 2
    #   VC j=2 (light trace)  N p_2 = 2 a0 a1 b2  = 2 * 0.5 * 2   = 2
    #   VM at x_1             eta a1 p_1          = 0.5 * 2 * 2   = 2
    # balance: (1, 2, 2, 2) / 7; power: (1, 4, 4, 4) / 13.
    a, b = [0.5, 2.0, 1.0], [0.25, 4.0, 1.0]
    w_exp, w_rec = weights(a, b, [False] * 3, 2, False, False, 2, [math.log(0.5)] * 3, "vcm",
                           float(beta), dtype)
    terms = np.array([1.0, 2.0, 2.0, 2.0]) ** beta
    ref = terms / terms.sum()
    got = w_rec[[0, 1, 2, LMAX + 2]]  # VM at x_1: index LMAX + 1 + 1
    np.testing.assert_allclose(got, ref, rtol=RANGES[dtype][0])
    np.testing.assert_allclose(w_exp[[0, 1, 2, LMAX + 2]], ref, rtol=RANGES[dtype][0])
    assert np.sum(w_rec) == pytest.approx(1.0, abs=RANGES[dtype][0])


@pytest.mark.parametrize("dtype", list(RANGES))
def test_linear_space_overflows_in_float32_where_log_space_does_not(dtype):
    # x_0 .. x_4 with a_i = b_i = (1, 1e-10, 1e-10, 1, 1): every connection technique has
    # the same pdf p_j = 1e-20, so with n_lt = 1 the five techniques j = 0..4 each get 1/5
    # (bdpt, power heuristic). The recursion, with A = a^2, B = b^2:
    #   light side   dVCM_1 = 1/A_1 = 1e20, dVC_1 = dVCM_0/A_1 = 1e20,
    #                dVC_2 = (dVCM_1 + dVC_1 B_0)/A_2 = 2e20/1e-20 = 2e40,
    #   camera side  dVCM^c_2 = 1/B_2 = 1e20, dVC^c_2 = dVCM^c_3/B_2 = 1e20,
    #                dVC^c_1 = (dVCM^c_2 + dVC^c_2 A_3)/B_1 = 2e40;
    # 2e40 > 3.4e38 overflows float32, so every technique that reads dVC_2 (s = 3, 4: light
    # subpaths through x_2) or dVC^c_1 (s = 0, 1) gets 1 / (inf + ...) = 0; only s = 2 reads
    # neither: w_light = B_1 (dVCM_1 + dVC_1 B_0) = 2, w_camera = A_2 (dVCM^c_2 + dVC^c_2 A_3)
    # = 2, w = 1/(2 + 1 + 2) = 1/5. Measured, float32: recursive (0, 0, 0.2, 0, 0) (finite,
    # summing to 0.2), explicit (log space) 0.2 each; float64: both 0.2 each.
    a = b = [1.0, 1e-10, 1e-10, 1.0, 1.0]
    w_exp, w_rec = weights(a, b, [False] * 5, 4, False, False, 1, [0.0] * 5, "bdpt", 2.0, dtype)
    np.testing.assert_allclose(w_exp[:5], 0.2, rtol=1e-6)
    if dtype == "float64":
        np.testing.assert_allclose(w_rec[:5], 0.2, rtol=1e-12)
    else:
        assert np.all(np.isfinite(w_rec))  # the zero-product guards keep it finite ...
        np.testing.assert_allclose(w_rec[:5], [0.0, 0.0, 0.2, 0.0, 0.0], rtol=1e-6, atol=0)
        assert w_rec.sum() == pytest.approx(0.2, rel=1e-6)  # ... but not normalised


# ---------------------------------------------------------------- the renderer's switch
def test_config_validates_mis_form():
    assert RenderConfig().mis_form == "explicit"
    with pytest.raises(ValueError, match="config.mis_form"):
        RenderConfig(mis_form="iterative")


@pytest.mark.parametrize("alg", ["vcm"])  # vcm holds every bdpt technique too
def test_recursive_render_equals_explicit(alg):
    # Box of emitting walls filled with a scattering medium (tests/_scenes.py): every
    # pixel sees emitter hits, NEE, light tracing, connections and (vcm, sphere kernels at
    # medium vertices) merging. Same scene, key and pass: every contribution is identical
    # except for its MIS weight, which the two forms compute to float32 rounding, so the
    # images agree to ~1e-6 relative (measured 1.5e-7 for both algorithms). At radius 0.1
    # (of the view radius, 4.7 cm) merging takes part in the vcm image, so the merging
    # weights are compared too.
    sc = jaxvcm.scene_from_dict(S.medium_furnace(np.array([1.0, 2.0, 0.5]), (0.3, 0.6, 1.2),
                                                 w=8, h=8))
    cfg = RenderConfig(algorithm=alg, max_depth=3, radius=0.1)
    key = jax.random.key(7)
    img_e, diag_e, _ = render_pass_host(sc, key, cfg, 0)
    img_r, diag_r, _ = render_pass_host(sc, key, dataclasses.replace(cfg, mis_form="recursive"), 0)
    img_e, img_r = np.asarray(img_e, np.float64), np.asarray(img_r, np.float64)
    assert int(diag_e.nonfinite) == 0 and int(diag_r.nonfinite) == 0
    assert np.all(img_e > 0)  # the comparison has teeth: every pixel has contributions
    np.testing.assert_allclose(img_r, img_e, rtol=1e-5, atol=0)


# ---------------------------------------------------------------- carried along the subpaths
_technique_images = jax.jit(technique_images, static_argnums=2)


def _carried_scene(name):
    if name == "medium_furnace":
        return jaxvcm.scene_from_dict(S.medium_furnace(np.array([1.0, 2.0, 0.5]),
                                                       (0.3, 0.6, 1.2), w=8, h=8))
    return jaxvcm.load_scene(os.path.join(ROOT, "scenes", f"{name}.toml"), width=16, height=16)


def _carried_config(alg, spp=1, radius=0.1, **kw):
    # rr_depth 2 < max_depth 5: roulette starts inside the paths, so the recursion's
    # roulette variants (the reverse factors near the join without q) are all read
    return RenderConfig(algorithm=alg, max_depth=5, rr_depth=2, radius=radius, spp=spp, **kw)


# medium_furnace: a scattering medium inside emitting walls (medium and surface vertices,
# volume and area merging kernels, every technique at every pixel); pool_sun: the delta,
# infinite sun through the delta water surface (delta vertices, solid-angle pdfs at
# infinity); pt on pool_sky (the sky, an infinite non-delta light): its own technique masks,
# NEE against emitter hits
@pytest.mark.parametrize("alg,name", [("vcm", "medium_furnace"), ("vcm", "pool_sun"),
                                      ("pt", "pool_sky")], ids=lambda v: v)
def test_carried_recursive_technique_images_equal_explicit(alg, name):
    # Same key, same samples: every contribution is the same in both forms except its MIS
    # weight, so each technique image agrees to float32 rounding (measured <= 2e-7 of the
    # image's largest value; a wrong roulette variant of the merges gave 1.2e-2, bpm on the
    # furnace). Tolerance 1e-5 of the largest technique value.
    sc = _carried_scene(name)
    if name == "medium_furnace":  # a 9.6 cm first radius (twice the view radius's 0.1)
        cfg = _carried_config(alg, spp=1, radius=S.radius_fraction(sc, 0.096))
    else:
        cfg = _carried_config(alg, spp=4)
    key = jax.random.key(3)
    te, se = _technique_images(sc, key, cfg)
    tr, sr = _technique_images(sc, key, dataclasses.replace(cfg, mis_form="recursive"))
    assert te.labels == tr.labels
    ie = np.asarray(te.images, np.float64)
    ir = np.asarray(tr.images, np.float64)
    assert np.all(np.isfinite(ie)) and np.all(np.isfinite(ir))
    scale = float(np.max(np.abs(ie)))
    # teeth: most techniques contribute somewhere (vcm: connections and merges too)
    live = [lab for lab, img in zip(te.labels, ie) if np.any(img != 0)]
    assert len(live) >= (12 if alg == "vcm" else 6), live
    if alg == "vcm":
        assert any(lab.kind == "merge" for lab in live)
        assert any(lab.kind == "connection" and lab.s >= 2 and lab.t >= 2 for lab in live)
    for lab, a, b in zip(te.labels, ie, ir):
        err = float(np.max(np.abs(b - a)))
        assert err <= 1e-5 * scale, f"{lab}: max |recursive - explicit| {err:.3g} of {scale:.3g}"


def test_carried_recursive_checks_the_stored_pdfs(monkeypatch):
    # A planted mistake in the stored records: the camera-side pdf of camera vertex z_2
    # (its `pdf_fwd` record, B in the explicit sums) scaled by 1.5 after the trace. In pt
    # the emitter hit at z_2 reads it (its weight is 1 / (1 + (a_0 / b_0)^2 ...), b_0 = B of
    # z_2); every other pdf pt needs is re-evaluated at the join. The explicit form builds
    # its weights from the records, the recursive one carried its own while tracing: the
    # explicit image moves (measured 8.6e-2 of the image's largest value), the recursive
    # one does not.
    sc = _carried_scene("pool_sky")
    cfg = _carried_config("pt", spp=4)
    key = jax.random.key(3)
    good, _ = _technique_images(sc, key, cfg)
    ends = _subpath.ends

    def planted(verts, light, table=None):
        e = ends(verts, light, table)
        return e if light else e._replace(B=e.B.at[2].multiply(1.5), table=None)

    monkeypatch.setattr(_subpath, "ends", planted)
    # trace_split changes the work, not the result (a fresh trace that sees the mistake)
    bad_e, _ = _technique_images(sc, key, cfg.tuned(trace_split=3))
    bad_r, _ = _technique_images(sc, key, dataclasses.replace(cfg.tuned(trace_split=3),
                                                             mis_form="recursive"))
    g = np.asarray(good.images, np.float64).sum(axis=0)
    e = np.asarray(bad_e.images, np.float64).sum(axis=0)
    r = np.asarray(bad_r.images, np.float64).sum(axis=0)
    scale = float(np.max(np.abs(g)))
    assert float(np.max(np.abs(r - g))) <= 1e-5 * scale
    assert float(np.max(np.abs(e - g))) > 1e-3 * scale
