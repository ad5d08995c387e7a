"""Work queues: run an expensive per-item kernel only on the items that need it.

Under `vmap` every lane pays for every item, wanted or not. Here the wanted items are
compacted (`first_true` of the mask, in order) and processed `width` at a time in a
`lax.scan`; a round whose slice of the queue is empty is skipped by a `lax.cond` on a
scalar, and the results are scattered back to the items' places. There are enough rounds
for every item, so nothing is dropped and no capacity can overflow; the cost follows the
number of wanted items. (Under an outer `vmap` the `cond` becomes a select and every
round runs: still correct, no faster; so passes are batched by loops, not by `vmap`.)
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np


INT32_MAX = (1 << 31) - 1  # the queues' indices, fill values included, are int32
MIN_ROUND = 1024  # narrower rounds cost more in per-round overhead than they save


def round_width(n: int, split: int) -> int:
    """Items per round of a queue over n items: n / split, but not below MIN_ROUND (small
    batches: a few wide rounds); at most 2 MIN_ROUND items run as one round (the dense map:
    a second round's gathers, scatters and `cond` cost more than the dead items they would
    skip)."""
    if n <= 2 * MIN_ROUND:
        return n
    return max(-(-n // split), min(n, MIN_ROUND))


def running_count(m):
    """Inclusive running count of the True items of a flat boolean mask (int32)."""
    return jnp.cumsum(m, dtype=jnp.int32)


def first_true(m, size: int):
    """Indices of the first `size` True items of a flat boolean mask, in order, padded with
    m.size: `jnp.nonzero(m, size=size, fill_value=m.size)[0]`, by one running count and one
    scatter, where `nonzero` takes two running counts and a scatter-add (fewer kernels in
    every queue of the pass)."""
    M = m.shape[0]
    if max(M, size) > INT32_MAX:  # `_integrator.check_chunks` keeps a chunk's items below
        raise ValueError(f"config.tuning.chunks: a work queue of {M} items ({size} slots) "
                         f"is beyond int32 indices; use more chunks")
    pos = jnp.where(m, running_count(m) - 1, size)
    return jnp.full((size,), M, jnp.int32).at[pos].set(jnp.arange(M, dtype=jnp.int32),
                                                       mode="drop")


def traced_once(fn: Callable) -> Callable:
    """`fn` as a `jax.jit` function: the output shapes that a queue's buffers need
    (`jax.eval_shape` on one round's arguments, `round_args`) and the round's own call
    then share one trace of the kernel (jit's trace cache) instead of tracing its Python
    twice. The compiled program is the same: XLA inlines the call."""
    return jax.jit(fn)


def round_args(flat, W: int):
    """Shape structs of one round's arguments: W items of each leaf of `flat`."""
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct((W,) + a.shape[1:], a.dtype), flat)


def masked_map(fn: Callable, mask, args, fill, split: int, cheap=None, summed=False,
               summed_rows: int | None = None):
    """`fn` vmapped over the items of `args` (pytree of arrays with leading item axes of
    `mask`'s shape) where `mask` holds; `fill` (pytree of scalars, like fn's output)
    elsewhere. `split`: rounds per full sweep (`round_width`); 1 = one round of every
    item. `cheap`: None, or (cheap_fn, cheap_mask): a cheaper `fn` that is valid for the
    items where cheap_mask holds; those items are queued first, and a round made of them
    alone runs cheap_fn (a round that mixes both kinds runs `fn`, valid for every item).

    `summed` (a mask [J, N] of (technique, path) items, fn returning one array): the
    results summed over J per path instead, ([N, ...] sum, number of non-finite result
    elements): each item's non-finite elements are zeroed and counted, as the film does
    with a technique's image. The queue then writes no [J, N, ...] buffer (`fill` 0).
    `summed_rows`: fn returns (row, result) instead, each item added into that row of a
    [summed_rows, ...] sum (e.g. a light-tracing splat into its pixel's row)."""
    shape = mask.shape
    M = mask.size
    flat = jax.tree.map(lambda a: a.reshape((M,) + a.shape[len(shape):]), args)
    W = round_width(M, split)
    if summed:
        return _summed_map(fn, mask, flat, W, summed_rows)
    if W >= M:  # one round: the dense map, no gathers, no cond
        res = jax.vmap(fn)(*flat)
        m = mask.reshape(M)
        out = jax.tree.map(lambda r, f: jnp.where(m.reshape((M,) + (1,) * (r.ndim - 1)), r,
                                                  jnp.asarray(f, r.dtype)), res, fill)
        return jax.tree.map(lambda o: o.reshape(shape + o.shape[1:]), out)
    rounds = -(-M // W)
    m = mask.reshape(M)
    count = jnp.sum(mask, dtype=jnp.int32)
    if cheap is None:
        order = first_true(m, rounds * W)
    else:  # the cheap items first, in order, then the others: each item's place from
        # a running count of its kind (one scatter, as `first_true`)
        cheap_fn, cm = cheap
        first = m & cm.reshape(M)
        n_cheap = jnp.sum(first, dtype=jnp.int32)
        rest = m & ~first
        at = jnp.where(first, running_count(first) - 1,
                       jnp.where(rest, n_cheap + running_count(rest) - 1, rounds * W))
        order = jnp.full((rounds * W,), M, jnp.int32).at[at].set(
            jnp.arange(M, dtype=jnp.int32), mode="drop")
    order = order.reshape(rounds, W)
    vfn = traced_once(jax.vmap(fn))
    shapes = jax.eval_shape(vfn, *round_args(flat, W))
    out0 = jax.tree.map(lambda f, s: jnp.full((M,) + s.shape[1:], f, s.dtype), fill, shapes)

    def work(out, idx, f=vfn):
        g = jnp.minimum(idx, M - 1)
        res = f(*jax.tree.map(lambda a: a[g], flat))
        return jax.tree.map(lambda o, r: o.at[idx].set(r, mode="drop"), out, res)

    if cheap is None:
        def body(out, x):
            r, idx = x
            return jax.lax.cond(r * W < count, work, lambda o, _: o, out, idx), None
    else:
        def body(out, x):
            r, idx = x
            all_cheap = jnp.minimum((r + 1) * W, count) <= n_cheap  # (the padding: none)
            branch = jnp.where(r * W >= count, 0, jnp.where(all_cheap, 1, 2))
            return jax.lax.switch(branch, [lambda o, _: o,
                                           lambda o, i: work(o, i, jax.vmap(cheap_fn)),
                                           work], out, idx), None

    out, _ = jax.lax.scan(body, out0, (jnp.arange(rounds, dtype=jnp.int32), order))
    return jax.tree.map(lambda o: o.reshape(shape + o.shape[1:]), out)


def _summed_map(fn: Callable, mask, flat, W: int, n_rows: int | None = None):
    """`masked_map(..., summed=True)`: the items' results added into their path's row (or,
    with `n_rows`, into the row fn returns with its result)."""
    J, N = mask.shape
    M = mask.size
    m = mask.reshape(M)

    def clean(*a):  # one item: its non-finite elements zeroed and counted
        row, r = fn(*a) if n_rows is not None else (None, fn(*a))
        ok = jnp.isfinite(r)
        r = jnp.where(ok, r, jnp.zeros((), r.dtype))
        bad = jnp.sum(~ok, dtype=jnp.int32)
        return (r, bad) if n_rows is None else (r, bad, row)

    if W >= M:  # one round: the dense map, summed over the rows
        res = jax.vmap(clean)(*flat)
        r, bad = res[0], res[1]
        r = jnp.where(m.reshape((M,) + (1,) * (r.ndim - 1)), r, jnp.zeros((), r.dtype))
        n_bad = jnp.sum(jnp.where(m, bad, 0), dtype=jnp.int32)
        if n_rows is None:
            return r.reshape((J, N) + r.shape[1:]).sum(axis=0), n_bad
        out = jnp.zeros((n_rows,) + r.shape[1:], r.dtype).at[res[2]].add(r, mode="drop")
        return out, n_bad
    rounds = -(-M // W)
    count = jnp.sum(mask, dtype=jnp.int32)
    order = first_true(m, rounds * W).reshape(rounds, W)
    vfn = traced_once(jax.vmap(clean))
    shape = jax.eval_shape(vfn, *round_args(flat, W))[0]
    rows_out = N if n_rows is None else n_rows
    out0 = (jnp.zeros((rows_out,) + shape.shape[1:], shape.dtype), jnp.zeros((), jnp.int32))

    def work(out, idx):
        g = jnp.minimum(idx, M - 1)
        res = vfn(*jax.tree.map(lambda a: a[g], flat))
        r, bad = res[0], res[1]
        lane = g % N if n_rows is None else res[2]  # item (j, n) -> path n, or its row
        lane = jnp.where(idx < M, lane, rows_out)  # padding dropped
        n_bad = jnp.sum(jnp.where(idx < M, bad, 0), dtype=jnp.int32)
        return out[0].at[lane].add(r, mode="drop"), out[1] + n_bad

    def body(out, x):
        r, idx = x
        return jax.lax.cond(r * W < count, work, lambda o, _: o, out, idx), None

    out, _ = jax.lax.scan(body, out0, (jnp.arange(rounds, dtype=jnp.int32), order))
    return out


class Packed:
    """A pytree of arrays with a common leading shape, held as one [*lead, F] array per
    dtype (fewer, wider gathers and scatters in the queues' loops: one per dtype instead
    of one per field)."""

    def __init__(self, tree, lead: int):
        leaves, self.treedef = jax.tree.flatten(tree)
        self.lead = lead
        self.meta = [(a.dtype, a.shape[lead:]) for a in leaves]
        self.dtypes = sorted({str(m[0]) for m in self.meta})
        self.arrays = {d: jnp.concatenate(
            [a.reshape(a.shape[:lead] + (-1,)) for a in leaves if str(a.dtype) == d], axis=-1)
            for d in self.dtypes}

    def pack(self, tree) -> dict:
        """Another tree of the same structure (any leading shape) -> {dtype: [..., F]}."""
        leaves = jax.tree.leaves(tree)
        lead = [a.ndim - len(m[1]) for a, m in zip(leaves, self.meta)][0]
        return {d: jnp.concatenate([a.reshape(a.shape[:lead] + (-1,)) for a, m
                                    in zip(leaves, self.meta) if str(m[0]) == d], axis=-1)
                for d in self.dtypes}

    def unpack(self, arrays: dict):
        """{dtype: [..., F]} -> the tree (leading shape from the arrays)."""
        offs = {d: 0 for d in self.dtypes}
        leaves = []
        for dt, shape in self.meta:
            d = str(dt)
            a = arrays[d]
            n = int(np.prod(shape, dtype=np.int64))
            leaves.append(a[..., offs[d]:offs[d] + n].reshape(a.shape[:-1] + shape))
            offs[d] += n
        return jax.tree.unflatten(self.treedef, leaves)

    def column(self, leaf: int) -> tuple[str, int]:
        """(dtype, column) of scalar leaf number `leaf` in the packed arrays."""
        d = str(self.meta[leaf][0])
        col = sum(int(np.prod(m[1], dtype=np.int64)) for m in self.meta[:leaf] if str(m[0]) == d)
        return d, col


def compact(mask, capacity: int):
    """The items where `mask` holds, gathered into a static capacity: ([capacity] int32
    indices into the flattened mask, in order, padded with mask.size; the number of such
    items; overflow: more than `capacity` of them, so the ones after the first `capacity`
    are missing). The caller ORs `overflow` into its sticky diagnostics and the host
    re-runs with room for the count (`_render.with_retry`): nothing is dropped silently."""
    m = jnp.reshape(mask, (-1,))
    count = jnp.sum(m, dtype=jnp.int32)
    idx = first_true(m, capacity)
    return idx, count, count > capacity
