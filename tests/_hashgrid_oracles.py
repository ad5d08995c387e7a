"""Fixed-K hash grid queries, for the tests and the grid benchmark only.

The renderer needs only `jaxvcm._hashgrid.build` and `query_reduce` (a kernel sum, no
neighbour list). `query` (every neighbour's index in a [Q, K] array), its host helper
`query_with_retry` and `candidate_counts` (the candidate-list length of each query, the
loop length of both queries) were in `jaxvcm/_hashgrid.py`; they are kept here, unchanged,
because tests/merge/test_hashgrid.py checks the grid's neighbour sets through `query` against
the brute-force oracle and `benchmarks/hashgrid.py` times them (docs/design/merging.md). They
are built from the grid's private building blocks (`_prep`, `_block`, `_test`, ...), which
is why they live with the white-box tests rather than in `benchmarks/` (the benchmarks use
only the public `jaxvcm` API).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike

from jaxvcm import _hashgrid as HG


def query(grid: HG.HashGrid, qx: ArrayLike, qy: ArrayLike, qz: ArrayLike,
          radius: ArrayLike | None = None, *, max_neighbours: int,
          chunk: int = HG.DEFAULT_CHUNK, sort_queries: bool = True) -> tuple[Array, Array, Array]:
    """Every valid point within distance <= radius (default: the build radius) of each query.

    Returns (idx [Q, K] int32: indices into the build arrays, -1 padded, in bucket order;
    count [Q] int32: the true number of neighbours, also when it exceeds K; overflow:
    bool scalar, any count > K). K = `max_neighbours` (static). Queries are (optionally,
    static `sort_queries`) sorted by block, then processed in chunks of `chunk` (static)
    lanes by a while loop over the candidate slots of the chunk's longest candidate list:
    work ~ sum over chunks of chunk * max candidates. Non-finite queries have no
    neighbours. `radius` must not exceed the build radius.
    """
    k = int(max_neighbours)
    if k < 0:
        raise ValueError(f"max_neighbours must be >= 0, got {max_neighbours}")
    n_q = jnp.shape(qx)[0]
    if grid.points.shape[0] == 0 or n_q == 0:
        return (jnp.full((n_q, k), -1, jnp.int32), jnp.zeros((n_q,), jnp.int32),
                jnp.zeros((), bool))
    qs = HG._prep(grid, qx, qy, qz, radius, chunk, sort_queries)
    r, b = qs.r, qs.b
    r2 = r * r
    lane = lax.iota(jnp.int32, b)

    def one_chunk(qc):
        cx, cy, cz = qc
        blk = HG._block(grid, cx, cy, cz, r)

        def body(state):
            t, count, idx = state
            hit, pos, _ = HG._test(grid, cx, cy, cz, r2, blk, t)
            # flat [B * (K + 1)] buffer, column K of every row a trash slot for misses and
            # for hits past K: an in-bounds scatter with unique indices, 2x faster than 2-D
            slot = lane * (k + 1) + jnp.where(hit & (count < k), count, k)
            idx = idx.at[slot].set(pos, mode="promise_in_bounds", unique_indices=True,
                                   wrap_negative_indices=False)
            return t + 1, count + hit.astype(jnp.int32), idx

        init = (jnp.zeros((), jnp.int32), jnp.zeros((b,), jnp.int32),
                jnp.full((b * (k + 1),), -1, jnp.int32))
        _, count, idx = lax.while_loop(lambda s: s[0] < jnp.max(blk.total), body, init)
        return idx.reshape(b, k + 1)[:, :k], count

    idx, count = lax.map(one_chunk, tuple(qs.q))
    idx, count = HG._unsort(qs, idx), HG._unsort(qs, count)
    idx = jnp.where(idx >= 0, HG._gather(grid.order, jnp.maximum(idx, 0)), -1)
    return idx, count, jnp.any(count > k)


def candidate_counts(grid: HG.HashGrid, qx: ArrayLike, qy: ArrayLike, qz: ArrayLike,
                     radius: ArrayLike | None = None) -> Array:
    """[Q] int32 number of candidates (points in the distinct buckets of each query's block):
    the loop length of `query`/`query_reduce`; its max is a good `max_candidates`."""
    dt = grid.dtype
    r = grid.radius if radius is None else jnp.asarray(radius).astype(dt)
    q = [jnp.asarray(a).astype(dt) for a in (qx, qy, qz)]
    if grid.points.shape[0] == 0:
        return jnp.zeros(q[0].shape, jnp.int32)
    return HG._block(grid, *q, r).total


_query_jit = jax.jit(query, static_argnames=("max_neighbours", "chunk", "sort_queries"))


def query_with_retry(grid: HG.HashGrid, qx: ArrayLike, qy: ArrayLike, qz: ArrayLike,
                     radius: ArrayLike | None = None, *, max_neighbours: int = 16,
                     max_capacity: int = 1 << 16, **kw):
    """Host loop: jitted `query`; on overflow double K (as often as the exact counts say
    is needed, so one re-run) and re-run until no overflow. Returns ((idx, count,
    overflow=False), K used). Raises if K would exceed `max_capacity`. Capacities stay
    max_neighbours * 2**j (few recompiles). `kw`: chunk, sort_queries."""
    k = max(1, int(max_neighbours))
    while True:
        idx, count, overflow = _query_jit(grid, qx, qy, qz, radius, max_neighbours=k, **kw)
        if not bool(overflow):
            return (idx, count, overflow), k
        need = int(jnp.max(count))
        k = k * 2 ** max(1, math.ceil(math.log2(need / k)))
        if k > max_capacity:
            raise RuntimeError(f"hash grid query needs {need} neighbours > max_capacity "
                               f"{max_capacity}")
