"""The explicit MIS sums of `_full`, evaluated at the join: O(D) per subpath, O(1) per
technique.

`_mis.mis_weight` assembles the whole path x_0..x_k for every technique of every lane and
sums over all of its techniques: O(D) gathers and O(D^2) adds per technique. The sums
split at the join. With c_j = sum_{i<j} (log a_i - log b_i) (`_full`), every term of
technique s's denominator relative to the connection technique s is, in log space,
    connection j < s:  sum_{i=j}^{s-1} d_i,               d_i = log b_i - log a_i,
    merge at i < s:    log b_i + log eta_i + sum_{m=i+1}^{s-1} d_m,
    connection j > s:  log n_j + sum_{i=s}^{j-1} e_i,     e_i = log a_i - log b_i,
    merge at i >= s:   log a_i + log eta_i + sum_{m=s}^{i-1} e_m,
(each times beta), so the light side's log-sum obeys S(p+1) = u_p (+) (d_p + S(p)) and the
camera side's T(p) = u_p (+) (e_p + T(p+1)) ((+) = logaddexp; u_p the terms that start
at x_p: the tech report's dVCM/dVC/dVM recursion, here in log space). Only the pdfs next
to the join depend on the technique: b_{s-1}, b_{s-2} and a_s, a_{s+1} (re-evaluated by
the join: `_connect`'s join pdfs, `_path.reverse_pdf`), and the Russian roulette of each
direction, which counts from the generating end: b_i (light vertex) carries q_{i+1} iff
k - i - 1 >= rr_depth, so on the light side the last rr_depth - t - 1 vertices before
those two lack it (t: camera vertices), and symmetrically a_i on the camera side with s.
Each subpath therefore keeps, per vertex position m and per "other side length" variant,
the log-sum over the vertices before the two join vertices (`Partials.table`, built once
per subpath by the recursion with q and at most rr_depth - 1 steps without it), and a
technique adds its two join vertices on each side, its own term, and one log-sum-exp.
Same weights as `mis_weight` to float32 round-off (the MIS tests,
tests/mis/test_mis_partial.py, compare them on random subpaths). ppm (photons gathered
only at the first non-delta camera vertex) takes no weights at all
(`_config.Techniques.weighted`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._config import RenderConfig
from ._base import AbstractMIS

NEG = -jnp.inf


def _lae(*xs):
    out = xs[0]
    for x in xs[1:]:
        out = jnp.logaddexp(out, x)
    return out


def log_pos(x, zero):
    """log x, with `zero` where x <= 0."""
    return jnp.where(x > 0, jnp.log(jnp.where(x > 0, x, 1.0)), zero)


_log_pos = log_pos


def _rr(index, q, rr_depth):
    return jnp.where(index >= rr_depth, q, 1.0)


def variants(cfg: RenderConfig, M: int) -> tuple[int, int]:
    """(lowest other-side length o_lo, number of variants) of a subpath with M vertices: a
    variant with other-side length o has min(max(rr_depth - o - 1, 0), M) vertices without
    roulette before the join vertices; o <= rr_depth - 1 - M all have M, o >= rr_depth - 1
    none, and no side is longer than max_depth + 1 vertices (roulette that never starts:
    one variant)."""
    hi = min(cfg.rr_depth - 1, cfg.max_depth + 1)
    lo = min(max(0, cfg.rr_depth - 1 - M), hi)
    return lo, hi - lo + 1


class Partials(NamedTuple):
    """One subpath's share of the MIS sums, per lane (built by `light` or `camera`).

    table: [V, M+1] log-sum over the techniques that start at the first m vertices
           (light: x_0..x_{m-1}; camera: z_0..z_{m-1}), carried to vertex m, per variant;
    lp:    [M] log of the local pdf with its own roulette (light: a_i; camera: b_i); a zero
           pdf is logged as 0 and flagged in `zero`;
    zero:  [M+1] a zero local pdf among the first m vertices (the technique is impossible);
    vc:    [M] the connection technique that starts at the vertex is enabled and
           connectable (light x_i: technique i; camera z_c: technique k - c + 1);
    vm:    [M] merging at the vertex is enabled (non-delta, not the subpath's first);
    q, delta, leta: [M] local roulette survival, delta flag, log(kernel N) at the vertex;
    mn, lm: [M] (light subpaths with manifold next-event estimation, else None) the
           connection technique that starts at the vertex is a manifold connection
           through the delta vertex before it (`_mnee`: y_2 after the water surface y_1),
           and the log of its pdf relative to that of the connection the delta convention
           would give it, log(a_1^eff / a_1) (added to its term; 0 elsewhere).
    """

    table: Array
    lp: Array
    zero: Array
    vc: Array
    vm: Array
    q: Array
    delta: Array
    leta: Array
    mn: Array | None = None
    lm: Array | None = None


def _tables(cfg, M, u_q, d_q, u_1, d_1, bad):
    """Per variant, log-sums S[m] (m = 0..M) of S(p+1) = u_p (+) (d_p + S(p)), S(0) = -inf,
    with (u_1, d_1) (no roulette) for the last z vertices before m and (u_q, d_q) before;
    and zero[m]: `bad` among the first m vertices. Inputs [M, *lanes] -> [V, M+1, *lanes],
    [M+1, *lanes]."""
    def step(carry, x):
        Sq, S1, z = carry
        uq, dq, u1, d1, b = x
        carry = (jnp.logaddexp(uq, dq + Sq), jnp.logaddexp(u1, d1 + S1), z | b)
        return carry, carry

    lanes = d_q.shape[1:]
    ex = (1,) * len(lanes)  # trailing lane axes of the static masks
    neg = jnp.full(lanes, NEG, d_q.dtype)
    no = jnp.zeros(lanes, bool)
    lo, V = variants(cfg, M)
    z = np.array([min(max(cfg.rr_depth - o - 1, 0), M) for o in range(lo, lo + V)])[:, None]
    if M == 1:  # a lone start vertex (next-event estimation's light sample, the pinhole)
        S1 = jnp.where(z.reshape((V,) + ex) >= 1, u_1[0], u_q[0])
        return (jnp.stack([jnp.broadcast_to(neg, S1.shape), S1], axis=1),
                jnp.stack([no, bad[0]]))
    _, (Sq, S1, zero) = jax.lax.scan(step, (neg, neg, no), (u_q, d_q, u_1, d_1, bad))
    Sq = jnp.concatenate([neg[None], Sq])
    S1 = jnp.concatenate([neg[None], S1])  # no roulette at all: the variants with z = M
    zero = jnp.concatenate([no[None], zero])
    # variant with z vertices without roulette before the join: S_z[m] is the roulette
    # recursion's S[m - z] carried on by z steps without it. The last of those steps is
    # vertex m - 1's, and what it starts from is variant z - 1 at row m - 1, so
    #     S_z[m] = u_1[m-1] (+) (d_1[m-1] + S_{z-1}[m-1]),  S_z[0] = S[0],  S_0 = Sq:
    # one elementwise step over [M+1, lanes] per variant, the row shift a pad (the same
    # operations in the same order as z steps per variant, which cost sum z instead of
    # max z; a gather of u_1[p] for all variants at once would be a scalar gather loop
    # over [V, M+1, lanes] on the CPU backend).
    zs = [int(x) for x in z[:, 0]]
    m = np.arange(M + 1)
    pad = jnp.zeros((1,) + u_1.shape[1:], u_1.dtype)
    us = jnp.concatenate([pad, u_1[:M]])  # row m: u_1[m - 1]
    ds = jnp.concatenate([pad, d_1[:M]])
    on = (m >= 1).reshape((M + 1,) + ex)
    chain = [Sq]
    for _ in range(min(max(zs), M)):
        prev = jnp.concatenate([Sq[:1], chain[-1][:M]])  # row m: S_{z-1}[m - 1]
        chain.append(jnp.where(on, jnp.logaddexp(us, ds + prev), Sq[:1]))
    table = [S1 if zv >= M else chain[zv] for zv in zs]  # no roulette at all: S1
    return jnp.stack(table), zero


def subpath(cfg: RenderConfig, A, B, q, delta, medium, camera_side, delta_light=False,
            log_n_lt=0.0, etas=(0.0, 0.0), mn=None, lm=None) -> Partials:
    """Partials of one subpath (A, B, q, delta, medium [M, *lanes]: vertices first, any
    trailing lane axes; camera_side, delta_light broadcast against the lanes): a light subpath
    y_0..y_{M-1} (`camera_side` False) or a camera subpath z_0..z_{M-1} (True; z_0 the
    pinhole); `camera_side` may be a traced flag (light and camera lanes in one call).
    The pdfs the join re-evaluates (B of a light subpath's, A of a camera subpath's last
    two vertices) are never read.

    The local pdf (light a_i, camera b_c) carries the subpath's own roulette (index from
    its start); the other one (light b_i, camera a_i) the roulette of the other direction,
    q of the next vertex along the subpath, with (`_q`) or without (`_1`) it. `mn`, `lm`
    ([M, *lanes] or None): manifold connections (`Partials`; False / 0 on camera lanes)."""
    tech = cfg.techniques
    beta = 2.0 if cfg.mis == "power" else 1.0
    M = A.shape[0]
    dt = A.dtype
    delta_light = jnp.asarray(delta_light, bool)
    i = np.arange(M).reshape((M,) + (1,) * (A.ndim - 1))
    one = jnp.ones((1,) + A.shape[1:], dt)
    q_prev = jnp.concatenate([one, q[:-1]])
    q_next = jnp.concatenate([q[1:], one])
    own = jnp.where(camera_side, B, A)
    other = jnp.where(camera_side, A, B)
    local = own * jnp.where(i >= 1, _rr(i - 1, q_prev, cfg.rr_depth), 1.0)
    lp = _log_pos(local, 0.0)
    leta = jnp.where(medium, etas[1], etas[0]).astype(dt)
    d_prev = jnp.concatenate([jnp.zeros((1,) + A.shape[1:], bool), delta[:-1]])
    # the connection technique that starts at the vertex: light x_i starts technique i
    # (x_{i-1} - x_i; i = 0 the emitter hit, i = 1 next-event estimation); camera z_c
    # starts technique k - c + 1 (z_c - z_{c-1}; c = 1 light tracing, c = 0 none)
    vc_light = jnp.where(i == 0, tech.emitter_hits & ~delta_light,
                         jnp.where(i == 1, tech.nee, tech.connections) & ~delta
                         & ((i == 1) | ~d_prev))
    vc_camera = jnp.where(i == 0, False,
                          jnp.where(i == 1, tech.light_tracing & ~delta,
                                    tech.connections & ~delta & ~d_prev))
    vc = jnp.where(camera_side, vc_camera, vc_light)
    if mn is not None:  # a manifold connection starts where the delta convention has none
        vc = vc | mn
    ln = jnp.where(camera_side & (i == 1), log_n_lt, 0.0).astype(dt)
    vm = jnp.asarray(tech.merging == "all") & (i >= 1) & ~delta

    def terms(lo):  # u: the techniques that start at the vertex; d: the step to the next
        d = beta * (lo - lp)
        c = d + beta * ln if lm is None else d + beta * (ln + lm)
        u = jnp.logaddexp(jnp.where(vc, c, NEG), jnp.where(vm, beta * (lo + leta), NEG))
        return u, d

    table, zero = _tables(cfg, M, *terms(_log_pos(other * q_next, NEG)),
                          *terms(_log_pos(other, NEG)), ~(local > 0))
    return Partials(table, lp, zero, vc, vm, q, delta, leta, mn, lm)


def light(cfg: RenderConfig, A, B, q, delta, medium, delta_light, etas=(0.0, 0.0), mn=None,
          lm=None) -> Partials:
    """Partials of a light subpath y_0..y_{M-1} (one lane)."""
    return subpath(cfg, A, B, q, delta, medium, False, delta_light, 0.0, etas, mn, lm)


def camera(cfg: RenderConfig, A, B, q, delta, medium, log_n_lt, etas=(0.0, 0.0)) -> Partials:
    """Partials of a camera subpath z_0..z_{M-1} (one lane)."""
    return subpath(cfg, A, B, q, delta, medium, True, False, log_n_lt, etas)


class Entries(NamedTuple):
    """What a technique reads from one side's partials: the two vertices next to the join
    (1: adjacent, 2: the one before), the table entry before them, the zero flag."""

    ok1: Array
    lp1: Array
    vc1: Array
    vm1: Array
    q1: Array
    delta1: Array
    leta1: Array
    ok2: Array
    lp2: Array
    vc2: Array
    vm2: Array
    delta2: Array
    leta2: Array
    table: Array
    zero: Array
    # manifold connections (None without them): the log factor of the connection that
    # starts at each of the two vertices, and whether the connection technique s that
    # starts at x_s (a merge's photon) is a manifold one, with its factor
    lm1: Array | None = None
    lm2: Array | None = None
    mn0: Array | None = None
    lm0: Array | None = None


def entries(cfg: RenderConfig, P: Partials, n, other, index=()) -> Entries:
    """The entries of a side with n vertices in the technique (light: s, camera: t) whose
    other side has `other` vertices. Indices may be numpy arrays (a family of techniques:
    static slices of fields [M, ...]), traced (one technique per lane) or mixed; `index`:
    indices of the fields' trailing axes (e.g. the lane of each technique)."""
    M = P.lp.shape[0]
    xp = np if isinstance(n, (int, np.ndarray)) else jnp
    V = variants(cfg, M)

    def row(i):
        ic = xp.clip(i, 0, M - 1)
        ok = (i >= 0) & (i < M)
        lead = P.lp[(ic,) + index].ndim - np.ndim(ok)  # trailing lane axes of a family
        return ok.reshape(np.shape(ok) + (1,) * lead), lambda a: a[(ic,) + index]

    ok1, g1 = row(n - 1)
    ok2, g2 = row(n - 2)
    v = xp.clip(other, V[0], V[0] + V[1] - 1) - V[0]
    mn = {}
    if P.mn is not None:
        ok0, g0 = row(n)
        mn = dict(lm1=g1(P.lm), lm2=g2(P.lm), mn0=g0(P.mn) & ok0, lm0=g0(P.lm))
    return Entries(ok1, g1(P.lp), g1(P.vc) & ok1, g1(P.vm) & ok1, g1(P.q), g1(P.delta),
                   g1(P.leta), ok2, g2(P.lp), g2(P.vc) & ok2, g2(P.vm) & ok2, g2(P.delta),
                   g2(P.leta), P.table[(v, xp.clip(n - 2, 0, M)) + index],
                   P.zero[(xp.clip(n, 0, M),) + index], **mn)


