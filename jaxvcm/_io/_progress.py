"""A throttled one-line progress display for renders (passes, passes/s, elapsed, ETA)."""

from __future__ import annotations

import math
import sys
import time as _time

__all__ = ["Progress"]


class Progress:
    """One carriage-return-updated status line on stderr: passes done (of total), passes/s,
    ETA (from `total` passes or the `time_budget` in seconds, whichever ends first).
    Redrawn at most ~4 times a second; silent when `enabled` is False."""

    min_interval = 0.25

    def __init__(self, total: int | None, time_budget: float | None, enabled: bool = True,
                 stream=None):
        self.total = total
        self.time_budget = time_budget
        self.enabled = enabled
        self.stream = stream
        self._last_draw = -math.inf
        self._pending: tuple[int, float] | None = None
        self._width = 0
        self._drawn = False

    def _out(self):
        return self.stream if self.stream is not None else sys.stderr

    def _line(self, i: int, elapsed: float) -> str:
        rate = i / elapsed if elapsed > 0 else 0.0
        done = f"{i}/{self.total}" if self.total is not None else f"{i}"
        etas = []
        if self.total is not None and rate > 0:
            etas.append(max(self.total - i, 0) / rate)
        if self.time_budget is not None:
            etas.append(max(self.time_budget - elapsed, 0.0))
        eta = _fmt_time(min(etas)) if etas else "?"
        return (f"render: {done} passes  {rate:.2f} passes/s  "
                f"elapsed {_fmt_time(elapsed)}  ETA {eta}")

    def _draw(self, i: int, elapsed: float) -> None:
        line = self._line(i, elapsed)
        pad = max(self._width - len(line), 0)
        self._width = len(line)
        s = self._out()
        try:
            s.write("\r" + line + " " * pad)
            s.flush()
        except (OSError, ValueError):
            self.enabled = False
            return
        self._drawn = True

    def start(self) -> None:
        """The line shown until the first pass is done: it compiles the pass (seconds to a
        minute from an empty cache), so say so rather than show 0 passes/s."""
        if not self.enabled:
            return
        line = "render: compiling (the first pass includes the compilation) ..."
        self._width = len(line)
        try:
            s = self._out()
            s.write("\r" + line)
            s.flush()
        except (OSError, ValueError):
            self.enabled = False
            return
        self._drawn = True

    def update(self, i: int, elapsed: float) -> None:
        if not self.enabled:
            return
        now = _time.monotonic()
        final = self.total is not None and i >= self.total
        if final or now - self._last_draw >= self.min_interval:
            self._draw(i, elapsed)
            self._last_draw = now
            self._pending = None
        else:
            self._pending = (i, elapsed)

    def close(self) -> None:
        if not self.enabled:
            return
        if self._pending is not None:
            self._draw(*self._pending)
            self._pending = None
        if self._drawn:
            try:
                self._out().write("\n")
                self._out().flush()
            except (OSError, ValueError):
                pass
        self._drawn = False


def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    h, r = divmod(s, 3600)
    m, sec = divmod(r, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"
