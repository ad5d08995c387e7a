"""MIS weights by the recursive dVCM / dVC / dVM form of Georgiev's tech report
"Implementing Vertex Connection and Merging" (2012), in two shapes:
- `mis_weight_recursive`: a second, independent implementation of `_mis.mis_weight` (same
  signature, same semantics) over an assembled full path, an oracle of the MIS tests
  (tests/mis);
- the renderer's recursive form (`RenderConfig(mis_form="recursive")`, end of this
  module): dVCM / dVC / dVM carried along each subpath as it is traced (`carry_step`,
  SmallVCM's way) and joined per technique (`join`), O(1) per technique.

Equation numbers "(tr. NN)" are those of the tech report as cited by SmallVCM's
`vertexcm.hxx`: (20) eta_VCM = pi r^2 N; (31)-(33) subpath start; (34)-(36) non-delta
scattering; (37) full weight; (38)/(39) merging; (40)/(41) connection; (42)/(43) camera
subpath hits a light; (44)/(45) next-event estimation; (46)/(47) light vertex to camera;
(48)-(50) delta lights; (53)-(55) specular (delta) scattering.

Notation
--------
Full path x_0 .. x_k (x_0 on the light, x_k the pinhole); a_i, b_i the light- and
camera-side pdfs of x_i in area / volume measure (the cosines, squared distances,
distance-sampling and Russian-roulette factors already folded in, the Dirac of a pdf
after a delta vertex counted as 1, its conversion kept: `_subpath` module doc); eta_i the
merging kernel times N at x_i (pi r^2 N on surfaces, 4/3 pi r^3 N in the medium); nu_j
the multiplicity of connection technique j (N_light for light tracing, j = k; 1
otherwise). Connection technique j (j light vertices) has
p_j = prod_{i<j} a_i prod_{i>=j} b_i; merging at x_i has n p = eta_i a_i p_i.
The power heuristic raises every factor to beta ("Mis(x)" of the tech report), so below
A_i = a_i^beta, B_i = b_i^beta, H_i = eta_i^beta, E_j = e_j nu_j^beta, where e_j in {0, 1}
and f_i in {0, 1} are the per-technique enable factors of connection j and merging at i.

Area-measure recurrences (derivation)
-------------------------------------
Light subpath. Let S_i be the sum over the techniques that sample fewer light vertices
than the connection technique i+1 (connections j <= i, merges at l <= i), each divided by
p_{i+1}^beta:
    S_i = sum_{j<=i} E_j prod_{m=j..i} B_m/A_m + sum_{l<=i} f_l H_l A_l prod_{m=l..i} B_m/A_m
        = B_i (E_i/A_i + f_i H_i + S_{i-1}/A_i).
b_i and b_{i-1} are the two pdfs a join re-evaluates (the camera side generating x_i and
x_{i-1}), so they must stay outside the stored quantities. Define at x_i
    dVCM_i = E_i / A_i,
    dVC_i  = S_{i-1} / (B_{i-1} A_i),
    dVM_i  = dVC_i / H_i,
then S_i = B_i (f_i H_i + dVCM_i + dVC_i B_{i-1}) and
    dVCM_i = E_i / A_i
    dVC_i  = (f_{i-1} H_{i-1} + dVCM_{i-1} + dVC_{i-1} B_{i-2}) / A_i
    dVM_i  = (H_{i-1}/H_i) (f_{i-1} + dVCM_{i-1}/H_{i-1} + dVM_{i-1} B_{i-2}) / A_i
(the three updates of tr. 34-36 followed by the distance/cosine completion on arrival)
with dVC_0 = dVM_0 = 0, dVCM_0 = E_0 / A_0 (tr. 31-33). In solid-angle form the factor
1/A_i is the tech report's cos(theta_o)/p_fwd_W at x_{i-1} followed by d^2/|cos theta_i|
on arrival at x_i, and B_{i-2} its reverse solid-angle pdf with the cosine/distance it
pairs with; here the area pdfs carry both. The tech report's light start
dVCM = p_direct/p_emit, dVC = cos/p_emit is this recursion's state at x_1 (with our
convention that next-event estimation and emission share a_0). The ratio H_{i-1}/H_i
generalises (tr. 36) to a merging kernel that changes along the path (surface vs
medium); for a constant eta it is 1 and dVM = dVC/eta as in the tech report.

Camera subpath, mirrored (x_k is the pinhole, the subpath runs x_k, x_{k-1}, ...): with
R_i the sum over the techniques that sample more light vertices than connection i
(connections j >= i+1, merges at l >= i), each divided by p_i^beta,
    dVCM^c_i = E_{i+1} / B_i,
    dVC^c_i  = (f_{i+1} H_{i+1} + dVCM^c_{i+1} + dVC^c_{i+1} A_{i+2}) / B_i,
    dVM^c_i  = (H_{i+1}/H_i) (f_{i+1} + dVCM^c_{i+1}/H_{i+1} + dVM^c_{i+1} A_{i+2}) / B_i,
    R_i      = A_i (f_i H_i + dVCM^c_i + dVC^c_i A_{i+1}),
starting from dVCM^c_k = dVC^c_k = dVM^c_k = 0 (the pinhole cannot be hit: E_{k+1} = 0),
so dVCM^c_{k-1} = E_k / B_{k-1} = N^beta / B_{k-1}: the tech report's camera start
Mis(N / p_cam_W) after the first segment (tr. 31-33).

Weights (tr. 37: w = 1 / (w_light + 1 + w_camera))
    connection s (light x_0..x_{s-1}, camera x_s..x_k), own multiplicity nu_s:
        w_light  = B_{s-1} (f_{s-1} H_{s-1} + dVCM_{s-1} + dVC_{s-1} B_{s-2}) / nu_s^beta
                   (tr. 40; s = 1 next-event estimation, tr. 44; 0 for s = 0, tr. 42),
        w_camera = A_s (f_s H_s + dVCM^c_s + dVC^c_s A_{s+1}) / nu_s^beta
                   (tr. 41; s = 0 emitter hit, tr. 43; 0 for s = k light tracing, tr. 47;
                   light tracing's own N_light^beta is the 1/N of tr. 46),
    merging at x_s:
        w_light  = dVCM_s / H_s + dVM_s B_{s-1}                                    (tr. 38)
        w_camera = dVCM^c_s / H_s + dVM^c_s A_{s+1}                                (tr. 39)

Rules carried by the enable factors
-----------------------------------
Delta vertices never join: e_j = 0 if x_{j-1} (j >= 2) or x_j (j <= k-1) is delta,
f_i = 0 at a delta x_i; this is the tech report's dVCM <- 0 after a specular scatter
(tr. 53-55: the next connection technique is e = 0) and its dropping of the dVCM and eta
terms at the specular vertex itself. A delta light has e_0 = 0 (tr. 48-50: dVC = 0 at the
light); an infinite light cannot be joined to the pinhole for k = 1 (e_1 = 0). The
algorithm masks are per-technique enable factors, since the tech report's two global
switches (mUseVC / mUseVM: all e or all f zero) express only bdpt, bpm and vcm:
    pt   e_j = 1 for j = 0 and for j = 1 with k >= 2 (emitter hits and NEE), f = 0;
    lt   e_k only (light tracing), f = 0;
    bdpt all e, f = 0;          vcm  all e, all f;
    bpm  e_0 only, all f;
    ppm  f only at the largest non-delta interior index (the first non-delta vertex seen
         from the camera), e_0 only when there is no non-delta interior vertex.
Merging needs 1 <= i <= k-1. Zero pdfs need no factor: a technique whose p is 0 has a
zero factor in its product of ratios relative to the own technique s, and the
quantities read for s only divide by a_i, i < s, and b_i, i >= s, which are all positive
when s itself is possible; the own technique is checked explicitly (weight 0 when
impossible). Reciprocals of zero pdfs are taken as 0, and a product with an exactly zero
pdf or enable factor is exactly 0 even when the other factor has overflowed, so that
parts of the scans that no possible technique reads stay finite (unguarded, such
products turn into NaN on rare float32 paths).

Range
-----
The quantities are sums of products of pdf ratios in linear space, and a stored
quantity can exceed the ratio it finally contributes by the product of the ratios along
a run of the path (dVC_i is divided by B_{i-1} A_i until the join multiplies those back),
so an intermediate overflows (weight 0) or underflows (term lost) while the true weight
is moderate. The explicit sums (`_full`, `_explicit`) work in log space and have no such
limit. The two forms agree while the pdfs stay within a few orders of magnitude of one
in float32 (further in float64); beyond that a share of paths gets a wrong (zero or
unnormalised) weight, never a non-finite one. docs/design/mis.md ("Range") gives the
failure rates against the explicit sums; the MIS tests (tests/mis/test_mis_recursive.py)
keep float32 at pdfs 10^+-2 and radii 1e-3..10 and show a concrete overflowing path.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._config import TECHNIQUES
from ._base import AbstractMIS


def _recip(x):
    """1/x, and 0 for x = 0 (an impossible technique contributes nothing)."""
    pos = x > 0
    return jnp.where(pos, 1.0 / jnp.where(pos, x, 1.0), 0.0)


def _times(x, p):
    """x p, exactly 0 when the factor p is 0 (a zero pdf or a disabled technique), also
    when x has overflowed: the product of ratios of an impossible technique is 0."""
    return jnp.where(p > 0, x * p, 0.0)


def enable_factors(algorithm: str, delta, k, delta_light, infinite_light):
    """(e [L+1], f [L]) in {0, 1}: connection technique j and merging at x_i are enabled
    by the path's delta vertices, the light and the algorithm (pdfs not considered)."""
    L = delta.shape[0]
    j = jnp.arange(L + 1, dtype=jnp.int32)
    i = jnp.arange(L, dtype=jnp.int32)
    d = delta & (i <= k)
    d_left = jnp.concatenate([jnp.zeros((1,), bool), d])  # x_{j-1}
    d_right = jnp.concatenate([d, jnp.zeros((1,), bool)])  # x_j
    e = jnp.where(j == 0, ~delta_light,
                  ~((j >= 2) & d_left) & ~((j <= k - 1) & d_right) & (j <= k))
    e = e & ~((j == 1) & (k == 1) & infinite_light)
    interior_nd = ~d & (i >= 1) & (i <= k - 1)  # non-delta vertices that can merge
    tech = TECHNIQUES[algorithm]
    e = e & tech.connection_mask(j, k)
    f = interior_nd
    if tech.merging == "first":
        last = jnp.max(jnp.where(interior_nd, i, 0))  # first non-delta vertex from the camera
        f = f & (i == last)
        e = e & (last == 0)  # emitter hits only through a purely delta camera prefix
    if tech.merging is None:
        f = jnp.zeros_like(f)
    return e, f


