"""Hash grid (vertex merging lookups): exact radius queries against a brute-force oracle.

The oracle is an O(Q M) NumPy search: for every query the valid points with
(dx*dx + dy*dy) + dz*dz <= r*r, dx = p - q, in float64 from the very numbers given to the
grid (float32 coordinates convert exactly). The grid evaluates the same inclusive test in
float64 (x64 is on in the tests), so the expected neighbour sets are equal as sets, with
no tolerance: a miss, an extra point, a point counted twice (two cells of a query's
2x2x2 block sharing a bucket) or a collision not filtered out all fail. Boundary sets use
dyadic coordinates for which every operation is exact, so points at distance exactly r
are in (inclusive test) and the next float32 outwards is out.

Shapes are kept to a few (M = 2048 point slots, Q = 256 queries) so that the suite
compiles few programs; smaller sets are padded with invalid points / NaN queries (a NaN
query has no neighbours, in the oracle too).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxvcm import _hashgrid as HG

from .. import _hashgrid_oracles as HO

M_SLOTS = 2048
Q_SLOTS = 256
K = 64

build = jax.jit(HG.build, static_argnames=("table_size", "dtype"))
query = jax.jit(HO.query, static_argnames=("max_neighbours", "chunk", "sort_queries"))
reduce_ = jax.jit(HG.query_reduce,
                  static_argnames=("fn", "max_candidates", "chunk", "sort_queries",
                                   "return_need"))


# ------------------------------------------------------------------------------ oracle
def brute(P, V, Q, r):
    """[Q] list of sorted index arrays of the valid points within r (inclusive), float64."""
    p = np.asarray(P).astype(np.float64)
    q = np.asarray(Q).astype(np.float64)
    r = np.float64(r)
    dx, dy, dz = (p[a][None, :] - q[a][:, None] for a in range(3))
    with np.errstate(invalid="ignore"):
        inside = (dx * dx + dy * dy + dz * dz <= r * r) & np.asarray(V, bool)[None, :]
    return [np.flatnonzero(row) for row in inside]


def check(idx, count, overflow, ref, k):
    """Grid result == oracle sets; rows past the count padded with -1; overflow flag."""
    idx, count = np.asarray(idx), np.asarray(count)
    assert idx.shape == (len(ref), k) and count.shape == (len(ref),)
    for i, want in enumerate(ref):
        assert count[i] == len(want), (i, count[i], len(want))
        got = idx[i, : min(count[i], k)]
        assert len(np.unique(got)) == len(got), f"query {i}: a point returned twice"
        assert np.all(idx[i, len(got):] == -1)
        if count[i] <= k:
            np.testing.assert_array_equal(np.sort(got), want)
        else:  # capacity exceeded: K distinct true neighbours
            assert np.isin(got, want).all()
    assert bool(overflow) == any(len(w) > k for w in ref)


def pad_points(P, V, m=M_SLOTS):
    n = P.shape[1]
    P = np.concatenate([P, np.full((3, m - n), 7.0, P.dtype)], axis=1)  # far junk, invalid
    return P, np.concatenate([V, np.zeros(m - n, bool)])


def pad_queries(Q, n=Q_SLOTS):
    return np.concatenate([Q, np.full((3, n - Q.shape[1]), np.nan, Q.dtype)], axis=1)


def run_case(P, V, Q, r, *, table_size, k=K):
    grid = build(*P, V, r, table_size=table_size)
    assert bool(grid.precise)
    assert int(grid.num_valid) == int(np.sum(V & np.isfinite(P).all(0)))
    idx, count, overflow = query(grid, *Q, max_neighbours=k)
    ref = brute(P, V, Q, r)
    check(idx, count, overflow, ref, k)
    return grid, ref


# ---------------------------------------------------------------------------- data sets
def uniform(dt, seed=0):
    """2048 slots in [0,1]^3, 10% invalid; queries in [-0.05, 1.05]^3; r = 0.15: mean
    neighbour count ~ 0.9 * 2048 * (4/3) pi 0.15^3 ~ 26 inside the cube (K = 64 holds
    the max, ~50)."""
    rng = np.random.default_rng(seed)
    P = rng.random((3, M_SLOTS)).astype(dt)
    V = rng.random(M_SLOTS) < 0.9
    Q = (rng.random((3, Q_SLOTS)) * 1.1 - 0.05).astype(dt)
    return P, V, Q, dt(0.15)


def clustered(dt, seed=1):
    """Caustic-like: 2000 points in a ball of radius r/5 (all in one or two cells) plus 48
    uniform ones; half the queries within 1.5 r of the cluster centre, so counts reach
    2000 (via query_with_retry), half uniform."""
    rng = np.random.default_rng(seed)
    r = 0.05
    c = np.array([[0.41], [0.57], [0.33]])
    d = rng.normal(size=(3, 2000))
    d *= (0.2 * r) * rng.random(2000) ** (1 / 3) / np.linalg.norm(d, axis=0)
    P = np.concatenate([c + d, rng.random((3, M_SLOTS - 2000))], axis=1).astype(dt)
    e = rng.normal(size=(3, 128))
    e *= 1.5 * r * rng.random(128) / np.linalg.norm(e, axis=0)
    Q = np.concatenate([c + e, rng.random((3, 128))], axis=1).astype(dt)
    return P, np.ones(M_SLOTS, bool), Q, dt(r)


def boundary():
    """Dyadic float32 sets, all arithmetic exact. r = 7/64; 36 query centres on a 1/32
    lattice (so q - r falls on many phases of the cell grid); around each centre 54 points
    at distance exactly r (offsets (7,0,0)/64 and (2,3,6)/64 with all permutations and
    signs: 4 + 9 + 36 = 49 = 7^2) and the point c + (2,3,6)/64 with its z moved one float32
    ulp outwards (out) and one inwards (in). Expected (inclusive test): 55 per centre, plus
    points of other centres within r. The other 36 queries sit 1/64 off the centres."""
    r = np.float32(7 / 64)
    exact = set()
    for v in ((7, 0, 0), (2, 3, 6)):
        for p in itertools.permutations(v):
            for s in itertools.product((1, -1), repeat=3):
                exact.add(tuple(a * b for a, b in zip(p, s)))
    offs = np.array(sorted(exact), np.float32).T / np.float32(64)  # 6 + 48 = 54 offsets
    rng = np.random.default_rng(2)
    centres = (rng.integers(0, 33, (3, 36)) / 32).astype(np.float32)
    pts = centres[:, :, None] + offs[:, None, :]  # multiples of 1/64 below 2: exact
    assert np.array_equal(pts - centres[:, :, None], np.broadcast_to(offs[:, None, :], pts.shape))
    edge = centres + (np.array([2, 3, 6], np.float32) / np.float32(64))[:, None]
    out, inn = edge.copy(), edge.copy()
    out[2] = np.nextafter(edge[2], np.float32(np.inf))
    inn[2] = np.nextafter(edge[2], np.float32(-np.inf))
    P = np.concatenate([pts, out[:, :, None], inn[:, :, None]], axis=2).reshape(3, -1)
    P, V = pad_points(P, np.ones(P.shape[1], bool))  # 36 * 56 = 2016 points
    Q = pad_queries(np.concatenate([centres, centres + np.float32(1 / 64)], axis=1))
    return P, V, Q, r


def outside(dt):
    """Points in [0,1]^3; queries far outside the bounding box (count 0), just outside it
    (within r of its faces: counts > 0), at +-1e30 / inf / nan (count 0)."""
    rng = np.random.default_rng(3)
    P = rng.random((3, M_SLOTS)).astype(dt)
    r = 0.1
    near = np.concatenate([rng.random((3, 60)), rng.random((3, 60))], axis=1)
    near[0, :60] = -0.5 * r * rng.random(60)  # just below x = 0
    near[2, 60:] = 1 + 0.9 * r * rng.random(60)  # just above z = 1
    far = np.array([[10, -10, 0.5], [0.5, 1e6, 0.5], [1e30, -1e30, 1e30],
                    [np.inf, 0.5, 0.5], [-np.inf, -np.inf, 0.5], [np.nan, 0.5, 0.5],
                    [0.5, -3 * r, 0.5], [1 + 2.1 * r, 0.5, 0.5]], np.float64).T
    Q = pad_queries(np.concatenate([near, far], axis=1).astype(dt))
    return P, np.ones(M_SLOTS, bool), Q, dt(r)


DTYPES = [np.float32, np.float64]


# -------------------------------------------------------------------------------- tests
@pytest.mark.parametrize("table_size", [4096, 2039, 7, 1], ids=lambda t: f"T{t}")
@pytest.mark.parametrize("dt", DTYPES, ids=lambda d: np.dtype(d).name)
def test_uniform_exact(dt, table_size):
    # T = 7 or 1: the 8 cells of every block share buckets (T = 1: one bucket holding
    # every point), which must be visited once: counts equal the oracle's, no repeats.
    P, V, Q, r = uniform(dt)
    grid, ref = run_case(P, V, Q, r, table_size=table_size)
    assert np.mean([len(x) for x in ref]) > 10
    cand = np.asarray(HO.candidate_counts(grid, *Q))
    assert cand.max() <= V.sum()
    if table_size == 1:
        assert np.all(cand == V.sum())  # one bucket, visited once by every query


@pytest.mark.parametrize("dt", DTYPES, ids=lambda d: np.dtype(d).name)
def test_clustered_exact_with_retry(dt):
    P, V, Q, r = clustered(dt)
    grid = build(*P, V, r, table_size=4096)
    ref = brute(P, V, Q, r)
    assert max(len(x) for x in ref) >= 1900  # queries inside the cluster see all of it
    (idx, count, overflow), k = HO.query_with_retry(grid, *Q, max_neighbours=16)
    # counts are exact even on overflow, so one retry: K = 16 * 2^j >= max count (2048)
    assert k == 16 * 2 ** int(np.ceil(np.log2(max(len(x) for x in ref) / 16)))
    check(idx, count, overflow, ref, k)
    assert not bool(overflow)


def test_boundary_inclusive_exact():
    P, V, Q, r = boundary()
    _, ref = run_case(P, V, Q, r, table_size=M_SLOTS, k=128)
    counts = np.array([len(x) for x in ref[:36]])
    # each centre has its own 55 points at distance <= r (54 exactly r, 1 nudged in; the
    # nudged-out one excluded), plus those of other centres that happen to be within r
    assert np.all(counts >= 55)
    d = np.sqrt(((P[:, :56].astype(np.float64) - Q[:, :1]) ** 2).sum(0))
    assert np.sum(d == np.float64(r)) == 54 and np.sum(d > r) >= 1


@pytest.mark.parametrize("dt", DTYPES, ids=lambda d: np.dtype(d).name)
def test_queries_outside_bounding_box(dt):
    P, V, Q, r = outside(dt)
    _, ref = run_case(P, V, Q, r, table_size=4096)
    n = [len(x) for x in ref]
    assert sum(n[:120]) > 0 and all(x == 0 for x in n[120:])


@pytest.mark.parametrize("case", ["all_invalid", "no_slots", "nan_points"])
def test_empty_grids(case):
    rng = np.random.default_rng(4)
    P = rng.random((3, M_SLOTS)).astype(np.float32)
    V = np.zeros(M_SLOTS, bool)
    if case == "no_slots":
        P, V = P[:, :0], V[:0]
    if case == "nan_points":  # valid but non-finite: treated as invalid
        P[0] = np.nan
        V[:] = True
    Q = rng.random((3, Q_SLOTS)).astype(np.float32)
    grid = build(*P, V, np.float32(0.2), table_size=64)
    assert int(grid.num_valid) == 0
    idx, count, overflow = query(grid, *Q, max_neighbours=K)
    assert np.all(np.asarray(idx) == -1) and np.all(np.asarray(count) == 0)
    assert not bool(overflow)
    acc, overflow = reduce_(grid, *Q, lambda qi, pj, d2: d2)
    assert np.all(np.asarray(acc) == 0)


def test_forced_overflow_and_retry():
    P, V, Q, r = uniform(np.float32)
    grid = build(*P, V, r, table_size=4096)
    ref = brute(P, V, Q, r)
    idx, count, overflow = query(grid, *Q, max_neighbours=3)
    check(idx, count, overflow, ref, 3)  # true counts, 3 true neighbours each
    assert bool(overflow)
    (idx, count, overflow), k = HO.query_with_retry(grid, *Q, max_neighbours=3)
    assert k >= max(len(x) for x in ref) and k // 3 & (k // 3 - 1) == 0  # 3 * 2^j
    check(idx, count, overflow, ref, k)


@pytest.mark.parametrize("chunk, sort_queries", [(32, True), (100, False)],
                         ids=lambda v: f"chunk{v}" if not isinstance(v, bool) else
                         ("sorted" if v else "unsorted"))
def test_chunking_and_query_order_do_not_change_results(chunk, sort_queries):
    # 256 queries in chunks of 32 (exact) or 100 (padded with NaN queries), sorted by block
    # internally (results returned in the caller's order) or not; the other tests run the
    # default (one chunk of 256, sorted)
    P, V, Q, r = uniform(np.float32)
    grid = build(*P, V, r, table_size=4096)
    idx, count, overflow = query(grid, *Q, max_neighbours=K, chunk=chunk,
                                 sort_queries=sort_queries)
    check(idx, count, overflow, brute(P, V, Q, r), K)
    fn = lambda qi, pj, d2: (qi, jnp.ones_like(d2))  # noqa: E731
    (qsum, ones), _ = reduce_(grid, *Q, fn, chunk=chunk, sort_queries=sort_queries)
    np.testing.assert_array_equal(ones, count)
    np.testing.assert_array_equal(qsum, np.arange(Q_SLOTS) * np.asarray(count))  # qi = own index


def test_query_radius_smaller_than_build_radius():
    P, V, Q, r = uniform(np.float64)
    grid = build(*P, V, r, table_size=4096)
    idx, count, overflow = query(grid, *Q, 0.6 * r, max_neighbours=K)
    check(idx, count, overflow, brute(P, V, Q, 0.6 * r), K)


# ------------------------------------------------------------------------- query_reduce
def kernel_sums(P, V, Q, r, w):
    """Oracle of sum_j w_j (1 - d2/r^2) and of its gradient w.r.t. q (2 w_j (p_j - q)/r^2)."""
    p, q = np.asarray(P, np.float64), np.asarray(Q, np.float64)
    ref = brute(P, V, Q, r)
    r = np.float64(r)
    s = np.array([np.sum(w[j] * (1 - ((p[:, j] - q[:, [i]]) ** 2).sum(0) / r**2))
                  for i, j in enumerate(ref)])
    g = np.array([[np.sum(2 * w[j] * (p[a, j] - q[a, i]) / r**2) for a in range(3)]
                  for i, j in enumerate(ref)]).T
    return ref, s, g


@pytest.mark.parametrize("max_candidates", [None, "exact", "short"])
def test_query_reduce_sums_and_overflow(max_candidates):
    P, V, Q, r = uniform(np.float32)
    grid = build(*P, V, r, table_size=4096)
    w = np.random.default_rng(5).random(M_SLOTS)
    ref, s, _ = kernel_sums(P, V, Q, r, w)
    need = int(jnp.max(HO.candidate_counts(grid, *Q)))
    cap = {None: None, "exact": need, "short": need - 1}[max_candidates]
    wj = jnp.asarray(w)
    r2 = jnp.float64(r) ** 2
    fn = lambda qi, pj, d2: (wj[pj] * (1 - d2 / r2), jnp.ones_like(d2))  # noqa: E731
    (acc, ones), overflow = reduce_(grid, *Q, fn, max_candidates=cap)
    assert bool(overflow) == (max_candidates == "short")
    if max_candidates != "short":
        np.testing.assert_array_equal(ones, [len(x) for x in ref])
        np.testing.assert_allclose(acc, s, rtol=1e-12, atol=1e-12)
    else:  # the longest lists were cut short: counts are lower bounds
        assert np.all(np.asarray(ones) <= [len(x) for x in ref])
    # the room that would have been enough is reported whatever the capacity (the host
    # re-runs once with it): the longest candidate list of the oracle
    _, overflow2, reported = reduce_(grid, *Q, fn, max_candidates=cap, return_need=True)
    assert int(reported) == need and bool(overflow2) == bool(overflow)


def test_query_reduce_gradient():
    # d/dq sum_j w_j (1 - |p_j - q|^2 / r^2) = sum_j 2 w_j (p_j - q) / r^2, through the
    # static-length (fori_loop -> scan) reduction
    P, V, Q, r = uniform(np.float64)
    grid = build(*P, V, r, table_size=4096)
    w = np.random.default_rng(6).random(M_SLOTS)
    _, _, g_ref = kernel_sums(P, V, Q, r, w)
    cap = int(jnp.max(HO.candidate_counts(grid, *Q)))
    wj, r2 = jnp.asarray(w), jnp.float64(r) ** 2

    def total(qx, qy, qz):
        fn = lambda qi, pj, d2: wj[pj] * (1 - d2 / r2)  # noqa: E731
        return HG.query_reduce(grid, qx, qy, qz, fn, max_candidates=cap)[0].sum()

    g = jax.jit(jax.grad(total, argnums=(0, 1, 2)))(*(jnp.asarray(a) for a in Q))
    np.testing.assert_allclose(np.stack(g), g_ref, rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------------ building blocks
@pytest.mark.parametrize("key_bound", [64, 1 << 30, 1 << 62],
                         ids=lambda b: f"bound2^{b.bit_length() - 1}")
def test_sort_order_matches_stable_argsort(key_bound):
    # bounds 64 / 2^30 / 2^62 with 2048 keys: packed uint32 / packed uint64 / two-operand
    keys = np.random.default_rng(7).integers(0, min(key_bound, 50), 2048).astype(np.int32)
    got = jax.jit(HG.sort_order, static_argnums=1)(jnp.asarray(keys), key_bound)
    np.testing.assert_array_equal(got, np.argsort(keys, kind="stable"))


def test_precise_flag():
    # float32 grid: coordinates must stay within ~4096 cells of 0 (docs/design/merging.md)
    P = np.array([[0, 1], [0, 1], [0, 1]], np.float32)
    ok = build(*P, None, np.float32(0.01), table_size=8, dtype=jnp.float32)  # ~100 cells
    far = build(*P, None, np.float32(1e-5), table_size=8, dtype=jnp.float32)  # ~1e5 cells
    zero = build(*P, None, np.float32(0), table_size=8)
    f64 = build(*P, None, np.float32(1e-5), table_size=8)  # float64 grid: fine
    assert bool(ok.precise) and not bool(far.precise) and not bool(zero.precise)
    assert bool(f64.precise)


def test_block_holds_every_neighbour_under_float32_rounding():
    # The invariant behind exactness: for every p with |p - q| <= r the cell of p is the
    # lower corner of q's block or the next one, per axis. Adversarial float32 grid (the
    # coarsest rounding): q - r within a few ulps of a cell boundary (q = o + k c + r),
    # p = q +- r within a few ulps, 40 random (r, origin), 4M pairs, k up to 2000 cells.
    # With a cell of exactly 2r (CELL_MARGIN = SEARCH_MARGIN = 0) about 1 pair in 25000
    # fails this (SmallVCM's floor(q/c - 0.5) likewise); the margins make it 0.
    rng = np.random.default_rng(9)
    f32 = np.float32

    @jax.jit
    def cells(grid, qx, px):
        z = jnp.zeros_like(qx)
        lo = HG._lower_corner(grid, qx, z, z, grid.radius)[0]
        return lo, HG._cell(px, grid.origin[0], grid.inv_cell)

    bad = n_inside = 0
    for _ in range(40):
        r, o = f32(rng.uniform(0.005, 0.2)), f32(rng.uniform(-1, 1))
        grid = build(np.array([o, o + 1], f32), np.zeros(2, f32), np.zeros(2, f32), None, r,
                     table_size=2, dtype=jnp.float32)
        assert bool(grid.precise)
        c = 1 / np.float64(grid.inv_cell)
        k = rng.integers(0, 2000, 100_000)
        q = (np.float64(o) + k * c + np.float64(r)).astype(f32)
        q = q + (rng.integers(-8, 9, q.size) * np.spacing(q)).astype(f32)
        p = (q + rng.choice([-1, 1], q.size).astype(f32) * r).astype(f32)
        p = p + (rng.integers(-3, 4, p.size) * np.spacing(p)).astype(f32)
        inside = np.abs(p.astype(np.float64) - q.astype(np.float64)) <= np.float64(r)
        lo, pc = (np.asarray(a) for a in cells(grid, q, p))
        bad += int(np.sum(inside & ((pc < lo) | (pc > lo + 1))))
        n_inside += int(inside.sum())
    assert n_inside > 1_000_000 and bad == 0


# --------------------------------------------------------------------------- hypothesis
coord = st.one_of(st.integers(-8, 8).map(lambda i: i / 8),  # dyadic: exact ties with r
                  st.floats(-1.0, 1.0, width=32))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    pts=st.lists(st.tuples(coord, coord, coord, st.booleans()), max_size=40),
    qs=st.lists(st.tuples(coord, coord, coord), min_size=1, max_size=12),
    r=st.sampled_from([0.125, 0.25, 0.375, 0.5, 0.3]),
    table_size=st.sampled_from([1, 7, 64]),
    dt=st.sampled_from(DTYPES),
)
def test_property_matches_brute_force(pts, qs, r, table_size, dt):
    # fixed shapes (48 point slots, 12 queries): padding is invalid points / NaN queries
    P = np.full((3, 48), 5.0, dt)
    V = np.zeros(48, bool)
    for i, (x, y, z, v) in enumerate(pts):
        P[:, i], V[i] = (x, y, z), v
    Q = np.full((3, 12), np.nan, dt)
    for i, q in enumerate(qs):
        Q[:, i] = q
    grid = build(*P, V, dt(r), table_size=table_size)
    idx, count, overflow = query(grid, *Q, max_neighbours=48)
    check(idx, count, overflow, brute(P, V, Q, dt(r)), 48)


@pytest.mark.parametrize("chunk, sort_queries", [(32, True), (100, False), (256, True)],
                         ids=lambda v: f"chunk{v}" if not isinstance(v, bool) else
                         ("sorted" if v else "unsorted"))
def test_query_reduce_valid_mask_keeps_every_sum_bit_for_bit(chunk, sort_queries):
    # queries with valid False get zero sums without a look-up (a chunk of them only is
    # skipped: sorted, they are the last lanes); every other query's sum is bit for bit the
    # one of the unmasked reduction (a lane adds its own pairs in candidate order, so the
    # lanes' order, their chunks and the invalid neighbours change nothing)
    P, V, Q, r = uniform(np.float32)
    grid = build(*P, V, r, table_size=4096)
    rng = np.random.default_rng(8)
    wj = jnp.asarray(rng.random(M_SLOTS))
    r2 = jnp.float64(r) ** 2
    fn = lambda qi, pj, d2: (wj[pj] * (1 - d2 / r2), jnp.ones_like(d2))  # noqa: E731
    (ref, ones), _ = reduce_(grid, *Q, fn, sort_queries=False)
    assert np.sum(np.asarray(ones) > 0) > Q_SLOTS // 2
    for mask in (rng.random(Q_SLOTS) < 0.3, np.arange(Q_SLOTS) < 40, np.zeros(Q_SLOTS, bool)):
        (got, n), _ = reduce_(grid, *Q, fn, chunk=chunk, sort_queries=sort_queries,
                              valid=jnp.asarray(mask))
        got, n = np.asarray(got), np.asarray(n)
        np.testing.assert_array_equal(got[mask], np.asarray(ref)[mask])
        np.testing.assert_array_equal(n, np.where(mask, ones, 0))
        assert np.all(got[~mask] == 0)
