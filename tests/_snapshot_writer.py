"""Child process of tests/io/test_snapshots.py: writes snapshot sets OUT.exr/.png/.json in a
loop (image value = pass count = the record's "passes"), as a render's snapshots do.

    python -m tests._snapshot_writer OUT START [KILL_AFTER]

With KILL_AFTER = k the process SIGKILLs itself right after its k-th `os.replace`, i.e. at a
chosen point between the renames of a set; without it, it writes until it is killed."""

import os
import signal
import sys

import numpy as np

from jaxvcm import _io

out, start = sys.argv[1], int(sys.argv[2])
kill_after = int(sys.argv[3]) if len(sys.argv) > 3 else None
if kill_after is not None:
    _replace, n = os.replace, [0]

    def replace(a, b):
        _replace(a, b)
        n[0] += 1
        if n[0] == kill_after:
            os.kill(os.getpid(), signal.SIGKILL)

    os.replace = replace
import OpenEXR  # noqa: E402,F401  (imports and the colour tables loaded before "ready")

_io.png_bytes(np.zeros((1, 1, 3), np.float32))
print("ready", flush=True)
i = start
while True:
    _io.write_outputs(out, np.full((16, 24, 3), float(i), np.float32),
                      {"passes": i, "snapshot": True}, exposure=0.5)
    i += 1