def mis_weight_recursive(a: Float[Array, "L"], b: Float[Array, "L"], delta: Bool[Array, "L"],
                         k: Int[Array, ""], s: Int[Array, ""], delta_light: Bool[Array, ""],
                         infinite_light: Bool[Array, ""], log_n_lt: Float[Array, ""],
                         algorithm: str = "bdpt", beta: float = 1.0,
                         log_eta: Float[Array, "L"] | None = None,
                         merge=False) -> Float[Array, ""]:
    """The MIS weight of technique s of a full path x_0..x_k, by the recursive form.

    The dVCM / dVC / dVM recursion of Georgiev's tech report run over the assembled path;
    entries i > k are ignored; arguments and result as `mis_weight`."""
    L = a.shape[0]
    dt = a.dtype
    k = jnp.asarray(k, jnp.int32)
    s = jnp.asarray(s, jnp.int32)
    i = jnp.arange(L, dtype=jnp.int32)
    in_path = i <= k
    merging = TECHNIQUES[algorithm].merging is not None
    if merging and log_eta is None:
        raise ValueError("log_eta: required for the merging algorithms")
    beta = jnp.asarray(beta, dt)
    a = jnp.where(in_path, a, 1.0)
    b = jnp.where(in_path, b, 1.0)
    # ---- Mis(.) of every factor ----
    A = jnp.power(a, beta)
    B = jnp.power(b, beta)
    H = jnp.exp(beta * jnp.asarray(log_eta, dt)) if merging else jnp.ones((L,), dt)
    H = jnp.where(in_path, H, 1.0)
    e, f = enable_factors(algorithm, delta, k, delta_light, infinite_light)
    jj = jnp.arange(L + 1, dtype=jnp.int32)
    nu = jnp.where(jj == k, jnp.exp(beta * jnp.asarray(log_n_lt, dt)), 1.0).astype(dt)
    E = e.astype(dt) * nu  # E_j, j = 0..L
    F = f.astype(dt)  # f_i, i = 0..L-1
    zero, one = jnp.zeros((1,), dt), jnp.ones((1,), dt)

    # ---- light subpath x_0, x_1, ...: (tr. 31-36) in area measure ----
    def light_step(carry, x):
        dvcm, dvc, dvm = carry  # at x_{i-1}
        A_i, B_im2, H_im1, H_i, F_im1, E_i = x
        inv = _recip(A_i)
        dvc_n = _times(_times(H_im1, F_im1) + dvcm + _times(dvc, B_im2), inv)
        dvm_n = _times((H_im1 / H_i) * (F_im1 + dvcm / H_im1 + _times(dvm, B_im2)), inv)
        dvcm_n = _times(E_i, inv)
        out = (dvcm_n, dvc_n, dvm_n)
        return out, out

    sh = lambda v, n, fill: jnp.concatenate([jnp.full((n,), fill, dt), v[: L - n]])  # noqa: E731
    xs_l = (A, sh(B, 2, 0.0), sh(H, 1, 1.0), H, sh(F, 1, 0.0), E[:L])
    z0 = (jnp.zeros((), dt),) * 3
    _, (l_vcm, l_vc, l_vm) = jax.lax.scan(light_step, z0, xs_l)

    # ---- camera subpath x_k, x_{k-1}, ...: mirrored, starting at the pinhole ----
    def camera_step(carry, x):
        dvcm, dvc, dvm = carry  # at x_{i+1}
        B_i, A_ip2, H_ip1, H_i, F_ip1, E_ip1, started = x
        inv = _recip(B_i)
        dvc_n = _times(_times(H_ip1, F_ip1) + dvcm + _times(dvc, A_ip2), inv)
        dvm_n = _times((H_ip1 / H_i) * (F_ip1 + dvcm / H_ip1 + _times(dvm, A_ip2)), inv)
        dvcm_n = _times(E_ip1, inv)
        out = tuple(jnp.where(started, v, 0.0) for v in (dvcm_n, dvc_n, dvm_n))
        return out, out

    up = lambda v, n, fill: jnp.concatenate([v[n:], jnp.full((n,), fill, dt)])  # noqa: E731
    xs_c = (B, up(A, 2, 0.0), up(H, 1, 1.0), H, up(F, 1, 0.0), E[1:], in_path)
    _, (c_vcm, c_vc, c_vm) = jax.lax.scan(camera_step, z0, xs_c, reverse=True)

    # ---- join ----
    Ap = jnp.concatenate([A, zero, zero])  # A_{L}, A_{L+1}: beyond any path
    Bp = jnp.concatenate([one, B])  # Bp[i + 1] = B_i, Bp[0]: B_{-1}, never used (dVC_0 = 0)
    Hp = jnp.concatenate([H, one])
    Fp = jnp.concatenate([F, zero])
    at = lambda v, idx: v[jnp.clip(idx, 0, v.shape[0] - 1)]  # noqa: E731
    pad = lambda v: jnp.concatenate([v, zero])  # noqa: E731
    sl = jnp.maximum(s - 1, 0)  # the light subpath's last vertex x_{s-1}
    # connection s (tr. 40/41; 42-47 are its special cases s = 0, 1, k)
    wl_vc = _times(_times(at(Hp, sl), at(Fp, sl)) + at(pad(l_vcm), sl)
                   + _times(at(pad(l_vc), sl), at(Bp, sl)), at(Bp, sl + 1))
    wl_vc = jnp.where(s >= 1, wl_vc, 0.0)
    wc_vc = _times(_times(at(Hp, s), at(Fp, s)) + at(pad(c_vcm), s)
                   + _times(at(pad(c_vc), s), at(Ap, s + 1)), at(Ap, s))
    wc_vc = jnp.where(s <= k, wc_vc, 0.0)
    nu_s = at(nu, s)
    w_vc = 1.0 / (wl_vc / nu_s + 1.0 + wc_vc / nu_s)  # (tr. 37)
    # own technique possible: enabled and all its pdfs positive
    pos_a = jnp.all(jnp.where(i < s, a > 0, True))
    pos_b = jnp.all(jnp.where((i >= s) & in_path, b > 0, True))
    ok_vc = at(e, s) & (s <= k) & pos_a & pos_b
    w, ok = w_vc, ok_vc
    if merging:
        # merging at x_s (tr. 38/39)
        H_s = at(Hp, s)
        wl_vm = at(pad(l_vcm), s) / H_s + _times(at(pad(l_vm), s), at(Bp, s))
        wc_vm = at(pad(c_vcm), s) / H_s + _times(at(pad(c_vm), s), at(Ap, s + 1))
        w_vm = 1.0 / (wl_vm + 1.0 + wc_vm)  # (tr. 37)
        ok_vm = (at(Fp, s) > 0) & (at(pad(a), s) > 0) & pos_a & pos_b
        w = jnp.where(merge, w_vm, w)
        ok = jnp.where(merge, ok_vm, ok)
    return jnp.where(ok, w, 0.0)


