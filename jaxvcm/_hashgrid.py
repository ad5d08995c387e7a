"""Hashed uniform grid for the photon (light vertex) lookups of vertex merging.

Design (after SmallVCM's `HashGrid`, Davidovic & Georgiev, the reference code of VCM,
Georgiev et al. 2012): the cell size is (slightly more than) twice the merging radius r,
so the ball of radius r around a query q lies inside the 2x2x2 block of cells whose lower
corner is the cell of q - r; the integer cell coordinates are hashed (xor of products with
large primes, Teschner et al. 2003) into `table_size` buckets; the points are sorted by
bucket and every bucket is a contiguous range [bucket_start[b], bucket_start[b + 1]) of
the sorted arrays. A query visits the (up to 8) distinct buckets of its block, so a bucket
shared by two of its cells is visited once, and keeps the points at distance <= r: hash
collisions and the parts of the cells outside the ball are removed by the distance test.

JAX form (after jax-md's cell and neighbour lists): every shape is static. `build` sorts
M point slots (invalid slots go to the end and are never returned); `query_reduce` sums a
per-pair kernel over the neighbours of each query without materialising a [Q, K] neighbour
list. (The fixed-K neighbour list `query`, its host helper `query_with_retry` and
`candidate_counts`, used only by the tests and the grid benchmark, live in
tests/_hashgrid_oracles.py.)

Exactness. The inclusion test is `dx*dx + dy*dy + dz*dz <= r*r` (inclusive) evaluated in
the grid's dtype (float64 when x64 is enabled, whatever the input dtype: float32 inputs
convert exactly, so the test equals a float64 oracle on the same float32 numbers). Cell
coordinates use one monotone function floor((x - origin) / cell) for points and queries,
and the cell is 2 r (1 + 2**-7), so the per-axis interval [q - r', q + r'] (r' = r (1 +
2**-8) > r, covering any rounding of the test) is narrower than a cell by a margin that
absorbs the rounding of the cell coordinates: the 2x2x2 block provably holds every point
that passes the test, as long as `grid.precise` holds (coordinates within ~4000 cells of
0 in float32, ~2 10**12 cells in float64). See docs/design/merging.md.
"""

from __future__ import annotations

import itertools
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike

CELL_MARGIN = 2.0**-7  # cell = 2 r (1 + CELL_MARGIN)
SEARCH_MARGIN = 2.0**-8  # per-axis search half-width r (1 + SEARCH_MARGIN)
_PRIMES = (73856093, 19349663, 83492791)  # Teschner et al. 2003, as in SmallVCM
_MAX_CELL = float(2**30)  # cell coordinates are clipped to +-2**30 (int32-safe, +1 too)
DEFAULT_CHUNK = 4096


class HashGrid(NamedTuple):
    """Points sorted by hash bucket. M = number of point slots, T = table size (static).

    points:       [M, 4] rows (x, y, z, 0) in sorted order, input dtype (one 16-byte row
                  per gather for float32, rather than one gather from each of three [M]
                  arrays);
                  slots >= num_valid are the invalid points (never read by a query).
    order:        [M] int32, sorted slot -> index into the arrays given to `build`.
    bucket_start: [T + 1] int32; bucket b holds sorted slots [start[b], start[b + 1]),
                  start[T] = num_valid.
    origin:       [3] cell origin (minimum of the valid points), grid dtype.
    inv_cell:     scalar 1 / cell size, grid dtype.
    radius:       scalar build radius (queries must use a radius <= this), grid dtype.
    num_valid:    scalar int32.
    precise:      scalar bool: the coordinates are small enough (in cells) for the
                  rounding argument above; False also for a radius <= 0 or non-finite.
    """

    points: Array
    order: Array
    bucket_start: Array
    origin: Array
    inv_cell: Array
    radius: Array
    num_valid: Array
    precise: Array

    @property
    def table_size(self) -> int:
        return self.bucket_start.shape[0] - 1

    @property
    def dtype(self):
        return self.inv_cell.dtype


def default_dtype():
    """Grid dtype: float64 when x64 is enabled (exact test for float32 data), else float32."""
    return jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32


# ------------------------------------------------------------------------------ helpers
def _cell(x: Array, o: Array, inv: Array) -> Array:
    """Integer cell coordinate floor((x - o) * inv): monotone non-decreasing in x."""
    c = jnp.floor((x - o) * inv)
    # NaN (invalid points, masked by the callers) converts to an arbitrary cell
    return jnp.clip(c, -_MAX_CELL, _MAX_CELL).astype(jnp.int32)


