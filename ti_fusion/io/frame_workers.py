"""Frames read in worker processes and handed over through shared memory (the reading side of
``ti_fusion.io.prefetch``).

    pool = WorkerPool(dataset, workers=2, slots=3, slot_bytes=...)   # starts the processes
    pool.request(i, worker, slot)      # worker reads dataset[i] into slot
    kind, item, read_ms, launches = pool.take(i, worker, slot)   # ("frame", Frame, ms, …) or ("error", exc, 0, …)
    count_launches(launches)           # a renderer's first launches, counted where the item is handed out
    pool.close()                       # stops and reaps every process

Why processes: Taichi holds the GIL through every kernel launch, so a reader thread gets the interpreter
only between launches; a process decodes beside them (docs/PERFORMANCE.md, reading in processes). A reader
that renders frames with Taichi (the synthetic sequence) starts Taichi of its own on the CPU; its kernels'
first launches travel with the frames to the caller's ``ti_fusion.frontend.CLOCK``.

How they start: a fresh interpreter (``sys.executable -c``) that imports this module only, with the
dataset pickled to it. Not multiprocessing's ``fork`` (Taichi's threads and LLVM state in a forked child
are undefined), nor its ``spawn`` or ``forkserver``: both run the parent's ``__main__`` script again in the
child (or the fork server), so a script without an ``if __name__ == "__main__"`` guard would run its
SLAM again there; the interpreter started here runs nothing of the caller's.

Shared memory: one anonymous ``memfd`` per pool, ``slots`` × ``slot_bytes``, passed to each process as a
file descriptor. It has no name in /dev/shm and goes with the last process that maps it, so nothing is
left behind however the run ends (SIGKILL included). A frame's depth and colour are written into its
slot by the worker and copied out by the caller, which then reuses the slot for a later frame; what does
not fit a slot (a colour camera larger than estimated) travels in the pickled message instead.

A worker runs in a session of its own, so a Ctrl-C or hang-up that the terminal sends to the caller's
process group never reaches it, not even while its interpreter is still starting (the caller decides how
the run ends and stops the workers); it also ignores SIGINT and SIGHUP sent to it by pid, and it ends when
the caller's end of its socket closes: the caller exited or was killed.
"""

from __future__ import annotations

import mmap
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection

import numpy as np

from ti_fusion.errors import TiFusionError

_ALIGN = 64  # each array in a slot starts on a cache line
_ARRAYS = ("depth", "color")  # the Frame fields that travel through shared memory
_STOP_WAIT_S = 5.0  # how long a stopping worker may take to finish its frame before it is killed
# How long a worker whose end of the socket closed may take to be reaped before it is said not to answer: a bound for
# one that closed it and lives on, not a timing the message depends on (a killed one's exit can be slow under load).
_DIED_WAIT_S = 60.0
# A reader that renders frames with Taichi (the synthetic sequence) does so on the CPU, leaving the caller's
# threads pinned to the CPUs alone (ti_fusion.backend).
_WORKER_ENV = {"TI_FUSION_ARCH": "cpu", "TI_FUSION_PIN_THREADS": "0"}


def fresh_interpreter(module: str, call: str, **popen) -> subprocess.Popen:
    """``from module import ...; call`` in a fresh interpreter of this Python with this process's
    ``sys.path``, in a session of its own (module docstring: why not multiprocessing, why a session);
    ``popen``: the rest of ``subprocess.Popen``'s arguments (its pipes, descriptors and environment)."""
    name = call.split("(", 1)[0]
    code = f"import sys; sys.path[:] = {sys.path!r}; from {module} import {name}; {call}"
    return subprocess.Popen([sys.executable, "-c", code], close_fds=True, start_new_session=True, **popen)


class ReaderDied(TiFusionError):
    """A frame reader process ended while the run waited for its frame."""