# ==================================================================================
# The recursion carried along the subpaths as they are traced (SmallVCM's way)
# ==================================================================================
# `mis_weight_recursive` above runs the recursion over an assembled full path per
# technique. The renderer's recursive form instead carries dVCM / dVC / dVM with each
# subpath while it is traced (`_subpath.step` calls `carry_step` with the pdfs it has just
# computed, before they are stored), records them per vertex, and evaluates each
# technique's weight at its join from the two records next to it (tr. 37-47): O(1) per
# vertex while tracing, O(1) per technique. It reads none of the stored pdf records, so
# an image rendered with it checks the records that the explicit sums (`_explicit`)
# are built from (and the queue's shifting of the reverse pdfs), not only the algebra.
#
# Russian roulette by index. A vertex's survival probability counts from whichever end
# generates the next vertex, so the reverse pdf b_m of a light vertex carries q_{m+1} iff
# the path has rr_depth or more segments between x_{m+1} and the camera: it depends on
# the camera side's length t, known only at the join. Only the last few stored factors can
# lack it: with z = clip(rr_depth - t - 1, 0, Z) (connections; merging: rr_depth - t), the
# z most recent reverse factors in dVC_{s-1} / dVM_{s-1} are without roulette and all the
# earlier ones with it. The recursion therefore carries one (dVC, dVM) per z = 0..Z, and a
# step shifts them: state_z(i) = update(state_{z-1}(i-1), b_{i-2} without q) for z >= 1,
# state_0(i) = update(state_0(i-1), b_{i-2} q_{i-1}). The camera side mirrors it with the
# light side's length s. The own-direction pdf (a_i on the light side) carries its own
# roulette, whose index is known while tracing.