def _hash(ix: Array, iy: Array, iz: Array, table_size: int) -> Array:
    """Bucket of cell (ix, iy, iz): xor of products with large primes, modulo T (uint32)."""
    h = ((ix.astype(jnp.uint32) * jnp.uint32(_PRIMES[0]))
         ^ (iy.astype(jnp.uint32) * jnp.uint32(_PRIMES[1]))
         ^ (iz.astype(jnp.uint32) * jnp.uint32(_PRIMES[2])))
    return (h % jnp.uint32(table_size)).astype(jnp.int32)


def _gather(a: Array, i: Array) -> Array:
    return a.at[i].get(mode="promise_in_bounds", wrap_negative_indices=False)


def sort_order(key: Array, key_bound: int) -> Array:
    """Permutation sorting `key` (int32 in [0, key_bound)) ascending, ties by index.

    The key and the slot index are packed into one unsigned integer (key << b | i) and
    sorted as a single operand, which the CPU backend sorts much faster than `jnp.argsort`
    or a two-operand `lax.sort((key, iota), num_keys=1)` (docs/design/merging.md). uint32
    when it fits, uint64 when x64 is enabled, else the two-operand sort.
    """
    m = key.shape[0]
    b = max(1, (m - 1).bit_length())
    kbits = max(1, (key_bound - 1).bit_length())
    if kbits + b <= 32 or (kbits + b <= 64 and jax.config.read("jax_enable_x64")):
        u = jnp.uint32 if kbits + b <= 32 else jnp.uint64
        packed = (key.astype(u) << u(b)) | lax.iota(u, m)
        return (lax.sort(packed) & u((1 << b) - 1)).astype(jnp.int32)
    return lax.sort((key, lax.iota(jnp.int32, m)), num_keys=1, is_stable=True)[1]


# -------------------------------------------------------------------------------- build
def build(px: ArrayLike, py: ArrayLike, pz: ArrayLike, valid: ArrayLike | None,
          radius: ArrayLike, *, table_size: int, dtype=None) -> HashGrid:
    """Hash grid of the points whose `valid` is True (None: all), for radius `radius`.

    `table_size` (static) is the number of buckets; about the number of points is a good
    choice (bucket_start is [T + 1] int32). Non-finite points are treated as invalid.
    `dtype` is the grid dtype (default `default_dtype()`). jit with
    `static_argnames=("table_size", "dtype")`.
    """
    dt = jnp.dtype(dtype or default_dtype())
    px, py, pz = jnp.asarray(px), jnp.asarray(py), jnp.asarray(pz)
    pdt = px.dtype if jnp.issubdtype(px.dtype, jnp.floating) else dt
    m = px.shape[0]
    t = int(table_size)
    if t < 1:
        raise ValueError(f"table_size must be >= 1, got {table_size}")
    valid = jnp.ones((m,), bool) if valid is None else jnp.asarray(valid, bool)
    r = jnp.asarray(radius).astype(dt)
    cell = 2.0 * r * jnp.asarray(1.0 + CELL_MARGIN, dt)
    inv = 1.0 / cell
    xs = [a.astype(dt) for a in (px, py, pz)]
    valid = valid & jnp.isfinite(xs[0]) & jnp.isfinite(xs[1]) & jnp.isfinite(xs[2])
    any_valid = jnp.any(valid)
    lo = [jnp.where(any_valid, jnp.min(jnp.where(valid, x, jnp.inf), initial=jnp.inf), 0.0)
          .astype(dt) for x in xs]
    hi = [jnp.where(any_valid, jnp.max(jnp.where(valid, x, -jnp.inf), initial=-jnp.inf), 0.0)
          .astype(dt) for x in xs]
    origin = jnp.stack(lo)
    # rounding of the cell coordinates must stay well inside the margin (module docstring):
    # error of floor((x - o) / c) <~ 3u (|x - o| / c) plus u |x| / c for forming q +- r'.
    u = float(jnp.finfo(dt).eps) / 2
    span = jnp.max(jnp.stack([jnp.maximum(jnp.abs(a), jnp.abs(b)) + (b - a)
                              for a, b in zip(lo, hi)]))
    precise = ((r > 0) & jnp.isfinite(inv) & jnp.isfinite(span)
               & (span * inv + 2.0 < CELL_MARGIN / (32.0 * u)))
    if m == 0:
        return HashGrid(jnp.zeros((0, 4), pdt), jnp.zeros((0,), jnp.int32),
                        jnp.zeros((t + 1,), jnp.int32), origin, inv, r,
                        jnp.zeros((), jnp.int32), precise)
    cx, cy, cz = (_cell(x, o, inv) for x, o in zip(xs, lo))
    key = jnp.where(valid, _hash(cx, cy, cz, t), t)  # invalid slots: key T, sorted last
    order = sort_order(key, t + 1)
    counts = jax.ops.segment_sum(jnp.ones((m,), jnp.int32), key, num_segments=t + 1)
    start = jnp.concatenate([jnp.zeros((1,), jnp.int32), jnp.cumsum(counts[:t], dtype=jnp.int32)])
    rows = jnp.stack([px.astype(pdt), py.astype(pdt), pz.astype(pdt), jnp.zeros((m,), pdt)], 1)
    return HashGrid(_gather(rows, order), order, start, origin, inv, r, start[t], precise)