def start_entries(cfg: RenderConfig, A0, delta_light, leta0=0.0) -> Entries:
    """The light side's `Entries` of a technique with s = 1 whose light subpath is the lone
    vertex y_0 (next-event estimation's fresh light sample), in closed form: what
    `entries(cfg, light(cfg, A0[None], B0[None], 1, False, False, delta_light, etas), 1, t)`
    reads. y_0 is the adjacent join vertex (ok1; its local pdf a_0 = A0 has no roulette,
    q1 = 1); the only technique starting at it is the emitter hit (vc1, unless the light
    is delta); no merging at a subpath's first vertex (vm1 = False); there is no second
    vertex (ok2 = False: u2 and the table drop out, table = -inf); the technique is
    impossible iff A0 = 0 (zero). B0 is never read (the join re-evaluates it), nor is the
    roulette variant (the table is empty). Elementwise in A0, delta_light."""
    A0 = jnp.asarray(A0)
    dt = A0.dtype
    f = jnp.zeros(A0.shape, bool)
    lp = _log_pos(A0, 0.0)
    leta = jnp.broadcast_to(jnp.asarray(leta0, dt), A0.shape)
    return Entries(ok1=~f, lp1=lp, vc1=jnp.asarray(cfg.techniques.emitter_hits) & ~delta_light,
                   vm1=f, q1=jnp.ones_like(A0), delta1=f, leta1=leta, ok2=f, lp2=lp, vc2=f,
                   vm2=f, delta2=f, leta2=leta, table=jnp.full(A0.shape, NEG, dt),
                   zero=~(A0 > 0))