class Carry(NamedTuple):
    """What a subpath carries from the vertex its ray left (per lane).

    rec:    [2 + 2V] that vertex's record: dVCM, 1 / Mis(local pdf), dVC[V], dVM[V];
    zero:   a zero local pdf at or before that vertex (the techniques through it are
            impossible);
    F:      merging at that vertex is enabled (0 / 1);
    leta:   log(kernel N) at that vertex;
    rev:    the reverse pdf of the vertex before it (computed when the ray left), RR-free;
    q_rev:  that reverse pdf's roulette factor: the local survival q of the vertex left;
    q_cont: the survival probability the subpath applied when it left the vertex.
    """

    rec: Array
    zero: Array
    F: Array
    leta: Array
    rev: Array
    q_rev: Array
    q_cont: Array


class Record(NamedTuple):
    """The carried quantities recorded at a vertex: rec [..., 2 + 2V] and zero."""

    rec: Array
    zero: Array


class Context(NamedTuple):
    """Per pass, the same for every lane: log(kernel N) on surfaces and in the medium, and
    log of light tracing's multiplicity (`_path.log_n_light_tracing`)."""

    leta_surf: Array
    leta_med: Array
    log_n_lt: Array


def n_variants(cfg) -> int:
    """V = Z + 1 roulette variants, Z = min(rr_depth - 1, max_depth + 1): no subpath holds
    more reverse factors than a full path has vertices."""
    return min(cfg.rr_depth - 1, cfg.max_depth + 1) + 1