# ------------------------------------------------------------------------------ queries
class _Block(NamedTuple):
    """Per-query candidate list: the distinct buckets of the 2x2x2 block laid end to end.

    Candidate t of a query (0 <= t < total) is sorted slot
    t + off0 + sum_i [t >= cum[i]] * delta[i]   (i = 1..7),
    cum[i] being the exclusive prefix sum of the bucket lengths and off_i = start_i - cum_i
    (delta[i] = off_i - off_(i-1), telescoping over empty buckets).
    """

    off0: Array
    cum: tuple
    delta: tuple
    total: Array


def _lower_corner(grid: HashGrid, qx: Array, qy: Array, qz: Array, r: Array) -> list:
    """Lower cell of the 2x2x2 block of each query: the cell of q - r (1 + SEARCH_MARGIN),
    i.e. floor(q / cell - ~0.5) as in SmallVCM; non-finite coordinates map to 0."""
    rs = r * jnp.asarray(1.0 + SEARCH_MARGIN, r.dtype)
    return [_cell(jnp.where(jnp.isfinite(q), q, 0.0) - rs, grid.origin[a], grid.inv_cell)
            for a, q in enumerate((qx, qy, qz))]


def _block(grid: HashGrid, qx: Array, qy: Array, qz: Array, r: Array) -> _Block:
    t = grid.table_size
    finite = jnp.isfinite(qx) & jnp.isfinite(qy) & jnp.isfinite(qz)
    lo = _lower_corner(grid, qx, qy, qz, r)
    hashes = [_hash(lo[0] + i, lo[1] + j, lo[2] + k, t)
              for i, j, k in itertools.product((0, 1), repeat=3)]
    starts, lens = [], []
    for j, h in enumerate(hashes):
        dup = jnp.zeros(h.shape, bool)
        for i in range(j):  # a bucket shared by two cells of the block is visited once
            dup = dup | (h == hashes[i])
        s = _gather(grid.bucket_start, h)
        n = _gather(grid.bucket_start, h + 1) - s
        starts.append(s)
        lens.append(jnp.where(dup | ~finite, 0, n))
    cum, acc = [], jnp.zeros_like(lens[0])
    for n in lens:
        cum.append(acc)
        acc = acc + n
    off = [s - c for s, c in zip(starts, cum)]
    return _Block(off[0], tuple(cum[1:]), tuple(o - p for o, p in zip(off[1:], off[:-1])), acc)


def _candidate(blk: _Block, t: Array) -> Array:
    pos = t + blk.off0
    for c, d in zip(blk.cum, blk.delta):
        pos = pos + jnp.where(t >= c, d, 0)
    return pos


def _test(grid: HashGrid, qx, qy, qz, r2, blk: _Block, t: Array):
    """(active & within, sorted slot, squared distance) of candidate t of every query."""
    active = t < blk.total
    pos = jnp.where(active, _candidate(blk, t), 0)
    p = _gather(grid.points, pos).astype(grid.dtype)
    dx, dy, dz = p[:, 0] - qx, p[:, 1] - qy, p[:, 2] - qz
    d2 = dx * dx + dy * dy + dz * dz
    return active & (d2 <= r2), pos, d2


