"""Work that a stop (Ctrl-C, SIGTERM, SIGHUP) must not cut in two: the CLI's signal handlers defer a stop
that arrives inside ``critical()`` until the block ends.

    with critical():             # one MCAP write: a chunk cut halfway loses the messages it held
        writer.add_message(...)

A handler calls ``interrupt(exc)``: outside a critical block it raises ``exc`` at once, inside one it
keeps ``exc`` and the block raises it as it ends. A flag rather than blocking the signals (pthread_sigmask):
a signal blocked in the main thread is still delivered to any other thread (Taichi's, OpenCV's, a frame
reader's), and Python then runs the handler in the main thread at once, inside the write. Python runs
signal handlers in the main thread only, so blocks on other threads defer nothing.

A stop that arrives while the main thread imports a module (``after_import``) is sent again when the import
ends: raised inside an extension module's initialisation it would turn into an ``ImportError``.

A stream without an end of its own (a live camera) ends at Ctrl-C: the loop over it runs inside
``stream_end()``, and the CLI's Ctrl-C handler first calls ``end_stream()``, which asks that loop to end after
its current frame (the run then finishes as at a recording's end); a second Ctrl-C stops the run.
"""

from __future__ import annotations

import signal
import sys
import threading
import time

_depth = 0                                 # critical blocks the main thread is in
_pending: BaseException | None = None      # the stop that arrived inside one
_stream: "stream_end | None" = None        # the endless stream whose loop the main thread is in


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


def _importing(frame, outer) -> bool:
    """Whether ``frame`` (the main thread's, where a handler runs) is inside an import that began after ``outer``
    (the frame that installed the handlers): a run started by a module's own import is stopped as any other."""
    while frame is not None and frame is not outer:
        name = frame.f_code.co_filename
        if name.startswith("<frozen importlib.") or "importlib/_bootstrap" in name:  # frozen or not
            return True
        frame = frame.f_back
    return False


_redelivering = False  # a stop signal is waiting for the main thread's import to end


def after_import(signum: int, frame, outer) -> bool:
    """For a signal handler: True when the main thread is inside an import begun below ``outer`` (the frame that
    installed the handler), having arranged for ``signum`` to be sent to it again once the import ends; the
    handler then returns. An exception raised into an extension module's initialisation (GTSAM's, OpenCV's,
    imported lazily during a run) comes out as ``ImportError: initialization failed`` instead of the stop."""
    global _redelivering
    if not _importing(frame, outer):
        return False
    if _redelivering:
        return True
    _redelivering = True
    main = threading.main_thread().ident

    def redeliver() -> None:
        global _redelivering
        while _importing(sys._current_frames().get(main), outer):
            time.sleep(0.01)
        _redelivering = False
        signal.pthread_kill(main, signum)

    threading.Thread(target=redeliver, name="stop-after-import", daemon=True).start()
    return True


class stream_end:
    """``with stream_end() as end:`` around the main thread's loop over an endless stream: the first Ctrl-C
    inside it (``end_stream()``) sets ``end.requested``, and the loop ends when it sees it."""

    __slots__ = ("requested", "_outer")

    def __init__(self) -> None:
        self.requested = False

    def __enter__(self) -> "stream_end":
        global _stream
        self._outer = _stream
        if threading.current_thread() is threading.main_thread():  # the one thread signal handlers run in
            _stream = self
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        global _stream
        if _stream is self:
            _stream = self._outer
        return False


def end_stream() -> bool:
    """For the Ctrl-C handler: True when this Ctrl-C asked the loop over an endless stream to end (the first one
    inside ``stream_end()``), False when it is to stop the run as any other."""
    if _stream is None or _stream.requested:
        return False
    _stream.requested = True
    return True
