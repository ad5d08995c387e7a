"""Signals that stop a render: SIGINT (Ctrl-C) and SIGTERM.

A progressive render (`_render.progressive`) keeps the passes it has: once its first pass is
done, the first signal is deferred to the end of the pass in flight, where the render writes
the image of the passes it has and raises `Interrupted`; a second signal interrupts at
once (the passes accumulated so far are still written). Before the first pass (loading,
compiling) there is nothing to keep and the signal interrupts at once.

`handled()` installs the handlers (the CLI does, for a render or a fit; a library caller
keeps Python's own SIGINT handler, whose KeyboardInterrupt the render catches the same
way). A signal is never lost: it is recorded before anything else, so a KeyboardInterrupt
that Python cannot deliver (raised inside a garbage-collection callback, say, where it is
"ignored") still stops the render at the next pass boundary (`check`).
"""

from __future__ import annotations

import contextlib
import signal
import threading

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A render stopped by a signal; `status` is the exit status a shell expects (128 + the
    signal's number: 130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def status(self) -> int:
        return 128 + self.signum


_pending: int | None = None  # the first signal received and not yet acted on
_defer = False  # inside a render loop whose first pass is done


def _handler(signum, frame):
    global _pending
    first = _pending is None
    if first:
        _pending = int(signum)
    if _defer and first:
        return  # acted on at the end of the pass in flight (`check`)
    raise Interrupted(_pending)


@contextlib.contextmanager
def handled():
    """SIGINT and SIGTERM raise `Interrupted` (deferred as the module doc says) for the
    duration; the previous handlers are restored after. Off the main thread, a no-op."""
    global _pending
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {}
    _pending = None
    try:
        for sig in SIGNALS:
            old[sig] = signal.signal(sig, _handler)
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        _pending = None


def defer(on: bool) -> None:
    """Inside a render loop: defer the first signal to `check` (on) or not (off)."""
    global _defer
    _defer = bool(on)


def check() -> None:
    """Raise `Interrupted` for a signal received since `handled()` began, if any."""
    if _pending is not None:
        raise Interrupted(_pending)