class _Queries(NamedTuple):
    q: list  # 3 x [C, B] query coordinates (grid dtype), NaN padded, maybe sorted
    qi: Array  # [C, B] index of each lane's query in the caller's arrays (0 for padding)
    inv: Array | None  # [n] caller index -> lane, or None (queries kept in their order)
    r: Array
    n: int
    b: int


def _prep(grid: HashGrid, qx, qy, qz, radius, chunk: int, sort_queries: bool,
          valid=None) -> _Queries:
    """Cast, optionally sort by the bucket of the lower corner of the block (queries with
    the same block become neighbouring lanes: shared candidates in cache, and similar
    candidate counts within a chunk), pad to chunks. Queries where `valid` (None: all) is
    False become NaN (no candidates) and, sorted, go to the end, so whole chunks of them
    are skipped. The sort key is the block's hash modulo at most 2**(32 - bits of n) - 1
    buckets, so that key and index pack into one uint32 (`sort_order`'s fast path): queries
    with the same block stay neighbours, and the order of the lanes never changes a query's
    sum (each lane adds its own pairs in candidate order)."""
    dt = grid.dtype
    r = grid.radius if radius is None else jnp.asarray(radius).astype(dt)
    q = [jnp.asarray(a).astype(dt) for a in (qx, qy, qz)]
    n = q[0].shape[0]
    qi, inv = lax.iota(jnp.int32, n), None
    ok = None if valid is None else jnp.asarray(valid, bool)
    if sort_queries and n > 1:
        kq = min(grid.table_size, (1 << (32 - max(1, (n - 1).bit_length()))) - 1)
        kq = max(kq, 1)
        key = _hash(*_lower_corner(grid, *q, r), kq)
        live = jnp.isfinite(q[0]) & jnp.isfinite(q[1]) & jnp.isfinite(q[2])
        if ok is not None:
            live = live & ok
        qi = sort_order(jnp.where(live, key, kq), kq + 1)
        inv = jnp.zeros((n,), jnp.int32).at[qi].set(lax.iota(jnp.int32, n), unique_indices=True)
        q = [_gather(a, qi) for a in q]
        ok = None if ok is None else _gather(ok, qi)
    if ok is not None:
        q = [jnp.where(ok, a, jnp.nan) for a in q]
    b = max(1, min(int(chunk), n))
    pad = (-n) % b
    q = [jnp.concatenate([a, jnp.full((pad,), jnp.nan, dt)]).reshape(-1, b) for a in q]
    qi = jnp.concatenate([qi, jnp.zeros((pad,), jnp.int32)]).reshape(-1, b)
    return _Queries(q, qi, inv, r, n, b)


def _unsort(qs: _Queries, a: Array) -> Array:
    """[C, B, ...] per-lane results -> [n, ...] in the caller's query order."""
    a = a.reshape((-1,) + a.shape[2:])[: qs.n]
    return a if qs.inv is None else _gather(a, qs.inv)


