"""Reading the next frames while the current one is processed: worker processes (or a thread) and a few
frames held.

    with Prefetcher(dataset, ahead=3, workers=2, mode="processes") as frames:
        for i, frame, read_ms in frames:
            ...

Frames come out in order. ``mode``:

- "processes" (files and bags): ``workers`` reader processes (``ti_fusion.io.frame_workers``) decode
  frames and hand their depth and colour over through shared memory, so decoding runs beside Taichi's
  kernel launches, which hold the GIL (docs/PERFORMANCE.md, reading in processes). A receiver thread takes
  frame i + 1 from its reader (the message, and the arrays copied out of the shared memory, a copy that
  releases the GIL) while the caller works on frame i, and as it starts, asks for frame i + ``ahead`` into
  the slot frame i has left, so the bound below holds as it did. The caller reads the first frame itself
  while the processes start, except a rendered one. On the CPU backend the synthetic sequence is rendered
  in a reader process too: its renderer compiles and runs beside the loop's kernels.
- "thread": one background thread (a camera, frames in memory, a dataset that does not pickle).
- "inline": the caller's thread (the synthetic sequence on a GPU backend: its frames come from Taichi kernels,
  which would hold the GIL anyway, and Taichi is not meant to launch from two threads at once).

No frame j is asked for before the caller has taken frame j − ``ahead`` (``ahead`` is at least one per
worker). An error raised while reading frame k (an ``InputError`` for an unreadable file) is raised in
the caller's thread when it asks for frame k, after frames 0 to k−1 have come out, so what is done before
the bad frame is kept, as without prefetching; a reader process that dies raises ``ReaderDied`` at the
frame it owed. Leaving the ``with`` block (normal end, error, Ctrl-C, SIGTERM) stops the thread or the
processes and releases the shared memory.
"""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Iterator, Sequence

from ti_fusion.io.frame_workers import WorkerPool, can_use_processes, count_launches
from ti_fusion.timing import Stopwatch

_STOP_POLL_S = 0.05  # how often a waiting reader thread or caller checks whether the reading is to stop
_SLOT_MARGIN = 1.25  # a frame slot's bytes over the frame's estimated depth and colour (a colour camera's size
#                      is not always known beforehand; what does not fit is pickled instead)
MODES = ("processes", "thread", "inline")


def usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))  # the CPUs this process may run on (a container's, a taskset's)
    except AttributeError:  # (not on every platform)
        return os.cpu_count() or 1