def join_weight(cfg: RenderConfig, s, t, L: Partials, C: Partials, A_s, A_s1, B_s1, B_s2,
                delta_light, infinite_light, log_n_lt, merge=False, lanes=((), ())):
    """MIS weight of technique (s, t) for one lane (`lanes`: each side's trailing-axis
    indices, see `entries`), from the two subpaths' partials and the four pdfs the join
    re-evaluates (`_connect.JoinPdfs`: A_s = a(x_s), A_s1 = a(x_{s+1}) if t >= 3,
    B_s1 = b(x_{s-1}), B_s2 = b(x_{s-2})); log_n_lt: log of light tracing's multiplicity;
    `merge`: merging at x_s = z_{t-1} (A_s is then the photon's pdf). The weight of
    `ExplicitMIS.join_weight`."""
    return join(cfg, s, t, entries(cfg, L, s, t, lanes[0]), entries(cfg, C, t, s, lanes[1]),
                A_s, A_s1, B_s1, B_s2, delta_light, infinite_light, log_n_lt, merge)


def join(cfg: RenderConfig, s, t, Le: Entries, Ce: Entries, A_s, A_s1, B_s1, B_s2,
         delta_light, infinite_light, log_n_lt, merge=False, lm_own=None, c2=None):
    """`join_weight` from the entries of both sides: elementwise, any batch shape (s, t
    broadcast against the pdfs).

    Manifold connections (`_mnee`; technique 2 through the delta vertex x_1 on the water
    surface, whose pdf is the delta convention's times exp(lm)): `lm_own` weights that
    technique itself (s = 2: its own term is beta lm instead of the connection's 0);
    `c2` = (ok, lm): an emitter hit (s = 0) whose z_{t-2} is such a surface vertex adds the
    manifold connection z_{t-2} - z_{t-3} to its camera-side sum; the light side's
    manifold connections come in the entries (`Entries.lm1`, ...)."""
    tech = cfg.techniques
    beta = 2.0 if cfg.mis == "power" else 1.0
    R = cfg.rr_depth
    k = s + t - 1
    dt = Le.lp1.dtype
    q_y = jnp.where(Le.ok1, Le.q1, 1.0)  # x_{s-1}
    q_z = Ce.q1  # x_s = z_{t-1}

    # ---- light side: b_{s-1}, b_{s-2} re-evaluated, roulette counted from the camera ----
    lb1 = _log_pos(B_s1 * _rr(t - 1, q_z, R), NEG)
    lb2 = _log_pos(B_s2 * _rr(t, q_y, R), NEG)
    d1 = jnp.where(Le.ok1, beta * (lb1 - Le.lp1), 0.0)
    d2 = jnp.where(Le.ok2, beta * (lb2 - Le.lp2), 0.0)
    c1 = d1 if Le.lm1 is None else d1 + beta * Le.lm1
    c2_ = d2 if Le.lm2 is None else d2 + beta * Le.lm2
    u1 = jnp.logaddexp(jnp.where(Le.vc1, c1, NEG), jnp.where(Le.vm1, beta * (lb1 + Le.leta1), NEG))
    u2 = jnp.logaddexp(jnp.where(Le.vc2, c2_, NEG), jnp.where(Le.vm2, beta * (lb2 + Le.leta2), NEG))
    SL = _lae(u1, d1 + u2, d1 + d2 + Le.table)

    # ---- camera side: a_s, a_{s+1} re-evaluated, roulette counted from the light ----
    la_s = _log_pos(A_s * jnp.where(s >= 1, _rr(s - 1, q_y, R), 1.0), NEG)
    la_s1 = _log_pos(jnp.where(t >= 3, A_s1, 1.0) * _rr(s, q_z, R), NEG)
    e1 = beta * (la_s - Ce.lp1)
    e2 = jnp.where(Ce.ok2, beta * (la_s1 - Ce.lp2), 0.0)
    # connection s + 1 joins x_s and x_{s+1}; for s = 0 it is next-event estimation (or
    # light tracing if k = 1: the pinhole is x_1), whose x_0 needs no connectability
    vc_s1 = jnp.where(s == 0,
                      jnp.where(k == 1, tech.light_tracing & ~infinite_light,
                                tech.nee & ~Ce.delta2),
                      Ce.vc1)
    ln_s1 = jnp.where(t == 2, log_n_lt, 0.0)  # connection s + 1 is light tracing iff t = 2
    ln_s2 = jnp.where(t == 3, log_n_lt, 0.0)  # connection s + 2 is light tracing iff t = 3
    vm_s = Ce.vm1 & (s >= 1)
    uc1 = jnp.logaddexp(jnp.where(vc_s1, e1 + beta * ln_s1, NEG),
                        jnp.where(vm_s, beta * (la_s + Ce.leta1), NEG))
    uc2 = jnp.logaddexp(jnp.where(Ce.vc2, e2 + beta * ln_s2, NEG),
                        jnp.where(Ce.vm2, beta * (la_s1 + Ce.leta2), NEG))
    if c2 is not None:  # the manifold connection z_{t-2} - z_{t-3} of an emitter hit
        ok_m, lm_m = c2
        uc2 = jnp.logaddexp(uc2, jnp.where(ok_m, e2 + beta * (ln_s2 + lm_m), NEG))
    SC = _lae(uc1, e1 + uc2, e1 + e2 + Ce.table)

    # ---- the connection technique s itself (x_{s-1} - x_s) ----
    positive = ~Le.zero & ~Ce.zero
    conn = jnp.where(s == 0, tech.emitter_hits & ~delta_light,
                     jnp.where(t == 1, tech.light_tracing & ((s == 1) | ~Le.delta1)
                               & ~((k == 1) & infinite_light),
                               jnp.where(s == 1, tech.nee & ~Ce.delta1,
                                         tech.connections & ~Le.delta1 & ~Ce.delta1)))
    conn = conn & positive
    ln_s = jnp.where(t == 1, log_n_lt, 0.0)  # n_s = N for light tracing
    own_conn = jnp.where(conn, beta * ln_s, NEG)
    if lm_own is not None:  # the manifold connection itself (s = 2, t >= 2)
        conn = positive
        own_conn = jnp.where(conn, beta * lm_own, NEG)
    if merge and Le.mn0 is not None:  # the connection technique s is a manifold one
        own_conn = jnp.where(conn, own_conn,
                             jnp.where(Le.mn0 & positive & ~Ce.delta1, beta * Le.lm0, NEG))
    if merge:
        own = beta * (la_s + Ce.leta1)
        own_ok = vm_s & positive & (t >= 2) & jnp.isfinite(la_s)
    else:
        own, own_ok = own_conn, conn
    total = _lae(own_conn, SL, SC)
    return jnp.where(own_ok, jnp.exp(own - total), jnp.zeros((), dt))


