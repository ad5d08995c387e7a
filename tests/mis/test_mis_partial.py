"""The renderer's O(1)-per-technique explicit MIS (`jaxvcm._mis_partial`: per-subpath
partial sums, the join adds its four re-evaluated pdfs) against the full-path assembly
(`jaxvcm._path.weight`, itself checked against exact rational oracles in test_mis.py).

Random full paths are cut into a light and a camera subpath for every technique (s, t)
and every merge, with the slots the join re-evaluates filled with garbage and the
subpaths padded with garbage to the renderer's fixed lengths; the weights must agree to
float32 round-off (float64: 1e-9) for every algorithm, both heuristics, and Russian
roulette starting anywhere from the first vertex to beyond the path (the roulette of
each direction counts from its own end, the part that makes the split non-trivial).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxvcm import RenderConfig
from jaxvcm._mis import _explicit as MP

from .._mis_oracle import Pdfs, weight

D = 7  # max depth: light subpaths of D vertices, camera subpaths of D + 1


@st.composite
def cut_paths(draw):
    k = draw(st.integers(1, D))
    logs = st.floats(-5.0, 5.0, allow_nan=False)
    A = [10.0 ** draw(logs) for _ in range(k + 1)]
    B = [10.0 ** draw(logs) for _ in range(k + 1)]
    B[k] = 1.0
    # a zero pdf now and then (the back of a one-sided light): impossible techniques
    if draw(st.booleans()):
        i = draw(st.integers(0, k))
        (A if draw(st.booleans()) else B)[i] = 0.0
    q = [draw(st.floats(0.05, 1.0)) for _ in range(k + 1)]
    delta = [False] + [draw(st.booleans()) for _ in range(k - 1)] + [False]
    medium = [draw(st.booleans()) for _ in range(k + 1)]
    return (k, A, B, q, delta, medium, draw(st.booleans()), draw(st.booleans()),
            draw(st.floats(1e-3, 1e3)), draw(st.floats(-6.0, 6.0)), draw(st.floats(-6.0, 6.0)))


def _cut(path, s, t, ML, MC):
    """The two subpaths of technique (s, t) as the renderer stores them (garbage in the
    join slots and the padding) and the four join pdfs."""
    k, A, B, q, delta, medium, _, _, g, _, _ = path

    def side(idx, good, fill):
        return [fill(i) if good(n, i) else g for n, i in enumerate(idx)]

    lidx = list(range(ML))
    cidx = [k - n for n in range(MC)]
    lok = lambda n, i: n < s  # noqa: E731
    cok = lambda n, i: n < t  # noqa: E731
    lA = side(lidx, lok, lambda i: A[i])
    lB = side(lidx, lambda n, i: n < s - 2, lambda i: B[i])
    lq = side(lidx, lok, lambda i: q[i])
    ld = [delta[i] if n < s else False for n, i in enumerate(lidx)]
    lm = [medium[i] if n < s else False for n, i in enumerate(lidx)]
    cA = side(cidx, lambda n, i: n < t - 2, lambda i: A[i])
    cB = side(cidx, cok, lambda i: B[i])
    cq = side(cidx, cok, lambda i: q[i])
    cd = [delta[i] if n < t else False for n, i in enumerate(cidx)]
    cm = [medium[i] if n < t else False for n, i in enumerate(cidx)]
    ov = lambda i, arr: arr[i] if 0 <= i <= k else 1.0  # noqa: E731
    joins = [ov(s, A), ov(s + 1, A), ov(s - 1, B), ov(s - 2, B)]
    return (lA, lB, lq, ld, lm), (cA, cB, cq, cd, cm), joins


def _batch(path, ML, MC, merge, only=None):
    """Every technique of the path (or those `only` keeps), padded to D + 1 rows (one
    compiled program per shape)."""
    k = path[0]
    ss = [s for s in (range(1, k) if merge else range(0, k + 1))
          if only is None or only(s, k + 1 - s)]
    if not ss:
        return None
    rows = [(s, k + 1 - s) + _cut(path, s, k + 1 - s, ML, MC) for s in ss]
    rows = rows + [rows[0]] * (D + 1 - len(rows))
    st_ = np.array([r[0] for r in rows], np.int32)
    tt = np.array([r[1] for r in rows], np.int32)
    lig = tuple(np.array([r[2][f] for r in rows]) for f in range(5))
    cam = tuple(np.array([r[3][f] for r in rows]) for f in range(5))
    joins = np.array([r[4] for r in rows])
    return st_, tt, lig, cam, joins, len(ss)


@functools.partial(jax.jit, static_argnames=("cfg", "merge"))
def _both(cfg, st_, tt, lig, cam, joins, dl, inf, etas, merge):
    LP = Pdfs(*lig)
    CP = Pdfs(*cam)
    log_n = jnp.log(jnp.asarray(37.0, joins.dtype))

    def one(s, t, lp, cp, j):
        old = weight(cfg, s, t, lp, cp, j[0], j[1], j[2], j[3], dl, inf, log_n, etas[0],
                     etas[1], merge)
        Lp = MP.light(cfg, lp.A, lp.B, lp.q, lp.delta, lp.medium, dl, etas)
        Cp = MP.camera(cfg, cp.A, cp.B, cp.q, cp.delta, cp.medium, log_n, etas)
        new = MP.join_weight(cfg, s, t, Lp, Cp, j[0], j[1], j[2], j[3], dl, inf, log_n, merge)
        if cfg.algorithm == "pt":  # PT's closed form (`pt_weight`, the renderer's `_inline`)
            pt = _pt_closed_form(cfg, s, t, lp, cp, j, dl)  # for PT's techniques
            return old, new, jnp.where((s <= 1) & (t >= 2), pt, new)
        if lp.A.shape[0] != 1:
            return old, new, new
        # a lone light vertex (next-event estimation): its entries in closed form, as the
        # renderer's NEE queue reads them
        Le = MP.start_entries(cfg, lp.A[0], dl, jnp.where(lp.medium[0], etas[1], etas[0]))
        start = MP.join(cfg, s, t, Le, MP.entries(cfg, Cp, t, s), j[0], j[1], j[2], j[3], dl,
                        inf, log_n, merge)
        return old, new, start

    return jax.vmap(one)(st_, tt, LP, CP, joins)


def _pt_closed_form(cfg, s, t, lp, cp, j, dl):
    """`MP.pt_weight` from what the camera trace knows at z_{t-1} (`_inline.estimate`):
    the camera's local pdfs z_0..z_{t-1} with their roulette, their zero flag, the delta
    flags of z_{t-1} and z_{t-2}; s = 0 reads A(z_{t-1}) = j[0], s = 1 the light sample's
    A(y_0) = lp.A[0] and B(y_0) = j[2]."""
    tech = cfg.techniques
    m = jnp.arange(cp.B.shape[0], dtype=jnp.int32)
    q_prev = jnp.concatenate([jnp.ones_like(cp.q[:1]), cp.q[:-1]])
    local = cp.B * jnp.where(m >= 1, MP._rr(m - 1, q_prev, cfg.rr_depth), 1.0)
    zero = jnp.any((m < t) & ~(local > 0))
    jz = t - 1  # z_j, the vertex of the technique
    lp_z = MP._log_pos(local[jz], 0.0)
    hit = MP.pt_weight(cfg, lp_z, MP._log_pos(j[0], MP.NEG),
                       tech.nee & (jz >= 2) & ~cp.delta[jnp.maximum(jz - 1, 0)],
                       tech.emitter_hits & ~dl & ~zero)
    other = MP._log_pos(j[2] * MP._rr(jz, cp.q[jz], cfg.rr_depth), MP.NEG)
    nee = MP.pt_weight(cfg, MP._log_pos(lp.A[0], 0.0), other, tech.emitter_hits & ~dl,
                       tech.nee & ~cp.delta[jz] & (lp.A[0] > 0) & ~zero)
    return jnp.where(s == 0, hit, nee)


def _weights(cfg, dtype, st_, tt, lig, cam, joins, n, dl, inf, etas, merge):
    """(assembled, partial sums) weights of the batch; for a one-vertex light side the
    closed-form start entries (`start_entries`) must equal the partial sums exactly."""
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    lig = (f(lig[0]), f(lig[1]), f(lig[2]), jnp.asarray(lig[3]), jnp.asarray(lig[4]))
    cam = (f(cam[0]), f(cam[1]), f(cam[2]), jnp.asarray(cam[3]), jnp.asarray(cam[4]))
    old, new, start = _both(cfg, jnp.asarray(st_), jnp.asarray(tt), lig, cam, f(joins),
                            jnp.asarray(dl), jnp.asarray(inf), (f(etas[0]), f(etas[1])), merge)
    # a one-vertex light side: `start_entries` must equal the partial sums exactly; PT: its
    # closed form (`pt_weight`) must equal the partial sums to round-off (s <= 1, t >= 2:
    # the techniques PT has)
    np.testing.assert_allclose(np.asarray(start)[:n], np.asarray(new)[:n], rtol=1e-6,
                               atol=0 if cfg.algorithm != "pt" else 1e-7,
                               err_msg="closed form differs from the partial sums")
    if cfg.algorithm != "pt":
        np.testing.assert_array_equal(np.asarray(start)[:n], np.asarray(new)[:n],
                                      err_msg="start_entries differ from the one-vertex partials")
    return np.asarray(old)[:n], np.asarray(new)[:n]


# (algorithm, roulette start, dtype, heuristic): every algorithm, roulette from the first vertex (1),
# inside the path (2, 3, 4) and never (9 > D); one compiled program per case and shape
CASES = [("vcm", 1, "float64", "power"), ("vcm", 2, "float32", "power"),
         ("vcm", 4, "float64", "balance"), ("vcm", 9, "float64", "power"),
         ("bpm", 3, "float64", "balance"), ("bdpt", 4, "float32", "power"),
         ("bdpt", 2, "float64", "balance"), ("pt", 2, "float64", "power"),
         ("lt", 3, "float64", "balance")]
TOL = {"float64": 1e-9, "float32": 2e-5}


@pytest.mark.parametrize("algorithm,rr_depth,dtype,mis", CASES,
                         ids=[f"{a}-rr{r}-{d}-{m}" for a, r, d, m in CASES])
@settings(max_examples=15, deadline=None)
@given(path=cut_paths())
def test_join_weights_equal_the_assembled_sums(path, mis, algorithm, rr_depth, dtype):
    tol = TOL[dtype]
    cfg = RenderConfig(algorithm=algorithm, max_depth=D, rr_depth=rr_depth, mis=mis)
    dt = getattr(jnp, dtype)
    k, dl, inf = path[0], path[6], path[7]
    etas = (path[9], path[10])
    for merge in ([False, True] if cfg.techniques.merging == "all" and k >= 2 else [False]):
        # the renderer's lengths (light D, camera D + 1), next-event estimation's one light
        # vertex (s = 1) and light tracing's lone pinhole (t = 1)
        for ML, MC, only in ((D, D + 1, None), (1, D + 1, lambda s, t: s == 1),
                             (D, 1, lambda s, t: t == 1)):
            b = _batch(path, ML, MC, merge, only)
            if b is None:
                continue
            old, new = _weights(cfg, dt, *b, dl, inf, etas, merge)
            np.testing.assert_allclose(new, old, rtol=tol, atol=tol,
                                       err_msg=f"merge={merge} ML={ML} s={b[0]} t={b[1]}")


def test_one_vertex_subpaths():
    # next-event estimation (a one-vertex light subpath, s = 1) and light tracing (the
    # pinhole alone, t = 1) on a path of k = 3 segments, vcm, roulette from the start
    cfg = RenderConfig(algorithm="vcm", max_depth=D, rr_depth=1, mis="power")
    path = (3, [0.5, 2.0, 0.3, 1.5], [0.7, 0.2, 4.0, 1.0], [0.9, 0.5, 0.8, 0.6],
            [False, False, False, False], [False, True, False, False], False, False, 7.0,
            -1.0, 0.5)
    for ML, MC, only in ((1, D + 1, lambda s, t: s == 1), (D, 1, lambda s, t: t == 1)):
        old, new = _weights(cfg, jnp.float64, *_batch(path, ML, MC, False, only), False,
                            False, (-1.0, 0.5), False)
        assert 0.0 < float(old[0]) < 1.0
        np.testing.assert_allclose(new, old, rtol=1e-12)
