"""Host memory of a long render on glibc (Linux): the passes reuse their buffers.

XLA:CPU allocates a pass's temporary buffers as one block (179 MB for PPM, 387 MB for VCM
on SmallVCM's scene 0 at 256x256, depth 10) with `malloc` from one of its worker threads.
glibc serves a request that large in a thread's arena by a fresh `mmap` (a thread arena's
heaps hold at most 64 MB) and unmaps it when it is freed, so every pass touches every page
of the block anew: 44 k page faults a PPM pass there (the kernel clears each page), 17-28 %
of the pass. With one arena (the main one, grown by `brk`), no `mmap` for large blocks and
no trimming of the heap's top, the block of one pass is the block of the next: no page
faults. The cost: the compiler's threads share that arena, which made a cold compilation
about a tenth slower (wall and CPU seconds, alternating runs), and the process keeps its
peak memory. So the command line's `render` and `bench` set it, for their process, before
the runtime starts its threads (`cli.entry`); a program that embeds jaxvcm may call
`reuse_host_buffers` first thing, or set `GLIBC_TUNABLES=glibc.malloc.arena_max=1:
glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=2147483647` in its environment, which
is the same. Elsewhere (another C library or OS) it does nothing.
"""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
_TRIM_NEVER = 2**31 - 1  # mallopt takes an int


def reuse_host_buffers() -> bool:
    """Make this process's large host buffers come from one reused heap (module doc).
    Call it before the first JAX computation (the arena of a thread that already
    allocated stays its own). Returns True where glibc took the settings."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018 (glibc only)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return all(mallopt(p, v) == 1 for p, v in ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0),
                                               (_M_TRIM_THRESHOLD, _TRIM_NEVER)))
