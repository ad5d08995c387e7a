"""`reuse_host_buffers`: on glibc a jitted program whose temporary buffer is as large as a
thread arena's heap (64 MB) touches it anew on every call (a fresh mmap each time, a page
fault per 4 kB page); with the setting the block is reused. Each side runs in its own
process (the setting holds for the whole process and only for threads that start after
it)."""

from __future__ import annotations

import subprocess
import sys

import pytest

# a loop over a 64 MB array (2^24 float32): its carry buffers are XLA:CPU temporaries at
# least as large as a thread arena's heap, allocated on the runtime's threads; the last
# calls' faults are counted (the heap grows to hold them in the first calls)
_PROGRAM = """
import resource, sys
import jaxvcm
applied = jaxvcm.reuse_host_buffers() if sys.argv[1] == "1" else None
import jax, jax.numpy as jnp
x = jnp.arange(1 << 24, dtype=jnp.float32)
f = jax.jit(lambda x: jax.lax.fori_loop(0, 3, lambda i, a: a[::-1] * 0.5 + i, x)[::7].sum())
faults = []
for _ in range(16):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    f(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
print(applied, sum(faults[-8:]))
"""


def _faults(apply: bool) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _PROGRAM, "1" if apply else "0"],
                         capture_output=True, text=True, check=True, timeout=300)
    applied, total = out.stdout.split()
    return applied, int(total)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_reuse_host_buffers_stops_the_page_faults_of_large_temporaries():
    applied, with_setting = _faults(True)
    _, without = _faults(False)
    assert applied == "True"
    # without: 8 calls x >= 64 MB touched anew = >= 131,072 faults of 4 kB pages (the test
    # measures what it is about; measured 32.8 k a call); with: the blocks are reused
    # (measured: 0 in most calls, 32.8 k in one of 8 or none), at most half of that left
    assert without >= 8 * (64 << 20) // 4096, without
    assert with_setting <= 0.5 * without, (with_setting, without)
