"""Reading the next frames while the current one is processed: background threads and a few frames held.

    with Prefetcher(dataset, ahead=3, workers=1) as frames:
        for i, frame, read_ms in frames:
            ...

Frames come out in order. Decoding a PNG or JPEG in OpenCV releases the GIL, so on a machine with a
spare core the loop's wait for the next frame shrinks to the time it takes to hand it over. With
``workers`` > 1, that many threads read different frames at once (for a dataset whose frames can be read
in any order and at the same time: ``Dataset.concurrent_reads``), for a machine where one thread decodes
more slowly than the loop processes (docs/PERFORMANCE.md, reading ahead). An error raised while reading
frame k (an ``InputError`` for an unreadable file) is raised in the caller's thread when it asks for frame
k, after frames 0 to k−1 have come out, so what is done before the bad frame is kept, as without
prefetching; no frame after k is handed out (one reader reads none). Leaving the ``with`` block (normal
end, error, Ctrl-C) stops the threads.

A dataset whose frames are made by Taichi kernels (the synthetic sequence) is read in the caller's thread
(``threaded=False``): Taichi kernel launches hold the GIL, so a second thread would gain nothing, and
Taichi's launch and compile paths are not meant to run on two threads at once.
"""

from __future__ import annotations

import os
import sys
import threading
from typing import Iterator, Sequence

from ti_fusion.timing import Stopwatch

_STOP_POLL_S = 0.05  # how often a waiting reader or caller checks whether the reading is to stop
# The GIL's switch interval while the readers run: the loop's thread holds the GIL through every Taichi
# kernel launch and between them hands it over only when this interval has passed, so a reader, which
# needs it for a moment between decodes, waits less with a shorter one (CPython's default is 5 ms).
_SWITCH_INTERVAL_S = 0.0005


def reader_threads(setting: int, dataset) -> int:
    """How many threads read ``dataset`` ahead for ``dataset.read_threads`` = ``setting``: one where its frames
    cannot be read at once (``concurrent_reads`` False); else the setting, and for 0 a quarter of the CPUs,
    1 to 4 (one per four cores leaves the others to Taichi's workers)."""
    if not getattr(dataset, "concurrent_reads", False):
        return 1
    if setting > 0:
        return int(setting)
    try:
        cpus = len(os.sched_getaffinity(0))  # the CPUs this process may run on (a container's, a taskset's)
    except AttributeError:  # (not on every platform)
        cpus = os.cpu_count() or 1
    return max(1, min(4, cpus // 4))


class Prefetcher:
    """Yields ``(i, dataset[i], read_ms)`` for i in 0..n−1, reading up to ``ahead`` frames in advance on
    ``workers`` threads (at least one per worker is allowed ahead).

    ``read_ms`` is the time the reading itself took (on its reader's thread when ``threaded``).
    """

    def __init__(self, dataset: Sequence, ahead: int = 3, threaded: bool = True, n: int | None = None,
                 workers: int = 1):
        self.dataset = dataset
        self.n = len(dataset) if n is None else n
        self.workers = max(int(workers), 1)
        self.ahead = max(int(ahead), self.workers)
        self.threaded = threaded
        self._lock = threading.Condition()
        self._ready: dict[int, tuple] = {}  # read, not yet handed out: index → (kind, frame or error, read_ms)
        self._next = 0  # the next index a reader takes
        self._handed = 0  # frames handed to the caller
        self._end = self.n  # no index from here on is read (after an error at k: k + 1)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._switch_interval: float | None = None

    def __enter__(self) -> Iterator[tuple[int, object, float]]:
        if not self.threaded:
            return self._inline()
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, _SWITCH_INTERVAL_S))
        try:
            for _ in range(self.workers):
                thread = threading.Thread(target=self._read_all, name="ti-fusion-reader", daemon=True)
                thread.start()
                self._threads.append(thread)
        except BaseException:  # (e.g. no thread could be started): stop those that did, give the interval back
            self.close()
            raise
        return self._from_readers()

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader threads (each finishes the frame it is reading) and drop what they have read."""
        self._stop.set()
        if self._switch_interval is None:
            return
        try:
            with self._lock:
                self._lock.notify_all()
            for thread in self._threads:
                thread.join()
        finally:  # a second Ctrl-C during a join still gives the interval back
            self._threads = []
            self._ready.clear()
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None

    # -- the caller's side ----------------------------------------------------------------------
    def _inline(self) -> Iterator[tuple[int, object, float]]:
        for i in range(self.n):
            watch = Stopwatch()
            frame = self.dataset[i]
            yield i, frame, watch.ms

    def _from_readers(self) -> Iterator[tuple[int, object, float]]:
        for i in range(self.n):
            with self._lock:
                while i not in self._ready:
                    if self._stop.is_set():  # closed while the caller still iterates: nothing more comes
                        return
                    self._lock.wait(_STOP_POLL_S)
                kind, payload, read_ms = self._ready.pop(i)
                self._handed = i + 1
                self._lock.notify_all()
            if kind == "error":
                raise payload
            yield i, payload, read_ms

    # -- the reader threads ---------------------------------------------------------------------
    def _read_all(self) -> None:
        while True:
            with self._lock:
                while (not self._stop.is_set() and self._next < self._end
                       and self._next >= self._handed + self.ahead):  # no further ahead than allowed
                    self._lock.wait(_STOP_POLL_S)
                if self._stop.is_set() or self._next >= self._end:
                    return
                i = self._next
                self._next += 1
            watch = Stopwatch()
            try:
                item = ("frame", self.dataset[i], watch.ms)
            except BaseException as exc:  # handed to the caller, raised there at frame i
                item = ("error", exc, 0.0)
            with self._lock:
                self._ready[i] = item
                if item[0] == "error":
                    self._end = min(self._end, i + 1)
                self._lock.notify_all()