def _beta(cfg) -> float:
    return 2.0 if cfg.mis == "power" else 1.0


def _mis(x, beta: float):
    """Mis(x) = x^beta (tr. "Mis"): x x for the power heuristic."""
    return x * x if beta == 2.0 else x


def _rec(dvcm, inv, dvc, dvm):
    return jnp.concatenate([dvcm[..., None], inv[..., None], dvc, dvm], axis=-1)


def start_carry(cfg, A0, E0, leta0, dtype) -> Carry:
    """The carry at a subpath's start vertex (x_0 of a light subpath: A0 its area pdf, E0 =
    the emitter hit is enabled, tr. 31-33; the pinhole z_0: E0 = False, A0 = 1, since the
    pinhole is never hit). Elementwise over lanes."""
    V = n_variants(cfg)
    A0 = jnp.asarray(A0, dtype)
    inv = _recip(_mis(A0, _beta(cfg)))
    zeros = jnp.zeros(A0.shape + (V,), dtype)
    one = jnp.ones(A0.shape, dtype)
    dvcm = _times(jnp.asarray(E0, dtype) * one, inv)
    return Carry(_rec(dvcm, inv, zeros, zeros), ~(A0 > 0), jnp.zeros(A0.shape, dtype),
                 jnp.broadcast_to(jnp.asarray(leta0, dtype), A0.shape), one, one, one)