def reader_count(setting: int, dataset) -> int:
    """How many workers read ``dataset`` ahead for ``dataset.read_workers`` = ``setting``: one where its frames
    cannot be read at once (``concurrent_reads`` False); else the setting, and for 0 a quarter of the usable
    CPUs, 1 to 4 (one per four cores leaves the others to Taichi's workers)."""
    if not getattr(dataset, "concurrent_reads", False):
        return 1
    if setting > 0:
        return int(setting)
    return max(1, min(4, usable_cpus() // 4))


def read_mode(dataset, arch: str | None = None) -> str:
    """How the pipeline reads ``dataset``: "inline" (frames made by Taichi kernels, on the loop's thread),
    "processes" (files and bags: ``Dataset.reads_in_process``, where the dataset pickles) or "thread"
    (a camera, frames in memory, a dataset class of the caller's own). Frames made by Taichi kernels are
    made in a reader process where the loop runs on the CPU (``arch``) and the dataset says they may be
    (``renders_in_process``, on its class: a wrapper that hands its attributes on renders inline, as it may
    not survive pickling): the reader's Taichi, on the CPU too, compiles the same code, so the frames are the
    same bits; on a GPU the loop's own backend renders them, as before."""
    if getattr(dataset, "renders_on_taichi", False):
        declared = getattr(type(dataset), "renders_in_process", False) and getattr(dataset, "renders_in_process")
        if arch == "cpu" and declared and can_use_processes(dataset):
            return "processes"
        return "inline"
    if getattr(dataset, "reads_in_process", False) and can_use_processes(dataset):
        return "processes"
    return "thread"


class Prefetcher:
    """Yields ``(i, dataset[i], read_ms)`` for i in 0..n−1, reading up to ``ahead`` frames in advance.

    ``read_ms`` is the time the reading itself took (in its reader process or thread).
    """

    def __init__(self, dataset: Sequence, ahead: int = 3, workers: int = 1, mode: str = "thread",
                 n: int | None = None):
        if mode not in MODES:
            raise ValueError(f"mode {mode!r}: one of {MODES}")
        self.dataset = dataset
        self.n = len(dataset) if n is None else n
        self.mode = mode
        self.workers = 0 if mode == "inline" else 1 if mode == "thread" else max(int(workers), 1)
        self.ahead = max(int(ahead), self.workers, 1)
        self.pool: WorkerPool | None = None
        # the thread's side
        self._lock = threading.Condition()
        self._ready: dict[int, tuple] = {}  # read, not yet handed out: index → (kind, frame or error, read_ms)
        self._next = 0  # the next index the thread reads
        self._handed = 0  # frames handed to the caller
        self._end = self.n  # no index from here on is read (after an error at k: k + 1)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # the processes' side: the thread that takes the next frame from its reader (its arrays copied out of the
        # shared memory, which releases the GIL) while the caller works on the one before
        self._receiver: ThreadPoolExecutor | None = None

    @classmethod
    def for_dataset(cls, dataset, setting: int = 0, ahead: int = 3, arch: str | None = None) -> "Prefetcher":
        """The pipeline's prefetcher: ``read_mode(dataset, arch)`` (``arch``: the loop's backend), and
        ``reader_count(setting, dataset)`` processes (``setting``: ``dataset.read_workers``)."""
        mode = read_mode(dataset, arch)
        return cls(dataset, ahead, reader_count(setting, dataset) if mode == "processes" else 1, mode)

    def __enter__(self) -> Iterator[tuple[int, object, float]]:
        if self.mode == "inline" or self.n == 0:
            return self._inline()
        if self.mode == "thread":
            self._thread = threading.Thread(target=self._read_all, name="ti-fusion-reader", daemon=True)
            self._thread.start()
            return self._from_thread()
        try:
            self.pool = WorkerPool(self.dataset, self.workers, self.ahead, self._slot_bytes())
        except OSError as exc:  # (no process could be started: out of memory or of process slots)
            # (rendered frames on the loop's own thread: Taichi is not meant to launch from two threads)
            self.mode = "inline" if getattr(self.dataset, "renders_on_taichi", False) else "thread"
            self.workers = 0 if self.mode == "inline" else 1
            logging.getLogger(__name__).warning(f"frames are read on {'the loop' if self.workers == 0 else 'a'} "
                                                f"thread: no reader process could start ({exc})")
            return self.__enter__()
        # frame 0 is read by the caller while the processes start (an interpreter and its imports), unless
        # frames are rendered (the point of the reader is then that the renderer compiles and runs beside the
        # loop's kernels); frame j goes to worker (j − first) mod workers, into slot j mod ahead, at most
        # ahead of them asked for at once
        self._first = 0 if getattr(self.dataset, "renders_on_taichi", False) else 1
        self._asked = self._first
        self._receiver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ti-fusion-receiver")
        while self._asked < min(self.n, self._first + self.ahead):
            self.pool.request(self._asked, self._worker(self._asked), self._asked % self.ahead)
            self._asked += 1
        return self._from_processes()

    @property
    def renders_elsewhere(self) -> bool:
        """Frames made by Taichi kernels are being made in reader processes (entered, "processes" mode)."""
        return self.pool is not None and getattr(self.dataset, "renders_on_taichi", False)

    def _worker(self, i: int) -> int:
        """The reader process that reads frame ``i``."""
        return (i - self._first) % self.workers

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader thread or processes (each finishes the frame it is reading), drop what they have
        read and release the shared memory."""
        self._stop.set()
        try:
            if self._thread is not None:
                with self._lock:
                    self._lock.notify_all()
                self._thread.join()
            if self._receiver is not None:  # (it stops waiting within _STOP_POLL_S: before the memory goes)
                self._receiver.shutdown(wait=True)
        finally:  # a second Ctrl-C during the join still stops the processes
            self._thread = None
            self._receiver = None
            self._ready.clear()
            if self.pool is not None:
                pool, self.pool = self.pool, None
                pool.close()

    def _slot_bytes(self) -> int:
        """A frame's depth (float32) and colour (RGB) bytes at the dataset's size, with a margin."""
        K = getattr(self.dataset, "intrinsics", None)
        if K is None:
            return 0
        pixels = int(K.width) * int(K.height)
        color = getattr(self.dataset, "color_intrinsics", None)
        color_pixels = int(color.width) * int(color.height) if color is not None else pixels
        return int(_SLOT_MARGIN * (4 * pixels + 3 * max(pixels, color_pixels))) + 256

    # -- inline ---------------------------------------------------------------------------------
    def _inline(self) -> Iterator[tuple[int, object, float]]:
        for i in range(self.n):
            watch = Stopwatch()
            frame = self.dataset[i]
            yield i, frame, watch.ms

    # -- processes ------------------------------------------------------------------------------
    def _from_processes(self) -> Iterator[tuple[int, object, float]]:
        pool, n, asked = self.pool, self.n, self._asked
        if self._first:
            watch = Stopwatch()
            frame = self.dataset[0]
            yield 0, frame, watch.ms
        receiver = self._receiver
        coming: Future | None = None  # frame i's receipt on the receiver thread, started as frame i - 1 went out
        for i in range(self._first, n):
            if self.pool is None:  # closed while the caller still iterates: nothing more comes
                return
            received = (coming or receiver.submit(self._receive, pool, i)).result()
            coming = None
            if received is None:  # closed meanwhile
                return
            kind, payload, read_ms, launches = received
            count_launches(launches)  # here: with the frame they were reported with
            if kind == "error":
                raise payload
            ask = None
            if asked < n:  # the slot is free again: the next frame into it, asked for on the receiver thread
                ask, asked = asked, asked + 1
            if i + 1 < n:  # (at the last frame every frame has been asked for: asked > i, and ask is None)
                coming = receiver.submit(self._receive, pool, i + 1, ask)
            yield i, payload, read_ms

    def _receive(self, pool: WorkerPool, i: int, ask: int | None = None) -> tuple[str, object, float, list] | None:
        """On the receiver thread: frame ``ask`` asked for (its slot is free: the frame before in it has been
        handed out), then frame ``i`` from its reader (``WorkerPool.take``); None once closing."""
        if ask is not None:
            pool.request(ask, self._worker(ask), ask % self.ahead)
        worker = self._worker(i)
        while not self._stop.is_set():
            if pool.ready(worker, _STOP_POLL_S):
                return pool.take(i, worker, i % self.ahead)
        return None

    # -- the thread -----------------------------------------------------------------------------
    def _from_thread(self) -> Iterator[tuple[int, object, float]]:
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
