"""Multiple importance sampling as explicit sums over every technique (Veach 1997, ch. 10;
pbrt's BDPT `MISWeight`; Georgiev et al. 2012 for the merging extension).

A full path x_0 ... x_k (x_0 on the light, x_k the camera) is described per vertex by
    a_i = p->(x_i): pdf of generating x_i from the light side (area / volume / solid-angle
          measure, Russian roulette included),
    b_i = p<-(x_i): pdf of generating x_i from the camera side,
and the connection technique with s light vertices has
    p_s = prod_{i<s} a_i  prod_{i>=s} b_i,    so  p_j / p_s = exp(c_j - c_s),
    c_j = sum_{i<j} log(a_i / b_i)                      (the cumulative log ratio).
Working with c in log space, the weight of technique s is
    w_s = n_s p_s^beta / sum_{valid j} n_j p_j^beta = exp(-logsumexp_j [beta (c_j - c_s) + log n_j - log n_s])
which cannot overflow or underflow however long the path or tiny the pdfs (float32 safe).

Delta vertices. After a delta (specular) vertex the pdf of the next vertex carries a
Dirac delta in both directions; the tracer stores the Dirac as 1 but keeps its conversion
to the next vertex's measure (cos / d^2: `_subpath` module doc, which says why pbrt's
remap of the whole pdf to 1 is wrong with merging), and every technique that would
connect at a delta vertex is invalid, so the Diracs never appear in a ratio. Zero pdfs
(e.g. the back of a one-sided light seen from the reverse side) make a technique
impossible; they are excluded explicitly rather than through 0 * inf.

Valid connection techniques j in [0, k+1] (j light vertices, t = k+1-j camera vertices):
    j = 0      the camera subpath hits the light: the light is not a delta light;
    1 <= j <= k  connect x_{j-1} and x_j: neither is a delta vertex (x_0 on any light and
               the pinhole x_k can always be connected to: NEE and light tracing);
    j = k+1    the light subpath hits the camera: impossible for a pinhole.
The algorithm flags restrict the set further (pt: j = 0, and j = 1 for k >= 2 (NEE; for
k = 1, j = 1 is light tracing); lt: j = k; bdpt: all).
Multiplicities n_j: light tracing (j = k) is evaluated once per light path for every
pixel, n = N_light (with the per-pixel camera pdf), all others n = 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._config import TECHNIQUES


def _sums(x, rel, cols: int):
    """out[j] = sum_i x[i] [rel(i, j)], j < cols: the prefix / suffix sums of a short
    per-path vector as one product with a constant 0/1 matrix (where `jnp.cumsum` lowers to
    a `reduce_window` whose window spans the whole axis: O(L^2) adds per lane on the
    CPU)."""
    L = x.shape[0]
    m = rel(np.arange(L)[:, None], np.arange(cols)[None, :]).astype(np.float32)
    return jnp.matmul(x, jnp.asarray(m, x.dtype), precision=jax.lax.Precision.HIGHEST)


def mis_weight(a: Float[Array, "L"], b: Float[Array, "L"], delta: Bool[Array, "L"],
               k: Int[Array, ""], s: Int[Array, ""], delta_light: Bool[Array, ""],
               infinite_light: Bool[Array, ""], log_n_lt: Float[Array, ""],
               algorithm: str = "bdpt", beta: float = 1.0, log_eta: Float[Array, "L"] | None = None,
               merge=False) -> Float[Array, ""]:
    """The MIS weight of technique s of a full path x_0..x_k, by explicit sums in log space.

    Entries i > k of the per-vertex arrays are ignored.
    a, b: per-vertex light- and camera-side pdfs (Diracs as 1, RR included);
    delta: per-vertex delta flag; delta_light: x_0 is on a delta light (the sun);
    infinite_light: x_0 is at infinity (sun, sky): it cannot be joined to the pinhole (k = 1);
    log_n_lt: log of the light-tracing multiplicity N_light; beta: 1 balance, 2 power.
    log_eta: per vertex log(kernel N): log(pi r^2 N) on surfaces, log(4/3 pi r^3 N) in the
    medium (merging algorithms only); merge: the technique is merging at vertex s
    (p_VM,s = a_s p_VC,s kernel, multiplicity N: Georgiev et al. 2012, tech. rep. eq. 12).
    Merging at x_i needs 1 <= i <= k-1 (not at the light's first vertex, not at the
    camera) and x_i non-delta; `ppm` keeps only the first non-delta vertex seen from the
    camera (and emitter hits through a purely delta camera prefix).
    """
    L = a.shape[0]
    dt = a.dtype
    k = jnp.asarray(k, jnp.int32)
    s = jnp.asarray(s, jnp.int32)
    i = jnp.arange(L, dtype=jnp.int32)
    in_path = i <= k
    pos_a = (a > 0) | ~in_path
    pos_b = (b > 0) | ~in_path
    la = jnp.log(jnp.where(in_path & (a > 0), a, 1.0))
    lb = jnp.log(jnp.where(in_path & (b > 0), b, 1.0))
    # c_j = sum_{i<j} (log a_i - log b_i), j = 0..L
    c = _sums(la - lb, lambda i, j: i < j, L + 1)  # c_j = sum_{i<j}, j = 0..L
    j = jnp.arange(L + 1, dtype=jnp.int32)
    # p_j > 0  <=>  a_i > 0 for all i < j  and  b_i > 0 for all k >= i >= j
    za = _sums((~pos_a).astype(dt), lambda i, j: i < j, L + 1)  # zeros among a_i, i < j
    zb_suffix = _sums((~pos_b).astype(dt), lambda i, j: i >= j, L + 1)  # among b_i, i >= j
    positive = (za == 0) & (zb_suffix == 0)
    # connectability of technique j: x_{j-1} and x_j non-delta (with the end rules)
    dpad = jnp.concatenate([delta & in_path, jnp.zeros((1,), bool)])
    left_delta = jnp.concatenate([jnp.zeros((1,), bool), delta & in_path])  # x_{j-1}
    conn = jnp.where(j == 0, ~delta_light,
                     jnp.where(j == k + 1, False,
                               ~jnp.where(j == 1, False, left_delta) & ~jnp.where(j == k, False, dpad)))
    conn = conn & ~((j == 1) & (k == 1) & infinite_light)
    tech = TECHNIQUES[algorithm]
    valid = conn & positive & (j <= k + 1) & tech.connection_mask(j, k)
    # non-delta interior vertices strictly between x_i and the camera (for ppm)
    nd = (~delta & in_path & (i >= 1) & (i <= k - 1)).astype(jnp.int32)
    nd_after = _sums(nd.astype(dt), lambda m, i: m > i, L)  # sum_{m > i} nd_m
    if tech.merging == "first":
        # emitter hits only through a purely delta camera prefix
        valid = valid & (jnp.sum(nd) == 0)
    log_n = jnp.where(j == k, log_n_lt, 0.0).astype(dt)
    lvc = c + log_n  # log(n_j p_j / p_b), p_b = prod b_i: j = 0..L
    own = lvc[s]
    own_valid = valid[s]
    if tech.merging is not None:
        lm = c[:-1] + la + log_eta  # log(n_VM p_VM,i / p_b), i = 0..L-1
        vm = (in_path & (i >= 1) & (i <= k - 1) & ~delta & positive[:-1] & pos_a)
        if tech.merging == "first":
            vm = vm & (nd_after == 0)
        own = jnp.where(merge, lm[jnp.minimum(s, L - 1)], own)
        own_valid = jnp.where(merge, vm[jnp.minimum(s, L - 1)], own_valid)
    # w = (n_s p_s)^beta / sum_T (n_T p_T)^beta: differences to the own technique first
    # (small numbers), then logsumexp
    terms = jnp.where(valid, beta * (lvc - own), -jnp.inf)
    if tech.merging is not None:
        terms = jnp.concatenate([terms, jnp.where(vm, beta * (lm - own), -jnp.inf)])
    w = jnp.exp(-jax.nn.logsumexp(terms))
    return jnp.where(own_valid, w, 0.0)
