"""Work that a stop (Ctrl-C, SIGTERM, SIGHUP) must not cut in two: the CLI's signal handlers defer a stop
that arrives inside ``critical()`` until the block ends.

    with critical():             # one MCAP write: a chunk cut halfway loses the messages it held
        writer.add_message(...)

A handler calls ``interrupt(exc)``: outside a critical block it raises ``exc`` at once, inside one it
keeps ``exc`` and the block raises it as it ends. A flag rather than blocking the signals (pthread_sigmask):
a signal blocked in the main thread is still delivered to any other thread (Taichi's, OpenCV's, a frame
reader's), and Python then runs the handler in the main thread at once, inside the write. Python runs
signal handlers in the main thread only, so blocks on other threads defer nothing.
"""

from __future__ import annotations

import threading

_depth = 0                                 # critical blocks the main thread is in
_pending: BaseException | None = None      # the stop that arrived inside one


class critical:
    """``with critical():``: a stop that arrives inside the block is raised when the block ends (unless the
    block ends with an exception of its own). Blocks nest."""

    __slots__ = ("_counted",)

    def __enter__(self) -> "critical":
        global _depth
        self._counted = threading.current_thread() is threading.main_thread()
        if self._counted:
            _depth += 1
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        global _depth, _pending
        if self._counted:
            _depth -= 1
            if _depth == 0 and _pending is not None:
                pending, _pending = _pending, None
                if exc is None:
                    raise pending
        return False


def interrupt(exc: BaseException) -> None:
    """For a signal handler: raise ``exc`` now, or when the critical block the main thread is in ends (the
    first stop wins)."""
    global _pending
    if _depth == 0:
        raise exc
    if _pending is None:
        _pending = exc
