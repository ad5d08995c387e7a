"""Many processes on JAX's own distributed runtime: `initialize` wraps
`jax.distributed.initialize`, after which `jax.devices()` lists every process's devices and
a render's device mesh (`_devices`) spans them all. Every process runs the same host loop
(SPMD, the multi-controller model of JAX): the same batches of passes, the same collective
calls in the same order. Process 0 leads: it alone prints progress and writes outputs, and
the decisions that depend on its clock (a time budget's end, when to snapshot) are
broadcast from it (`agree`), so no process waits on a collective that another skipped.

On the CPU the cross-process collectives are gloo's (set before the backend starts)."""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.experimental import multihost_utils


def _env_int(name: str):
    v = os.environ.get(name)
    if v is None or v == "":
        return None
    try:
        return int(v)
    except ValueError:
        raise ValueError(f"{name}: expected an integer, got {v!r}") from None


def requested(coordinator=None, num_processes=None, process_id=None) -> bool:
    """Whether a multi-process launch is asked for (by arguments or by the environment
    variables `initialize` reads)."""
    return any(x is not None for x in (
        coordinator, num_processes, process_id, os.environ.get("JAX_COORDINATOR_ADDRESS"),
        os.environ.get("JAX_NUM_PROCESSES"), os.environ.get("JAX_PROCESS_ID")))


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> None:
    """Join a multi-process render (`jax.distributed.initialize`).

    The coordinator's HOST:PORT, the process count and this process's id come each from
    its argument or else from `JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES`,
    `JAX_PROCESS_ID` (and, for what is still unset, JAX's cluster detection: SLURM, Open
    MPI, ...). Must come before anything starts a JAX backend."""
    coordinator = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS") or None
    if num_processes is None:
        num_processes = _env_int("JAX_NUM_PROCESSES")
    if process_id is None:
        process_id = _env_int("JAX_PROCESS_ID")
    if coordinator is not None and (":" not in coordinator
                                    or not coordinator.rsplit(":", 1)[1].isdigit()):
        raise ValueError(f"coordinator: expected HOST:PORT, got {coordinator!r}")
    if num_processes is not None and num_processes < 1:
        raise ValueError(f"num_processes: must be >= 1, got {num_processes}")
    if process_id is not None and not 0 <= process_id < (num_processes or 1 << 30):
        raise ValueError(f"process_id: must lie in [0, {num_processes - 1}], got {process_id}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU only; harmless else
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)


def count() -> int:
    return jax.process_count()


def is_lead() -> bool:
    """Process 0 prints and writes; on one process, always."""
    return jax.process_index() == 0


def agree(values):
    """Process 0's `values` (a tuple of host scalars) on every process."""
    if jax.process_count() == 1:
        return values
    out = multihost_utils.broadcast_one_to_all(np.asarray(values, np.float64))
    return tuple(np.asarray(out).tolist())


def to_host(x) -> np.ndarray:
    """A (possibly cross-process) jax.Array as a whole host array on every process."""
    if jax.process_count() == 1 or getattr(x, "is_fully_addressable", True):
        return np.asarray(x)
    if x.is_fully_replicated:
        return np.asarray(x.addressable_data(0))
    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def broadcast(x: np.ndarray) -> np.ndarray:
    """Process 0's array on every process."""
    if jax.process_count() == 1:
        return x
    return np.asarray(multihost_utils.broadcast_one_to_all(x))