# ---------------------------------------------------------------- PT: two techniques
def pt_weight(cfg: RenderConfig, lp_own, la_other, other_ok, conn):
    """`join`'s weight when the algorithm has only PT's techniques (s = 0 emitter hits,
    s = 1 next-event estimation; no light subpath, no connections, no merging, `_config`
    "pt"), for the technique at camera vertex z_j, from the two pdfs of its last vertex:

        w = p_own^beta / (p_own^beta + [other_ok] p_other^beta)
          = exp(-logaddexp(0, beta (log p_other - log p_own))),

    s = 0 (z_j on an emitter): p_own = B(z_j) rr(j - 1, q_{j-1}), the camera's pdf of z_j
          with its roulette (`subpath`'s local pdf: lp_own is its `_log_pos(., 0)`);
          p_other = A(z_j), the light's pdf of the point (`la_other`, `_log_pos(., -inf)`);
          other_ok: next-event estimation from z_{j-1} could have made it (j >= 2, z_{j-1}
          not delta);
    s = 1 (light sample y_0 from z_j): p_own = A(y_0) (`_log_pos(., 0)`); p_other =
          B(y_0) rr(j, q_j), the camera continuing from z_j to y_0; other_ok: the emitter
          hit exists (the light is not delta);
    `conn`: the technique itself is enabled and no pdf of the path is zero (`join`'s
    `conn & positive`); 0 where it is not.

    Derivation from `join` (with every camera-side u-term -inf: PT's camera vertices start
    no light tracing, connection or merge, so the camera table is -inf and uc2 = -inf):
    s = 0: SL = -inf (no light side), SC = uc1 = [vc_s1] beta (la_s - lp1), total =
    logaddexp(0, SC); s = 1: SC = -inf (uc1: no connection s + 2), SL = u1 = [vc1] beta
    (lb1 - lp1) (no second light vertex: d2 = 0, u2 = table = -inf), total = logaddexp(0,
    SL). The same operations in the same order (logaddexp with -inf is exact), so the
    weight equals `join_weight`'s to the bit (tests/mis/test_mis_partial.py)."""
    beta = 2.0 if cfg.mis == "power" else 1.0
    x = jnp.where(other_ok, beta * (la_other - lp_own), NEG)
    return jnp.where(conn, jnp.exp(0.0 - jnp.logaddexp(0.0, x)), jnp.zeros((), lp_own.dtype))


