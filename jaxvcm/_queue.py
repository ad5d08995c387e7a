"""Work queues: run an expensive per-item kernel only on the items that need it.

Under `vmap` every lane pays for every item, wanted or not. Here the wanted items are
compacted (one `nonzero` of the mask, in order) and processed `width` at a time in a
`lax.scan`; a round whose slice of the queue is empty is skipped by a `lax.cond` on a
scalar, and the results are scattered back to the items' places. There are enough rounds
for every item, so nothing is dropped and no capacity can overflow; the cost follows the
number of wanted items. (Under an outer `vmap` the `cond` becomes a select and every
round runs: still correct, no faster.)
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def masked_map(fn: Callable, mask, args, fill, split: int):
    """`fn` vmapped over the items of `args` (pytree of arrays with leading item axes of
    `mask`'s shape) where `mask` holds; `fill` (pytree of scalars, like fn's output)
    elsewhere. `split`: rounds per full sweep (width = items / split); 1 = one round of
    every item."""
    shape = mask.shape
    M = mask.size
    flat = jax.tree.map(lambda a: a.reshape((M,) + a.shape[len(shape):]), args)
    W = -(-M // split)
    rounds = -(-M // W)
    order = jnp.nonzero(mask.reshape(M), size=rounds * W, fill_value=M)[0].reshape(rounds, W)
    count = jnp.sum(mask, dtype=jnp.int32)
    out0 = jax.tree.map(lambda f: jnp.full((M,), f), fill)
    vfn = jax.vmap(fn)

    def work(out, idx):
        g = jnp.minimum(idx, M - 1)
        res = vfn(*jax.tree.map(lambda a: a[g], flat))
        return jax.tree.map(lambda o, r: o.at[idx].set(r, mode="drop"), out, res)

    def body(out, x):
        r, idx = x
        return jax.lax.cond(r * W < count, work, lambda o, _: o, out, idx), None

    out, _ = jax.lax.scan(body, out0, (jnp.arange(rounds, dtype=jnp.int32), order))
    return jax.tree.map(lambda o: o.reshape(shape), out)
