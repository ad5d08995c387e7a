"""Uniforms drawn where they are used (`jaxvcm._uniforms`) are jax.random.uniform's own
numbers, bit for bit: the fixed-key renders depend on it (tests/transport/test_golden.py), and a
change in JAX's threefry mapping (counter layout, bits -> float) must fail here first."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.random import threefry2x32_p

from jaxvcm._uniforms import Uniforms, threefry2x32


def test_unrolled_hash_is_the_primitive():
    k1, k2 = jnp.uint32(0x9E3779B9), jnp.uint32(12345)
    lo = jnp.arange(4096, dtype=jnp.uint32) * jnp.uint32(2654435761)
    hi = lo ^ jnp.uint32(0xDEADBEEF)
    ref = threefry2x32_p.bind(k1 + 0 * lo, k2 + 0 * lo, hi, lo)
    got = threefry2x32(k1, k2, hi, lo)
    assert all(bool(jnp.all(a == b)) for a, b in zip(ref, got))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_lazy_draws_are_the_dense_table(dtype):
    # two tables side by side along the lanes (camera and light subpaths of one trace):
    # every (depth, lane) of both, lazily and densely, equals jax.random.uniform's table
    kc, kl = jax.random.fold_in(jax.random.key(3), 9), jax.random.key(11)
    cam = Uniforms.draw(kc, (5, 37, 6), dtype)
    lig = Uniforms.draw(kl, (4, 37, 6), dtype)
    both = cam.beside(lig)
    ref_c = np.asarray(jax.random.uniform(kc, (5, 37, 6), dtype))
    ref_l = np.asarray(jax.random.uniform(kl, (4, 37, 6), dtype))
    dense = np.asarray(both.dense())
    np.testing.assert_array_equal(dense[:, :37], ref_c)
    np.testing.assert_array_equal(dense[:4, 37:], ref_l)
    assert np.all(dense[4, 37:] == 0)  # the light table's missing row
    d, g = (a.ravel().astype(np.int32) for a in np.meshgrid(np.arange(4), np.arange(74),
                                                            indexing="ij"))
    rows = jax.jit(lambda d, g: both.rows_at(d, g, d[0] >= 0))(d, g)
    np.testing.assert_array_equal(np.asarray(rows).reshape(4, 74, 6), dense[:4])
    assert both.lazy and rows.dtype == dtype
    # a round with no live lane draws nothing
    none = both.rows_at(jnp.asarray(d), jnp.asarray(g), jnp.asarray(False))
    assert np.all(np.asarray(none) == 0)
