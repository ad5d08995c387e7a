"""Manifold next-event estimation inside the explicit MIS sums (`jaxvcm._mnee`,
`jaxvcm._mis._explicit`): the weight identity.

A path x_0 (light) x_1 (the water surface: a delta vertex) x_2 .. x_k (camera side, x_k
the pinhole) is made by the emitter hit (s = 0), the connections with s >= 3 light
vertices, light tracing, merging at the non-delta vertices x_2 .. x_{k-1} and, new, the
manifold connection (technique 2: light y_0 and s, camera z from x_2 on), whose pdf is
the delta convention's times exp(lm). Every site evaluates its weight from its own side:
the emitter hit through `join(c2=...)`, the light subpaths' partials with the manifold
term at y_2 (`light(mn, lm)`), merges from the photon's row, and the technique itself
from its two-vertex light side (`_mnee.two_vertex_light`) with `lm_own`. Their weights
must sum to 1 on every path (random pdfs over ten decades, Russian roulette from
anywhere, both heuristics, every algorithm that runs the technique); a site that leaves
the term out, or uses another factor, breaks the sum (planted mistakes).
"""

from __future__ import annotations

import numpy as np
import pytest
import jax.numpy as jnp

from jaxvcm import RenderConfig
from jaxvcm._mis import _explicit as MP
from jaxvcm._mnee import two_vertex_light

from .test_mis_partial import D, _cut


def _path(rng, k):
    """Random pdfs of a path of k segments whose x_1 is the delta surface vertex."""
    A = list(10.0 ** rng.uniform(-5, 5, k + 1))
    B = list(10.0 ** rng.uniform(-5, 5, k + 1))
    B[k] = 1.0
    q = list(rng.uniform(0.05, 1.0, k + 1))
    delta = [False, True] + [bool(rng.random() < 0.3) for _ in range(k - 2)] + [False]
    delta[2] = False  # the manifold connection's camera vertex
    medium = [False, False] + [bool(rng.random() < 0.4) for _ in range(k - 2)] + [False]
    return (k, A, B, q, delta, medium, False, False, 123.0, -1.0, 0.5)


def _weights(cfg, path, lm, dl, lm_light=None, eh_term=True):
    """Every technique's weight for the path: connections s = 0..k, merges at x_1..x_{k-1},
    the manifold connection. lm_light: the factor the light partials use (a planted
    mistake when it differs from lm); eh_term: the emitter hit adds the manifold term."""
    k, A, B, q = path[0], path[1], path[2], path[3]
    etas = (jnp.float64(path[9]), jnp.float64(path[10]))
    log_n = jnp.log(jnp.float64(37.0))
    lm_light = lm if lm_light is None else lm_light
    dl, no = jnp.asarray(dl), jnp.asarray(False)
    f64 = lambda x: jnp.asarray(np.asarray(x, np.float64))  # noqa: E731
    rows2 = np.arange(D) == 2

    def parts(s, t, merge):
        (lA, lB, lq, ld, lmed), (cA, cB, cq, cd, cmed), joins = _cut(path, s, t, D, D + 1)
        L = MP.light(cfg, f64(lA), f64(lB), f64(lq), jnp.asarray(ld), jnp.asarray(lmed), dl,
                     etas, mn=jnp.asarray(rows2), lm=f64(np.where(rows2, lm_light, 0.0)))
        C = MP.camera(cfg, f64(cA), f64(cB), f64(cq), jnp.asarray(cd), jnp.asarray(cmed),
                      log_n, etas)
        return L, C, [f64(j) for j in joins]

    out = {}
    i32 = lambda x: jnp.asarray(x, jnp.int32)  # noqa: E731 (traced indices, as the renderer's)
    for s_ in range(0, k + 1):
        s, t = i32(s_), i32(k + 1 - s_)
        L, C, j = parts(s_, k + 1 - s_, False)
        if s == 0:
            Le, Ce = MP.entries(cfg, L, s, t), MP.entries(cfg, C, t, s)
            c2 = (jnp.asarray(eh_term), f64(lm)) if eh_term else None
            w = MP.join(cfg, s, t, Le, Ce, *j, dl, no, log_n, c2=c2)
        else:
            w = MP.join_weight(cfg, s, t, L, C, *j, dl, no, log_n)
        out[("conn", s_)] = float(w)
    if cfg.techniques.merging == "all":
        for s_ in range(1, k):
            L, C, j = parts(s_, k + 1 - s_, True)
            out[("merge", s_)] = float(MP.join_weight(cfg, i32(s_), i32(k + 1 - s_), L, C, *j,
                                                      dl, no, log_n, merge=True))
    # the manifold connection itself: s = 2 (y_0 and the surface vertex), t = k - 1
    _, C, j = parts(2, k - 1, False)
    Le = two_vertex_light(cfg, f64(A[0]), f64(A[1]), dl, etas[0], f64(q[1]))
    w = MP.join(cfg, i32(2), i32(k - 1), Le, MP.entries(cfg, C, i32(k - 1), i32(2)), *j, dl,
                no, log_n, lm_own=f64(lm))
    out[("manifold", 2)] = float(w)
    return out


