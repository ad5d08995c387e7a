"""Uniform random numbers drawn where they are used, equal bit for bit to the dense draw.

A pass draws its path uniforms as dense tables, `jax.random.uniform(key, (rows, lanes,
width))`: u[d, n] for every depth d of every lane n. Most lanes die long before the last
depth, so hashing the whole table would spend most of its threefry hashes on slots no
vertex reads. JAX's threefry is counter based: with `jax_threefry_partitionable` (JAX's
default) element i of the table is a function of the key and of i alone,
    bits(i) = x1 ^ x2,  (x1, x2) = threefry2x32(key, (hi(i), lo(i)))   (32-bit floats;
    float64: x1 << 32 | x2),
    u(i) = bitcast(bits >> (nbits - nmant) | bits(1.0)) - 1.0,
so the uniforms of one (depth, lane) can be hashed on their own, in the trace round that
needs them (`Uniforms.at`), and the samples do not change. `dense()` is
`jax.random.uniform` itself; the sampling tests (tests/sampling/test_uniforms.py) check
that the two agree bit for bit (in float32 and float64, one table and two tables side by
side), so a change in JAX's mapping is caught there, not in the renders. With another key
implementation, or the partitionable flag off, `at` gathers from the dense table (always
correct, no saving).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array


_ROT = ((13, 15, 26, 6), (17, 29, 16, 24))


def threefry2x32(k1, k2, x1, x2):
    """The Threefry-2x32 hash of 20 rounds (Salmon et al. 2011, Random123), the function of
    `jax.extend.random.threefry2x32_p`, unrolled into one fused loop (the CPU backend
    lowers JAX's primitive as a rolled loop of five blocks, with buffers per iteration
    that outweigh the hash for the few thousand lanes of a trace round). Equal bit for bit
    to the primitive (tests/sampling/test_uniforms.py)."""
    u32 = jnp.uint32
    ks = (k1, k2, k1 ^ k2 ^ u32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for i in range(5):
        for r in _ROT[i % 2]:
            x1 = x1 + x2
            x2 = (x2 << u32(r)) | (x2 >> u32(32 - r))
            x2 = x1 ^ x2
        x1 = x1 + ks[(i + 1) % 3]
        x2 = x2 + ks[(i + 2) % 3] + u32(i + 1)
    return x1, x2


def _lazy_ok(key) -> bool:
    return (bool(jax.config.jax_threefry_partitionable)
            and str(jax.random.key_impl(key)) == str(jax.random.key_impl(jax.random.key(0))))


class Uniforms(eqx.Module):
    """Tables `jax.random.uniform(keys[t], (rows[t], lanes, width), dtype)` for t = 0..T-1,
    side by side along the lane axis (lane g of the whole is lane g - t lanes of table t),
    drawn lazily: `at(d, g)` = the whole's u[d, g] ([width]), `dense()` the whole
    [max(rows), T lanes, width] (a shorter table's missing rows are zeros)."""

    keys: Array  # [T] typed PRNG keys
    rows: tuple[int, ...] = eqx.field(static=True)
    lanes: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    dtype: np.dtype = eqx.field(static=True)
    lazy: bool = eqx.field(static=True)

    @staticmethod
    def draw(key, shape, dtype) -> "Uniforms":
        """The table `jax.random.uniform(key, shape = (rows, lanes, width), dtype)`."""
        rows, lanes, width = shape
        dt = np.dtype(dtype)
        lazy = (_lazy_ok(key) and dt in (np.float32, np.float64)
                and rows * lanes * width < 2**32)  # 32-bit counters (no x64 needed)
        return Uniforms(key[None], (int(rows),), int(lanes), int(width), dt, lazy)

    def beside(self, other: "Uniforms") -> "Uniforms":
        """This table's lanes, then `other`'s (same lanes, width and dtype)."""
        assert (self.lanes, self.width, self.dtype) == (other.lanes, other.width, other.dtype)
        return Uniforms(jnp.concatenate([self.keys, other.keys]), self.rows + other.rows,
                        self.lanes, self.width, self.dtype, self.lazy and other.lazy)

    def _table(self, t: int):
        shape = (self.rows[t], self.lanes, self.width)
        if not self.lazy:
            return jax.random.uniform(self.keys[t], shape, self.dtype)
        # the same numbers by the unrolled hash over the flat index (`threefry2x32`)
        i = jnp.arange(int(np.prod(shape)), dtype=jnp.uint32)
        return _to_unit(self.keys[t], i, self.dtype).reshape(shape)

    def dense(self):
        """[max(rows), T lanes, width]: the tables themselves (`jax.random.uniform`'s)."""
        R = max(self.rows)
        parts = [jnp.pad(self._table(t), ((0, R - r), (0, 0), (0, 0)))
                 for t, r in enumerate(self.rows)]
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=1)

    def rows_at(self, d, g, live):
        """u[d[k], g[k], :] for a batch of items ([K], [K] -> [K, width]) as one buffer:
        hashed inside a conditional on `live` (a traced scalar: False only where no item
        needs them; zeros then). The branch is a computation boundary, so the hashes are
        computed once: as plain ops the CPU backend would fuse the integer hash into each
        of its consumers' loops and compute it there again (and it drops optimization
        barriers before fusion)."""
        return jax.lax.cond(live, lambda: jax.vmap(self.at)(d, g),
                            lambda: jnp.zeros(d.shape + (self.width,), self.dtype))

    def at(self, d, g):
        """u[d, g, :] of the whole ([width]; d, g integer scalars: vmap for batches)."""
        if not self.lazy:
            return self.dense()[d, g]
        d, g = jnp.asarray(d).astype(jnp.int32), jnp.asarray(g).astype(jnp.int32)
        t = g // self.lanes if len(self.rows) > 1 else jnp.zeros((), jnp.int32)
        n = g - t * self.lanes
        # the flat index of (d, n, c) in its table, below 2^32 (`draw`): hi word 0
        lo = ((d.astype(jnp.uint32) * np.uint32(self.lanes) + n.astype(jnp.uint32))
              * np.uint32(self.width) + jnp.arange(self.width, dtype=jnp.uint32))
        return _to_unit(self.keys[t], lo, self.dtype)


def _to_unit(key, lo, dtype):
    """jax.random.uniform's numbers at flat indices `lo` (< 2^32) of a table drawn with `key`
    (module doc): threefry of (0, lo), 32 or 64 bits, mantissa bits under an exponent of 1."""
    kd = jax.random.key_data(key)  # [2] uint32
    x1, x2 = threefry2x32(kd[0], kd[1], jnp.zeros_like(lo), lo)
    if dtype == np.float64:
        bits = (x1.astype(jnp.uint64) << jnp.uint64(32)) | x2.astype(jnp.uint64)
        one = jnp.uint64(np.array(1.0, np.float64).view(np.uint64))
        f = jax.lax.bitcast_convert_type((bits >> jnp.uint64(64 - 52)) | one, jnp.float64)
        return f - 1.0
    bits = x1 ^ x2
    one = jnp.uint32(np.array(1.0, np.float32).view(np.uint32))
    f = jax.lax.bitcast_convert_type((bits >> jnp.uint32(32 - 23)) | one, jnp.float32)
    return f - jnp.float32(1.0)