def carry_step(cfg, c: Carry, ctx: Context, camera, index, pdf_fwd, rev, q_loc, q_next,
               delta, medium, prev_delta) -> tuple[Carry, Record]:
    """One vertex of a subpath (one lane), from what `_subpath.step` has just computed:
    pdf_fwd its own-direction pdf (area / volume, RR-free, Diracs as 1), rev the reverse
    pdf of the vertex the ray left, q_loc its local survival, q_next the survival the
    subpath applies when it continues, delta / medium its flags, prev_delta the left
    vertex's; `camera`: a camera subpath (bool, possibly traced); index + 1 the vertex's
    position along the subpath. The update of (tr. 34-36) followed by the completion on
    arrival, in area measure (module doc: dVC_i = (f H + dVCM + dVC b) / a_i)."""
    tech = cfg.techniques
    beta = _beta(cfg)
    V = n_variants(cfg)
    dt = pdf_fwd.dtype
    i = index + 1
    dvcm_p, inv_p, dvc_p, dvm_p = c.rec[0], c.rec[1], c.rec[2:2 + V], c.rec[2 + V:]
    # ---- the new vertex's local pdf (own roulette, known while tracing) ----
    a = pdf_fwd * c.q_cont
    inv = _recip(_mis(a, beta))
    # ---- the left vertex's predecessor's reverse pdf: with / without its roulette ----
    b_q = _mis(c.rev * c.q_rev, beta)
    b_1 = _mis(c.rev, beta)
    Bf = jnp.concatenate([b_q[None], jnp.broadcast_to(b_1, (V - 1,))])
    src_vc = jnp.concatenate([dvc_p[:1], dvc_p[:V - 1]])  # variant z reads z - 1 (z >= 1)
    src_vm = jnp.concatenate([dvm_p[:1], dvm_p[:V - 1]])
    H_p = jnp.exp(beta * c.leta)
    leta = jnp.where(medium, ctx.leta_med, ctx.leta_surf).astype(dt)
    H = jnp.exp(beta * leta)
    # ---- the techniques that start at the new vertex ----
    # light x_i: connection i (x_{i-1} - x_i; i = 1 next-event estimation); camera z_c:
    # connection k - c + 1 (z_c - z_{c-1}; c = 1 light tracing, multiplicity N)
    first = i == 1
    on = jnp.where(first, jnp.where(camera, tech.light_tracing, tech.nee), tech.connections)
    E = (on & ~delta & (first | ~prev_delta)).astype(dt)
    E = E * jnp.where(camera & first, jnp.exp(beta * ctx.log_n_lt), 1.0).astype(dt)
    F = (jnp.asarray(tech.merging == "all") & ~delta).astype(dt)
    # ---- tr. 34-36 and the completion on arrival ----
    dvc = _times(_times(H_p, c.F) + dvcm_p + _times(src_vc, Bf), inv)
    dvm = _times((H_p / H) * (c.F + dvcm_p / H_p + _times(src_vm, Bf)), inv)
    dvcm = _times(E, inv)
    zero = c.zero | ~(a > 0)
    rec = _rec(dvcm, inv, dvc, dvm)
    return Carry(rec, zero, F, leta, rev, q_loc, q_next), Record(rec, zero)


class Carried(NamedTuple):
    """One subpath's carried records with what a join reads besides them, per lane:
    rec [2 + 2V, M, *lanes] (the record's fields first), zero, F, leta, q, delta [M, *lanes]."""

    rec: Array
    zero: Array
    F: Array
    leta: Array
    q: Array
    delta: Array


def carried(cfg, rec, zero, q, delta, medium, etas=(0.0, 0.0)) -> Carried:
    """`Carried` from a subpath's records with its start vertex (`_subpath.PathEnds.mis`:
    rec [M, *lanes, 2 + 2V], zero [M, *lanes]) and its flags [M, *lanes]."""
    M = q.shape[0]
    dt = rec.dtype
    i = np.arange(M).reshape((M,) + (1,) * (q.ndim - 1))
    F = (jnp.asarray(cfg.techniques.merging == "all") & ~delta & (i >= 1)).astype(dt)
    leta = jnp.where(medium, etas[1], etas[0]).astype(dt)
    return Carried(jnp.moveaxis(rec, -1, 0), zero, F, leta, q, delta)


def lone_start(cfg, lanes, dtype) -> Carried:
    """`Carried` of a subpath that is only its start vertex z_0, the pinhole (light tracing's
    camera side): [.., 1, *lanes]."""
    c = start_carry(cfg, jnp.ones((1,) + lanes, dtype), False, 0.0, dtype)
    f = jnp.zeros((1,) + lanes, bool)
    return Carried(jnp.moveaxis(c.rec, -1, 0), c.zero, c.F, c.leta, jnp.ones((1,) + lanes, dtype), f)


class Entries(NamedTuple):
    """What a technique reads from one side: the vertex next to the join (its record, with
    the roulette variant chosen, and flags) and the delta flag of the one before it."""

    ok: Array
    dvcm: Array
    inv: Array
    dvc: Array
    dvm: Array
    F: Array
    leta: Array
    q: Array
    delta: Array
    delta2: Array
    zero: Array


