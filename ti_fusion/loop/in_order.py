"""Functions run one after another on threads beside the caller's, in the order handed over (``InOrder``).

    queue = InOrder("ti-fusion-loop-closure")
    queue.submit(lambda: database.add(keyframe))             # what fails is raised by the next settle
    job = queue.submit(lambda: look_ahead(frame, ...), quiet=True)
    ahead = queue.take(job)                                  # its result, or None where it failed
    queue.settle()                                           # every function handed over is done

Each function gets a daemon thread of its own that first waits for the one handed over before it: a single-worker
``ThreadPoolExecutor`` would run them in order too, but the interpreter's exit waits for its worker, and what is
still running here when the process ends is read by no one. Loop closure is its user (``LoopClosure._beside``).
"""

from __future__ import annotations

import threading
from typing import Callable


class Job:
    """One function handed to ``InOrder``: it runs on its own thread once the one handed over before it is done."""

    def __init__(self, fn: Callable[[], object], previous: Job | None, quiet: bool, name: str):
        self.quiet = quiet  # its failure is the taker's to handle (``InOrder.take``), not raised by ``settle``
        self.cancelled = False  # set before it starts: it does not run (``InOrder.drop``)
        self.result = self.error = None
        self._fn, self._previous = fn, previous
        # a daemon: what is left running when the process ends is read by nothing (its user reads it settled)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        if self._previous is not None:
            self._previous.wait()
            self._previous = None
        fn, self._fn = self._fn, None  # (a cancelled job keeps no frame alive either)
        if self.cancelled:
            return
        try:
            self.result = fn()
        except BaseException as exc:  # handed to the caller's thread (``InOrder.settle``, ``InOrder.take``)
            self.error = exc
        if self.cancelled:  # cancelled while it ran: ``InOrder.drop`` cleared the result before it was set
            self.result = None

    def wait(self) -> None:
        self._thread.join()


class InOrder:
    """Functions run one after another, in the order handed over, each on a thread of its own named ``name``."""

    def __init__(self, name: str):
        self.name = name
        self._jobs: list[Job] = []  # handed over and not yet waited for by ``settle`` or ``take``

    def submit(self, fn: Callable[[], object], quiet: bool = False) -> Job:
        """Run ``fn`` after the functions handed over before it. ``quiet``: what it raises is left to ``take``."""
        job = Job(fn, self._jobs[-1] if self._jobs else None, quiet, self.name)
        self._jobs.append(job)
        return job

    def settle(self, upto: Job | None = None) -> None:
        """Wait for every function handed over (up to ``upto`` and it), and raise the first failure of one not
        ``quiet``."""
        end = len(self._jobs) if upto is None else self._jobs.index(upto) + 1
        # each job forgotten only once waited for: a Ctrl-C inside a wait leaves the rest for the next settle
        # (nothing reads what a function still running works on)
        failure = None
        for _ in range(end):
            job = self._jobs[0]
            job.wait()
            del self._jobs[0]
            if failure is None and not job.quiet and job.error is not None:
                failure = job.error
        if failure is not None:
            raise failure

    def drop(self, job: Job) -> None:
        """``job`` (``quiet``) will not be taken: it does not start if it has not, keeps no result, and leaves the
        queue once done, so that functions whose results go unused (a lost stretch's looks ahead: one a frame)
        add nothing."""
        job.cancelled, job.result = True, None
        # those dropped and done: nothing to wait for, and their failures are no one's (``quiet``)
        self._jobs = [j for j in self._jobs if not (j.quiet and j.cancelled and not j._thread.is_alive())]

    def take(self, job: Job):
        """``job``'s result once it and every function handed over before it are done; None where it failed or
        was cancelled (its work is then done again where it is needed, which raises as it would have)."""
        if job in self._jobs:
            self.settle(upto=job)
        return None if job.error is not None or job.cancelled else job.result
