"""Passes on several local devices at once (issue 11, devices): `jax.shard_map` over a 1-D
mesh, one whole pass per device, so every device runs the same single-pass program the
one-device render compiles (no `vmap` over passes: that would turn the queues' `cond`s
into selects, docs/design.md).

A batch is D = len(devices) passes with keys `pass_key(seed, i)` and pass indices i (the
merging radius schedule follows the pass index), so the samples do not depend on how
passes are spread over devices. The per-pass images come back to the host and are added
there in pass order in float64, exactly as the one-device driver adds them: a sharded
render equals the one-device render of the same passes bit for bit
(tests/test_devices.py). Merge-capacity overflow on any device re-runs the whole batch
with more room (`with_retry`). Not yet: a reduction on the devices (issue 11).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

AXIS = "passes"


def resolve_devices(devices) -> list:
    """None: every local device; an int N: the first N local devices; else the list."""
    local = jax.local_devices()
    if devices is None:
        return list(local)
    if isinstance(devices, bool) or not isinstance(devices, (int, list, tuple)):
        raise ValueError(f"devices: expected None, a count or a list of devices, "
                         f"got {devices!r}")
    if isinstance(devices, int):
        if not 1 <= devices <= len(local):
            raise ValueError(f"devices: must lie in [1, {len(local)}] (local devices), "
                             f"got {devices}")
        return list(local[:devices])
    if not devices:
        raise ValueError("devices: empty list")
    return list(devices)


@functools.lru_cache(maxsize=32)
def _sharded(pass_fn, devices: tuple, config):
    """jit(shard_map) of `pass_fn(scene, key, config, index) -> (image, aux)` over
    `devices`: keys [D] and indices [D] in, images [D, H, W, C] and aux leaves [D] out."""
    mesh = Mesh(np.array(devices), (AXIS,))

    def body(scene, keys, idx):
        img, aux = pass_fn(scene, keys[0], config, idx[0])
        return img[None], jax.tree.map(lambda x: jnp.asarray(x)[None], aux)

    f = jax.shard_map(body, mesh=mesh, in_specs=(P(), P(AXIS), P(AXIS)),
                      out_specs=(P(AXIS), P(AXIS)), check_vma=False)
    return jax.jit(f)


def sharded_passes(pass_fn, scene, keys, config, indices, devices: list):
    """Passes `indices` (one per device) with `keys`: (images [D, ...], aux with [D]
    leaves), as host-side arrays."""
    f = _sharded(pass_fn, tuple(devices), config)
    img, aux = f(scene, keys, jax.device_put(np.asarray(indices, np.int32)))
    return np.asarray(img), jax.tree.map(np.asarray, aux)