# ---------------------------------------------------------------- the form
def _sg(x):
    return jax.lax.stop_gradient(x)


class ExplicitMIS(AbstractMIS):
    """The explicit sums of `mis_weight` split at the join: per-subpath partial sums
    (`subpath`, O(D) per subpath) and O(1) per technique (`join`)."""

    def subpaths(self, cfg, lends, cends, delta_light, log_n_lt, etas, light_mnee=None):
        mn = lm = None
        if light_mnee is not None and lends is not None:  # (ok [N], lm [N]) of y_2
            Ml, N = lends.A.shape
            at2 = (np.arange(Ml) == 2)[:, None]
            mn = jnp.where(at2, light_mnee[0][None], False)
            lm = jnp.where(at2, _sg(light_mnee[1])[None], 0.0).astype(lends.A.dtype)
        if lends is not None and cends is not None:
            return self._both(cfg, lends, cends, delta_light, log_n_lt, etas, mn, lm)
        L = C = None
        if cends is not None:
            C = camera(cfg, _sg(cends.A), _sg(cends.B), _sg(cends.q), cends.delta,
                       cends.medium, _sg(log_n_lt), _sg(etas))
        if lends is not None:
            L = light(cfg, _sg(lends.A), _sg(lends.B), _sg(lends.q), lends.delta, lends.medium,
                      delta_light, _sg(etas), mn, lm)
        return L, C

    @staticmethod
    def _both(cfg, lig, cam, delta_light, log_n_lt, etas, mn=None, lm=None):
        """(light, camera) partials in one call over both subpaths' lanes (one copy of the
        builder in the compiled program): the light subpaths [M_l, N] are padded to the
        camera subpaths' length [M_c, N] (the padding is never read)."""
        Ml, N = lig.A.shape
        Mc = cam.A.shape[0]

        def cat(a, b, fill):
            pad = jnp.full((Mc - Ml, N), fill, a.dtype)
            return jnp.concatenate([jnp.concatenate([a, pad]), b], axis=1)

        P = subpath(
            cfg, _sg(cat(lig.A, cam.A, 1)), _sg(cat(lig.B, cam.B, 1)), _sg(cat(lig.q, cam.q, 1)),
            cat(lig.delta, cam.delta, False), cat(lig.medium, cam.medium, False),
            jnp.arange(2 * N) >= N,
            jnp.concatenate([jnp.broadcast_to(delta_light, (N,)), jnp.zeros((N,), bool)]),
            _sg(log_n_lt), _sg(etas),
            None if mn is None else cat(mn, jnp.zeros_like(cam.delta), False),
            None if lm is None else cat(lm, jnp.zeros_like(cam.A), 0))
        L = jax.tree.map(lambda a: a[..., :N], P)
        C = jax.tree.map(lambda a: a[..., N:], P)
        return L, C._replace(mn=None, lm=None)

    def empty_light(self, cfg, dtype, etas):
        one = jnp.ones((1, 1), dtype)
        f = jnp.zeros((1, 1), bool)
        return light(cfg, one, one, one, f, f, jnp.zeros((1,), bool), _sg(etas))

    def pinhole(self, cfg, log_n_lt, dtype, etas):
        one = jnp.ones((1, 1), dtype)
        f = jnp.zeros((1, 1), bool)
        return camera(cfg, one, one, one, f, f, _sg(log_n_lt), _sg(etas))

    # the per-technique functions of this module, as the interface's methods
    entries = staticmethod(entries)
    start_entries = staticmethod(start_entries)
    join = staticmethod(join)
    join_weight = staticmethod(join_weight)
