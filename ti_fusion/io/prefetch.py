"""Reading the next frames while the current one is processed: a background thread and a small queue.

    with Prefetcher(dataset, ahead=3) as frames:
        for i, frame, read_ms in frames:
            ...

Frames come out in order. Decoding a PNG or JPEG in OpenCV releases the GIL, so on a machine with a
spare core the loop's wait for the next frame shrinks to the time it takes to hand it over. An error
raised while reading frame k (an ``InputError`` for an unreadable file) is raised in the caller's thread
when it asks for frame k, after frames 0 to k−1 have come out, so what is done before the bad frame is
kept, as without prefetching. Leaving the ``with`` block (normal end, error, Ctrl-C) stops the thread.

A dataset whose frames are made by Taichi kernels (the synthetic sequence) is read in the caller's thread
(``threaded=False``): Taichi kernel launches hold the GIL, so a second thread would gain nothing, and
Taichi's launch and compile paths are not meant to run on two threads at once.
"""

from __future__ import annotations

import queue
import sys
import threading
from typing import Iterator, Sequence

from ti_fusion.timing import Stopwatch

_STOP_POLL_S = 0.05  # how often a reader blocked on a full queue checks whether it is asked to stop
# The GIL's switch interval while the reader runs: the loop's thread holds the GIL through every Taichi
# kernel launch and between them hands it over only when this interval has passed, so the reader, which
# needs it for a moment between decodes, waits less with a shorter one (CPython's default is 5 ms).
_SWITCH_INTERVAL_S = 0.0005


class Prefetcher:
    """Yields ``(i, dataset[i], read_ms)`` for i in 0..n−1, reading up to ``ahead`` frames in advance.

    ``read_ms`` is the time the reading itself took (on the reader's thread when ``threaded``).
    """

    def __init__(self, dataset: Sequence, ahead: int = 3, threaded: bool = True, n: int | None = None):
        self.dataset = dataset
        self.n = len(dataset) if n is None else n
        self.ahead = max(int(ahead), 1)
        self.threaded = threaded
        self._queue: queue.Queue = queue.Queue(maxsize=self.ahead)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._switch_interval: float | None = None

    def __enter__(self) -> Iterator[tuple[int, object, float]]:
        if not self.threaded:
            return self._inline()
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, _SWITCH_INTERVAL_S))
        self._thread = threading.Thread(target=self._read_all, name="ti-fusion-reader", daemon=True)
        self._thread.start()
        return self._from_queue()

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader thread (it finishes the frame it is reading) and drop what it has read."""
        self._stop.set()
        if self._thread is None:
            return
        while self._thread.is_alive():
            self._drain()
            self._thread.join(_STOP_POLL_S)
        self._drain()
        self._thread = None
        sys.setswitchinterval(self._switch_interval)

    # -- the caller's side ----------------------------------------------------------------------
    def _inline(self) -> Iterator[tuple[int, object, float]]:
        for i in range(self.n):
            watch = Stopwatch()
            frame = self.dataset[i]
            yield i, frame, watch.ms

    def _from_queue(self) -> Iterator[tuple[int, object, float]]:
        for i in range(self.n):
            kind, payload, read_ms = self._queue.get()
            if kind == "error":
                raise payload
            yield i, payload, read_ms

    def _drain(self) -> None:
        try:
            while True:
                self._queue.get_nowait()
        except queue.Empty:
            pass

    # -- the reader thread ----------------------------------------------------------------------
    def _read_all(self) -> None:
        for i in range(self.n):
            if self._stop.is_set():
                return
            watch = Stopwatch()
            try:
                item = ("frame", self.dataset[i], watch.ms)
            except BaseException as exc:  # handed to the caller, raised there at frame i
                item = ("error", exc, 0.0)
            if not self._put(item) or item[0] == "error":
                return

    def _put(self, item) -> bool:
        """Queue ``item``, waiting while the queue is full; False when asked to stop meanwhile."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=_STOP_POLL_S)
                return True
            except queue.Full:
                continue
        return False