CASES = [("vcm", 3, "power"), ("vcm", 1, "balance"), ("bdpt", 2, "power"),
         ("bpm", 4, "balance"), ("pt", 2, "power")]


@pytest.mark.parametrize("algorithm,rr_depth,mis", CASES,
                         ids=[f"{a}-rr{r}-{m}" for a, r, m in CASES])
def test_weights_of_every_technique_sum_to_one(algorithm, rr_depth, mis):
    cfg = RenderConfig(algorithm=algorithm, max_depth=D, rr_depth=rr_depth, mis=mis,
                       manifold_nee=True)
    rng = np.random.default_rng(rr_depth * 7 + len(algorithm))
    shares = []
    for trial in range(4):
        k = int(rng.integers(3, D + 1))
        path = _path(rng, k)
        dl = bool(trial == 3)  # a point light: no emitter hit
        lm = float(rng.uniform(-8, 8))
        w = _weights(cfg, path, lm, dl)
        assert all(0.0 <= v <= 1.0 + 1e-12 for v in w.values()), w
        np.testing.assert_allclose(sum(w.values()), 1.0, rtol=1e-9, err_msg=str((path, w)))
        shares.append(w[("manifold", 2)])
    # the technique takes a real share (neither never nor always)
    assert 0.0 < max(shares) and min(shares) < 1.0, shares


@pytest.mark.parametrize("mistake", ["emitter hit without the term", "light partials' factor"])
def test_a_site_that_disagrees_breaks_the_sum(mistake):
    cfg = RenderConfig(algorithm="vcm", max_depth=D, rr_depth=9, mis="power",
                       manifold_nee=True)
    # an area light (the emitter hit exists); technique 3 (light y_0, s, y_2) and merging
    # at y_2 compete with the manifold connection through the light partials
    # unit pdfs but a light-side pdf of x_3 (the camera's first vertex) of 0.03, which
    # keeps light tracing (37 light paths per pixel) from taking the path: the emitter
    # hit, technique 3, merging at x_2 and the manifold connection take about 0.19 each
    path = (4, [1.0, 1.0, 1.0, 0.03, 1.0], [1.0] * 5, [0.9] * 5,
            [False, True, False, False, False], [False] * 5, False, False, 1.0, 0.0, 0.0)
    lm = 0.0
    w = _weights(cfg, path, lm, False)
    assert abs(sum(w.values()) - 1.0) < 1e-12
    assert min(w[("conn", 0)], w[("manifold", 2)], w[("merge", 2)]) > 0.05, w
    if mistake == "emitter hit without the term":
        bad = _weights(cfg, path, lm, False, eh_term=False)
    else:
        bad = _weights(cfg, path, lm, False, lm_light=lm + np.log(2.0))
    assert abs(sum(bad.values()) - 1.0) > 0.02, bad