def entries(cfg, P: Carried, n, other, index=(), merge=False) -> Entries:
    """The entries of a side with n vertices in the technique (light: s, camera: t) whose
    other side has `other` vertices (indices static numpy, traced, or mixed; `index`: the
    fields' trailing-axis indices, e.g. the lane). The roulette variant: z = rr_depth -
    other - 1 reverse factors without roulette (`merge`: rr_depth - other, the photon one
    vertex further along its subpath than a connection's end)."""
    M = P.q.shape[0]
    V = n_variants(cfg)
    xp = np if isinstance(n, (int, np.ndarray)) and isinstance(other, (int, np.ndarray)) else jnp
    i1, i2 = n - 1, n - 2
    ic1, ic2 = xp.clip(i1, 0, M - 1), xp.clip(i2, 0, M - 1)
    ok = (i1 >= 0) & (i1 < M)
    z = xp.clip(cfg.rr_depth - other - (0 if merge else 1), 0, V - 1)
    lead = P.q[(ic1,) + index].ndim - np.ndim(ok)
    okb = ok.reshape(np.shape(ok) + (1,) * lead)
    g = lambda a, ic: a[(ic,) + index]  # noqa: E731
    r = lambda col: P.rec[(col, ic1) + index]  # noqa: E731
    d2 = g(P.delta, ic2) & ((i2 >= 0) & (i2 < M)).reshape(np.shape(ok) + (1,) * lead)
    return Entries(okb, r(0), r(1), r(2 + z), r(2 + V + z), g(P.F, ic1), g(P.leta, ic1),
                   g(P.q, ic1), g(P.delta, ic1) & okb, d2, g(P.zero, ic1) & okb)


def start_entries(cfg, A0, delta_light, leta0=0.0) -> Entries:
    """The light side of a technique whose light subpath is the lone fresh light sample y_0
    (next-event estimation): dVCM_0 = E_0 / Mis(a_0), no other technique starts before it
    (tr. 31-33, 44). Elementwise in A0, delta_light."""
    A0 = jnp.asarray(A0)
    dt = A0.dtype
    E0 = jnp.asarray(cfg.techniques.emitter_hits) & ~jnp.asarray(delta_light)
    c = start_carry(cfg, A0, E0, leta0, dt)
    f = jnp.zeros(A0.shape, bool)
    zero = jnp.zeros(A0.shape, dt)
    return Entries(~f, c.rec[..., 0], c.rec[..., 1], zero, zero, zero, c.leta, jnp.ones_like(A0),
                   f, f, c.zero)


def join_weight(cfg, s, t, L: Carried, C: Carried, A_s, A_s1, B_s1, B_s2, delta_light,
                infinite_light, log_n_lt, merge=False, lanes=((), ())):
    """MIS weight of technique (s, t) (or merging at x_s = z_{t-1}: the photon is y_s) from
    the two subpaths' carried records and the four pdfs the join re-evaluates; the same
    signature as `ExplicitMIS.join_weight` (A_s, the photon's pdf for a merge, is then
    already in the photon's record)."""
    if merge:
        Le = entries(cfg, L, s + 1, t, lanes[0], merge=True)
    else:
        Le = entries(cfg, L, s, t, lanes[0])
    return join(cfg, s, t, Le, entries(cfg, C, t, s, lanes[1]), A_s, A_s1, B_s1, B_s2,
                delta_light, infinite_light, log_n_lt, merge)


