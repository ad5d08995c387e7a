"""Values computed once, as their own kernel, however many fusions read them.

The CPU backend fuses an elementwise producer into every consumer fusion that reads it,
transcendental producers included, so a sampled direction's cosine and sine or a wave's
derivative would be evaluated again in each fusion that reads a component, a kind's
select or a column of the trace's packed state. A product with the identity keeps them
apart: XLA does not fuse a producer into a `dot`, so the producer becomes its own kernel
and its result a buffer (`jax.lax.optimization_barrier` does not serve here, as the CPU
pipeline removes barriers before fusion). docs/design/performance.md has the wider
picture.
"""

from __future__ import annotations

import jax.numpy as jnp


def computed_once(*xs):
    """`xs` (arrays of one shape and dtype), each computed once: returned through a
    product with the identity, which is exact for finite values (x * 1 + y * 0 = x; a
    non-finite value would spread to the others, so pass only values that are finite
    wherever they are used). Values, derivatives and batching are those of `xs`."""
    if len(xs) == 1:
        x = xs[0]
        return (x[..., None] @ jnp.ones((1, 1), x.dtype))[..., 0]
    v = jnp.stack(xs, axis=-1) @ jnp.eye(len(xs), dtype=xs[0].dtype)
    return tuple(v[..., i] for i in range(len(xs)))
