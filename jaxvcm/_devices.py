"""Passes on several devices at once: `jax.shard_map` over a 1-D mesh, one whole pass per
device, so every device runs the same single-pass program the one-device render compiles
(no `vmap` over passes: that would turn the work queues' `cond`s into selects, `_queue`).
The mesh spans the devices of every process of a multi-process render
(`_hosts`): the first N local devices of each process, in process order.

A batch is G = len(mesh devices) passes with keys `pass_key(seed, i)` and pass indices i
(the merging radius schedule follows the pass index), so the samples do not depend on how
passes are spread over devices and processes. The images stay on the devices: each device
adds its pass into its own running sum (float32, Kahan-compensated, so the sum's rounding
error does not grow with the pass count), and only the sums' total (`DeviceSum.total`, a
`psum` over the mesh) comes back, for a snapshot or the end. Images therefore equal the
one-device render's to float32 rounding of the sums (tests/host/test_devices.py),
not bit for bit: the one-device driver adds per-pass images on the host in float64. A
partial last batch masks the passes it does not need. Merge-capacity overflow on any device
re-runs the whole batch with more room (`with_retry`) before anything is added.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from . import _hosts

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


def mesh_devices(local: list) -> list:
    """The render's mesh: `local` on one process; on many, the first len(local) devices of
    every process in process order (every process must use the same count)."""
    if _hosts.count() == 1:
        return list(local)
    n = len(local)
    (lead_n,) = _hosts.agree((n,))
    if int(lead_n) != n:
        raise ValueError(f"devices: process {jax.process_index()} uses {n} devices, "
                         f"process 0 uses {int(lead_n)}; every process must use the same count")
    out = []
    for p in range(_hosts.count()):
        out += [d for d in jax.devices() if d.process_index == p][:n]
    return out


def _global(mesh, spec, host: np.ndarray):
    """A host array (the same on every process) as a jax.Array laid out by `spec`."""
    sh = NamedSharding(mesh, spec)
    return jax.make_array_from_callback(host.shape, sh, lambda idx: host[idx])


@functools.lru_cache(maxsize=32)
def _step(pass_fn, devices: tuple, config):
    """jit(shard_map): every device runs `pass_fn(scene, key, config, index)` on its key
    and index and adds the image (where its `valid` flag is set) into its running sum
    (acc, comp: Kahan's compensation); aux leaves come back as [G]."""
    mesh = Mesh(np.array(devices), (AXIS,))

    def body(scene, key_data, idx, valid, acc, comp):
        img, aux = pass_fn(scene, jax.random.wrap_key_data(key_data[0]), config, idx[0])
        x = jnp.where(valid[0], img.astype(jnp.float32), jnp.float32(0))
        y = x - comp[0]
        t = acc[0] + y
        c = (t - acc[0]) - y
        return t[None], c[None], jax.tree.map(lambda a: jnp.asarray(a)[None], aux)

    spec = P(AXIS)
    f = jax.shard_map(body, mesh=mesh, in_specs=(P(), spec, spec, spec, spec, spec),
                      out_specs=(spec, spec, spec), check_vma=False)
    return jax.jit(f)


@functools.lru_cache(maxsize=32)
def _reduce(devices: tuple):
    mesh = Mesh(np.array(devices), (AXIS,))

    def body(acc, comp):
        return jax.lax.psum(acc[0] - comp[0], AXIS)

    return jax.jit(jax.shard_map(body, mesh=mesh, in_specs=(P(AXIS), P(AXIS)),
                                 out_specs=P(), check_vma=False))


class DeviceSum:
    """Running per-device sums of pass images [G, *shape] on the mesh of `devices`."""

    def __init__(self, pass_fn, scene, devices: list, shape: tuple):
        self.pass_fn, self.devices = pass_fn, tuple(devices)
        self.mesh = Mesh(np.array(devices), (AXIS,))
        self.scene = jax.device_put(scene, NamedSharding(self.mesh, P()))
        zeros = np.zeros((len(devices), *shape), np.float32)
        self.acc = _global(self.mesh, P(AXIS), zeros)
        self.comp = _global(self.mesh, P(AXIS), zeros)

    def run(self, keys, indices, valid, config):
        """One batch (not yet added): ((acc, comp), aux with host [G] leaves)."""
        f = _step(self.pass_fn, self.devices, config)
        kd = np.asarray(jax.random.key_data(keys))
        acc, comp, aux = f(self.scene, _global(self.mesh, P(AXIS), kd),
                           _global(self.mesh, P(AXIS), np.asarray(indices, np.int32)),
                           _global(self.mesh, P(AXIS), np.asarray(valid, bool)),
                           self.acc, self.comp)
        return (acc, comp), jax.tree.map(_hosts.to_host, aux)

    def add(self, sums) -> None:
        self.acc, self.comp = sums

    def total(self) -> np.ndarray:
        """The sum of every pass added, float64 on the host (of every process)."""
        return _hosts.to_host(_reduce(self.devices)(self.acc, self.comp)).astype(np.float64)