def can_use_processes(dataset) -> bool:
    """Whether ``dataset`` can be read in worker processes here: Linux's memfd, an interpreter to start, and
    a dataset that pickles (a class of the caller's ``__main__`` does not reach a fresh interpreter)."""
    if not hasattr(os, "memfd_create") or not sys.executable:
        return False
    if getattr(type(dataset), "__module__", "__main__") == "__main__":
        return False
    try:
        pickle.dumps(dataset)
    except Exception:  # an open handle, a lambda: read on a thread instead
        return False
    return True


def count_launches(launches: list) -> None:
    """The kernels' first launches a reader reported with an item (a renderer's), counted with this process's."""
    if launches:
        from ti_fusion.frontend import CLOCK

        for name, seconds, compiled in launches:
            CLOCK.add(seconds, name, compiled, elsewhere=True)


def _aligned(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN


class WorkerPool:
    """``workers`` reader processes sharing ``slots`` frame slots of ``slot_bytes`` each."""

    def __init__(self, dataset, workers: int, slots: int, slot_bytes: int):
        self.slot_bytes = _aligned(max(int(slot_bytes), _ALIGN))
        self.slots = int(slots)
        self._procs: list[subprocess.Popen] = []
        self._conns: list[Connection] = []
        self._fd = os.memfd_create("ti-fusion-frames", os.MFD_CLOEXEC)
        self._buf = None
        try:
            os.ftruncate(self._fd, self.slots * self.slot_bytes)
            self._buf = mmap.mmap(self._fd, self.slots * self.slot_bytes)
            payload = pickle.dumps(dataset, protocol=pickle.HIGHEST_PROTOCOL)
            for _ in range(max(int(workers), 1)):
                self._start(payload)
        except BaseException:
            self.close()
            raise

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self._procs]

    def _start(self, payload: bytes) -> None:
        ours, theirs = socket.socketpair()
        try:
            proc = fresh_interpreter(__name__, f"_main({theirs.fileno()}, {self._fd})",
                                     pass_fds=(theirs.fileno(), self._fd), stdin=subprocess.DEVNULL,
                                     env={**os.environ, **_WORKER_ENV})
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self._procs.append(proc)
        conn = Connection(ours.detach())
        self._conns.append(conn)
        conn.send_bytes(pickle.dumps((self.slot_bytes, payload), protocol=pickle.HIGHEST_PROTOCOL))

    def request(self, i: int, worker: int, slot: int) -> None:
        """Worker ``worker`` reads item ``i`` into ``slot`` (after the items it was asked for before)."""
        try:
            self._conns[worker].send((i, slot))
        except OSError:  # it is gone: receive() says so at this item
            pass

    def ready(self, worker: int, timeout: float) -> bool:
        """Whether ``worker`` has sent something to ``take`` (or has gone), waiting up to ``timeout`` seconds."""
        try:
            return self._conns[worker].poll(timeout)
        except (EOFError, OSError):
            return True  # ``take`` says how it went
        except IndexError:  # closed
            return False

    def take(self, i: int, worker: int, slot: int) -> tuple[str, object, float, list]:
        """Item ``i`` from ``worker``, on any thread: ("frame", item, read ms, launches) with its arrays copied out
        of ``slot``, or ("error", the exception its reading raised, 0.0, launches); ``launches``: the kernels' first
        launches the reader reports with the item, for the caller to ``count_launches`` where the item is handed
        out. ``ReaderDied`` when the process is gone."""
        try:
            message = self._conns[worker].recv()
        except (EOFError, OSError):
            raise self._died(i, worker) from None
        kind, index, item, read_ms, launches = message
        if index != i:  # (a protocol error, not a user's: say it plainly)
            raise RuntimeError(f"frame reader sent item {index} where {i} was due")
        if kind == "frame":
            item = self._unpack(item, slot)
        return kind, item, read_ms, launches

    def _unpack(self, item, slot: int):
        packed = getattr(item, "_shm", None)
        if not packed:
            return item
        base = slot * self.slot_bytes
        for name, offset, shape, dtype in packed:
            dtype = np.dtype(dtype)
            count = int(np.prod(shape))
            view = np.frombuffer(self._buf, dtype=dtype, count=count, offset=base + offset)
            setattr(item, name, view.reshape(shape).copy())  # the slot is the next frame's once handed out
            del view
        del item._shm
        return item

    def _died(self, i: int, worker: int) -> ReaderDied:
        proc = self._procs[worker]
        try:
            code = proc.wait(timeout=_DIED_WAIT_S)
        except subprocess.TimeoutExpired:
            code = None
        how = ("is not answering" if code is None else
               f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}")
        return ReaderDied(f"the frame reader process (pid {proc.pid}) {how} while reading frame {i}")

    def close(self) -> None:
        """Stop every worker (each finishes the frame in its hands), kill one that does not stop, reap them
        all, and release the shared memory. Idempotent."""
        for conn in self._conns:
            try:
                conn.close()  # the worker sees the end of its socket and exits
            except OSError:
                pass
        self._conns = []
        deadline = time.monotonic() + _STOP_WAIT_S
        try:
            for proc in self._procs:
                try:
                    proc.wait(timeout=max(deadline - time.monotonic(), 0.01))
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        finally:
            for proc in self._procs:  # (a second Ctrl-C during the waits: none is left running)
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
            self._procs = []
            if self._buf is not None:
                buf, self._buf = self._buf, None
                try:
                    buf.close()
                except BufferError:  # a frame's copy out of it still holds a view (the prefetcher's receiver
                    pass             # thread, after a second Ctrl-C cut its join): the mapping goes with the view
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