def join(cfg, s, t, Le: Entries, Ce: Entries, A_s, A_s1, B_s1, B_s2, delta_light,
         infinite_light, log_n_lt, merge=False):
    """`join_weight` from the entries of both sides (Le: y_{s-1}, or the photon y_s for a
    merge; Ce: z_{t-1}); elementwise, any batch shape."""
    tech = cfg.techniques
    beta = _beta(cfg)
    R = cfg.rr_depth
    k = s + t - 1
    dt = Ce.dvcm.dtype
    rr = lambda index, q: jnp.where(index >= R, q, 1.0)  # noqa: E731
    q_y = jnp.where(Le.ok, Le.q, 1.0)  # y_{s-1} (connections)
    q_z = Ce.q  # z_{t-1}
    # ---- the re-evaluated pdfs, with the roulette of the direction that generates them ----
    Bs1 = _mis(B_s1 * rr(t - 1, q_z), beta)  # y_{s-1} from z_{t-1}
    Bs2 = _mis(B_s2 * rr(t, q_y), beta)  # y_{s-2} through y_{s-1}
    As = _mis(A_s * jnp.where(s >= 1, rr(s - 1, q_y), 1.0), beta)  # z_{t-1} from y_{s-1}
    As1 = _mis(jnp.where(t >= 3, A_s1, 1.0) * rr(s, q_z), beta)  # z_{t-2} through z_{t-1}
    H_c = jnp.exp(beta * Ce.leta)
    nu_lt = jnp.exp(beta * jnp.asarray(log_n_lt, dt))
    # connection s + 1 (x_s - x_{s+1}) is in z_{t-1}'s dVCM, except for s = 0, where x_s is
    # the light vertex: next-event estimation, or light tracing if k = 1 (multiplicity N)
    E_s1 = jnp.where(k == 1, tech.light_tracing & ~infinite_light, tech.nee & ~Ce.delta2)
    dvcm_c = jnp.where(s == 0, _times(E_s1.astype(dt) * jnp.where(t == 2, nu_lt, 1.0), Ce.inv),
                       Ce.dvcm)
    F_c = jnp.where(s >= 1, Ce.F, 0.0)  # no merging at the light vertex x_0
    positive = ~Le.zero & ~Ce.zero
    if merge:
        # ---- merging at x_s (tr. 38/39) ----
        H_p = jnp.exp(beta * Le.leta)
        wl = Le.dvcm / H_p + _times(Le.dvm, Bs1)
        wc = dvcm_c / H_c + _times(Ce.dvm, As1)
        w = 1.0 / (wl + 1.0 + wc)  # (tr. 37)
        ok = (F_c > 0) & ~Ce.delta & positive & (t >= 2) & Le.ok
        return jnp.where(ok, w, jnp.zeros((), dt))
    # ---- connection s (tr. 40/41; 42-47 its special cases s = 0, 1, t = 1) ----
    H_l = jnp.exp(beta * Le.leta)
    wl = _times(_times(H_l, Le.F) + Le.dvcm + _times(Le.dvc, Bs2), Bs1)
    wl = jnp.where((s >= 1) & Le.ok, wl, 0.0)  # tr. 42: no light vertex
    wc = _times(_times(H_c, F_c) + dvcm_c + _times(Ce.dvc, As1), As)  # tr. 47: 0 at z_0
    nu = jnp.where(t == 1, nu_lt, 1.0)  # light tracing's own multiplicity (tr. 46)
    w = 1.0 / (wl / nu + 1.0 + wc / nu)  # (tr. 37)
    conn = jnp.where(s == 0, tech.emitter_hits & ~delta_light,
                     jnp.where(t == 1, tech.light_tracing & ((s == 1) | ~Le.delta)
                               & ~((k == 1) & infinite_light),
                               jnp.where(s == 1, tech.nee & ~Ce.delta,
                                         tech.connections & ~Le.delta & ~Ce.delta)))
    return jnp.where(conn & positive, w, jnp.zeros((), dt))


# ---------------------------------------------------------------- the form
def _sg(x):
    return jax.lax.stop_gradient(x)


class RecursiveMIS(AbstractMIS):
    """dVCM / dVC / dVM carried along each subpath as it is traced (`carry_step`, called by
    the tracer with `trace_context`) and joined per technique (`join`)."""

    def trace_context(self, cfg, etas, log_n_lt, dtype):
        return Context(jnp.asarray(etas[0], dtype), jnp.asarray(etas[1], dtype), log_n_lt)

    def camera_carry(self, cfg, n_paths, etas, dtype):
        # nothing starts at the pinhole z_0
        return start_carry(cfg, jnp.ones((n_paths,), dtype), False, etas[0], dtype)

    def light_carry(self, cfg, emission, etas, dtype):
        # y_0: the emitter hit starts there (tr. 31-33)
        return start_carry(cfg, _sg(emission.pdf_pos),
                           cfg.techniques.emitter_hits & ~emission.delta, etas[0], dtype)

    def subpaths(self, cfg, lends, cends, delta_light, log_n_lt, etas, light_mnee=None):
        if light_mnee is not None:  # refused by RenderConfig (manifold_nee needs "explicit")
            raise ValueError("config.manifold_nee: needs mis_form 'explicit'")

        def one(e):
            return None if e is None else carried(cfg, _sg(e.mis.rec), e.mis.zero, _sg(e.q),
                                                  e.delta, e.medium, _sg(etas))
        return one(lends), one(cends)

    def empty_light(self, cfg, dtype, etas):
        return lone_start(cfg, (1,), dtype)

    def pinhole(self, cfg, log_n_lt, dtype, etas):
        return lone_start(cfg, (1,), dtype)

    # the per-technique functions of this module, as the interface's methods
    entries = staticmethod(entries)
    start_entries = staticmethod(start_entries)
    join = staticmethod(join)
    join_weight = staticmethod(join_weight)