def query_reduce(grid: HashGrid, qx: ArrayLike, qy: ArrayLike, qz: ArrayLike,
                 fn: Callable[[Array, Array, Array], Any], radius: ArrayLike | None = None,
                 *, max_candidates: int | None = None, chunk: int = DEFAULT_CHUNK,
                 sort_queries: bool = True, return_need: bool = False, valid=None):
    """Sum over neighbours of a per-pair kernel, without a [Q, K] array.

    `fn(qi, pj, d2)` gets [B] arrays (query index into the given queries, point index into
    the build arrays, squared distance in the grid dtype) and returns a pytree of [B, ...]
    arrays; returns (the per-query sums [Q, ...], overflow). `fn` is also
    evaluated on non-neighbour lanes (their values are discarded with `where`; keep it
    finite there, e.g. `jnp.where` its own inputs, so gradients stay finite).
    max_candidates=None: while loop to each chunk's longest candidate list (exact, forward
    only). An int (static): at most that many candidates per query, by `fori_loop` (reverse
    differentiable; steps past the chunk's longest list are skipped by `lax.cond`);
    `overflow` is set when some query has more candidates (then its sum misses points).
    Choose it from the candidate counts (tests/_hashgrid_oracles.py `candidate_counts`).
    return_need: also return the longest candidate list of any query (int32), which is the
    capacity that would have been enough: the host re-runs once with that much room.
    `valid` ([Q] bool, None: all): the other queries get zero sums without a look-up.
    Queries are (optionally, static `sort_queries`) sorted by block, then processed in
    chunks of `chunk` (static) lanes: distance tests ~ sum over chunks of chunk * max
    candidates; the kernel runs on the neighbour pairs only, `chunk` pairs per call
    (compacted as they are found), so kernel work ~ number of pairs + one call per chunk.
    """
    n_q = jnp.shape(qx)[0]
    dt = grid.dtype
    probe = jnp.zeros((max(1, min(int(chunk), n_q)),), jnp.int32)
    fn = jax.jit(fn)  # one trace for the output shapes and the chunks' calls (same shapes)
    shape = jax.eval_shape(fn, probe, probe, probe.astype(dt))
    if grid.points.shape[0] == 0 or n_q == 0:
        out = jax.tree.map(lambda s: jnp.zeros((n_q,) + s.shape[1:], s.dtype), shape)
        none = (out, jnp.zeros((), bool))
        return none + (jnp.zeros((), jnp.int32),) if return_need else none
    qs = _prep(grid, qx, qy, qz, radius, chunk, sort_queries, valid)
    r = qs.r
    r2 = r * r
    cap = None if max_candidates is None else int(max_candidates)
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)

    def one_chunk(args):
        qi, (cx, cy, cz) = args
        # a chunk of invalid (NaN) queries only: no look-up (sorted, they are the last)
        return lax.cond(jnp.any(jnp.isfinite(cx)), live_chunk,
                        lambda _: (zeros, jnp.zeros((), jnp.int32)), args)

    def live_chunk(args):
        qi, (cx, cy, cz) = args
        blk = _block(grid, cx, cy, cz, r)
        tmax = jnp.max(blk.total)
        B = cx.shape[0]
        lane_ids = lax.iota(jnp.int32, B)

        # ---- the kernel runs on neighbour pairs only: the pairs found at each candidate
        #      step are appended to a queue of 2B; whenever B are waiting, one kernel call
        #      on B pairs, scatter-added to their lanes (each lane's pairs in candidate order)
        def flush(c):
            acc, ql, qp, qd, n = c
            valid = lax.iota(jnp.int32, B) < n
            ln = jnp.where(valid, ql[:B], 0)
            v = fn(_gather(qi, ln), jnp.where(valid, qp[:B], qp[0]), qd[:B])
            acc = jax.tree.map(
                lambda a, x: a.at[jnp.where(valid, ln, B)].add(x, mode="drop"), acc, v)
            shift = lambda q: jnp.concatenate([q[B:], q[B:]])  # noqa: E731
            return acc, shift(ql), shift(qp), shift(qd), jnp.maximum(n - B, 0)

        def step(t, c):
            acc, ql, qp, qd, n = c
            hit, pos, d2 = _test(grid, cx, cy, cz, r2, blk, t)
            at = jnp.where(hit, n + jnp.cumsum(hit, dtype=jnp.int32) - 1, 2 * B)
            ql = ql.at[at].set(lane_ids, mode="drop")
            qp = qp.at[at].set(_gather(grid.order, pos), mode="drop")
            qd = qd.at[at].set(d2, mode="drop")
            c = acc, ql, qp, qd, n + jnp.sum(hit, dtype=jnp.int32)
            return lax.cond(c[-1] >= B, flush, lambda c: c, c)

        zi = jnp.zeros((2 * B,), jnp.int32)
        c = (zeros, zi, zi, jnp.zeros((2 * B,), dt), jnp.zeros((), jnp.int32))
        if cap is None:
            _, c = lax.while_loop(lambda s: s[0] < tmax, lambda s: (s[0] + 1, step(s[0], s[1])),
                                  (jnp.zeros((), jnp.int32), c))
        else:
            c = lax.fori_loop(0, cap, lambda t, c: lax.cond(t < tmax, partial(step, t),
                                                            lambda c: c, c), c)
        acc = lax.cond(c[-1] > 0, flush, lambda c: c, c)[0]
        return acc, tmax.astype(jnp.int32)

    acc, need = lax.map(one_chunk, (qs.qi, tuple(qs.q)))
    need = jnp.max(need)
    over = jnp.zeros((), bool) if cap is None else need > cap
    out = jax.tree.map(partial(_unsort, qs), acc)
    return (out, over, need) if return_need else (out, over)