# --------------------------------------------------------------------------------------------------
# The worker process
# --------------------------------------------------------------------------------------------------
def _pack(item, buf: mmap.mmap, slot: int, slot_bytes: int):
    """``item`` with its depth and colour arrays written into ``slot`` (recorded in ``item._shm``) where
    they fit together; else ``item`` as it is, to be pickled whole."""
    arrays = [(name, getattr(item, name, None)) for name in _ARRAYS]
    arrays = [(name, np.ascontiguousarray(a)) for name, a in arrays if isinstance(a, np.ndarray)]
    if not arrays or sum(_aligned(a.nbytes) for _, a in arrays) > slot_bytes:
        return item
    offset, packed = 0, []
    for name, a in arrays:
        start = slot * slot_bytes + offset
        np.frombuffer(buf, dtype=np.uint8, count=a.nbytes, offset=start)[:] = a.reshape(-1).view(np.uint8)
        packed.append((name, offset, a.shape, a.dtype.str))
        setattr(item, name, None)
        offset += _aligned(a.nbytes)
    item._shm = packed
    return item


def _main(sock_fd: int, mem_fd: int) -> None:
    for sig in (signal.SIGINT, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)
    try:
        import cv2

        cv2.setNumThreads(1)  # one decode per process: the processes are the parallelism
    except Exception:
        pass
    conn = Connection(sock_fd)
    try:
        slot_bytes, payload = pickle.loads(conn.recv_bytes())
        try:
            dataset, failed = pickle.loads(payload), None
        except BaseException as exc:  # (a dataset that cannot be opened again here): every frame says so
            dataset, failed = None, exc
        buf = mmap.mmap(mem_fd, os.fstat(mem_fd).st_size)
        sent = 0  # first kernel launches (ti_fusion.frontend.CLOCK) already reported to the caller
        while True:
            i, slot = conn.recv()
            start = time.perf_counter()
            try:
                if failed is not None:
                    raise failed
                item = dataset[i]
                message = ("frame", i, _pack(item, buf, slot, slot_bytes), (time.perf_counter() - start) * 1e3)
            except BaseException as exc:  # raised in the caller at item i
                message = ("error", i, _picklable(exc), 0.0)
            clock = sys.modules.get("ti_fusion.frontend")
            launches = clock.CLOCK.launches[sent:] if clock is not None else []
            sent += len(launches)
            try:
                conn.send((*message, launches))
            except (pickle.PicklingError, TypeError, AttributeError) as exc:
                conn.send(("error", i, RuntimeError(f"frame {i} could not be handed over: {exc}"), 0.0, launches))
    except (EOFError, OSError, KeyboardInterrupt):  # the caller closed its end, or is gone
        return


def _picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
