"""Loop closure's work that needs no Taichi and no pose, on threads beside the loop's (``LoopClosure`` hands it over).

    queue = InOrder()
    queue.submit(lambda: database.add(keyframe))             # read by the next keyframe's query only
    job = queue.submit(lambda: look_ahead(frame, ...), quiet=True)
    ahead = queue.take(job)                                  # its Ahead, or None where it failed

Two kinds of work, each on a thread of its own, one after another in the order handed over:
- a keyframe's addition to place recognition's database (``PlaceDatabase.add``: its word counts, and at each
  doubling of the keyframes the vocabulary learnt again), which only the next keyframe's query reads
  (``LoopClosure.database`` waits for the additions handed over before it);
- for a frame that the motion model's guess makes a keyframe (``look_ahead``), what verifying it needs of its
  images alone: its ORB features, place recognition's candidates, and each candidate's pre-check and PnP
  (``LoopVerifier.check_features``). None of it reads the frame's pose: the keyframe test on the tracked pose
  decides where it did, the same functions of the same inputs give the same answers, and a frame the guess
  got wrong is done on the loop's thread as before.

Why threads: OpenCV's ORB, matching and PnP RANSAC and NumPy's larger loops release the GIL, and on the CPU backend
the loop's thread holds it through each kernel launch while Taichi's workers wait on the loop's Python, so this
work fills the core the loop's Python leaves idle instead of following tracking and fusion on the loop's thread
(docs/PERFORMANCE.md, "Loop closure beside the frame").
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ti_fusion.loop.keyframes import Keyframe
from ti_fusion.loop.place_recognition import Place, PlaceDatabase
from ti_fusion.loop.verification import FeatureCheck, LoopVerifier
from ti_fusion.tracking.features import FrameFeatures, extract_features


class Job:
    """One function handed to ``InOrder``: it runs on its own thread once the one handed over before it is done."""

    def __init__(self, fn: Callable[[], object], previous: Job | None, quiet: bool):
        self.quiet = quiet  # its failure is the taker's to handle (``InOrder.take``), not raised by ``settle``
        self.cancelled = False  # set before it starts: it does not run (``InOrder.drop``)
        self.result = self.error = None
        self._fn, self._previous = fn, previous
        # a daemon: what is left running when the process ends is read by nothing (the database is read settled)
        self._thread = threading.Thread(target=self._run, name="ti-fusion-loop-closure", daemon=True)
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
        except BaseException as exc:  # handed to the loop's thread (``InOrder.settle``, ``InOrder.take``)
            self.error = exc
        if self.cancelled:  # cancelled while it ran: ``InOrder.drop`` cleared the result before it was set
            self.result = None

    def wait(self) -> None:
        self._thread.join()


class InOrder:
    """Functions run one after another, in the order handed over, each on a thread of its own."""

    def __init__(self):
        self._jobs: list[Job] = []  # handed over and not yet waited for by ``settle`` or ``take``

    def submit(self, fn: Callable[[], object], quiet: bool = False) -> Job:
        """Run ``fn`` after the functions handed over before it. ``quiet``: what it raises is left to ``take``."""
        job = Job(fn, self._jobs[-1] if self._jobs else None, quiet)
        self._jobs.append(job)
        return job

    def settle(self, upto: Job | None = None) -> None:
        """Wait for every function handed over (up to ``upto`` and it), and raise the first failure of one not
        ``quiet``."""
        end = len(self._jobs) if upto is None else self._jobs.index(upto) + 1
        # each job forgotten only once waited for: a Ctrl-C inside a wait leaves the rest for the next settle
        # (the database is not read while an addition may still run on it)
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
        queue once done, so that frames whose look ahead goes unused (a lost stretch: one a frame) add nothing."""
        job.cancelled, job.result = True, None
        # those dropped and done: nothing to wait for, and their failures are no one's (``quiet``)
        self._jobs = [j for j in self._jobs if not (j.quiet and j.cancelled and not j._thread.is_alive())]

    def take(self, job: Job):
        """``job``'s result once it and every function handed over before it are done; None where it failed or
        was cancelled (its work is then done again where it is needed, which raises as it would have)."""
        if job in self._jobs:
            self.settle(upto=job)
        return None if job.error is not None or job.cancelled else job.result


@dataclass
class Ahead:
    """A frame's look ahead (``look_ahead``): for its keyframe, if the tracked pose makes it one."""

    frame: int  # the frame's index
    features: FrameFeatures  # its ORB features, lifted with its depth
    places: list[Place]  # place recognition's candidates, best first
    checks: list[FeatureCheck]  # each candidate's pre-check and PnP, in the same order


def look_ahead(frame, keyframe_id: int, vo, orb, database: PlaceDatabase, keyframes: list[Keyframe],
               verifier: LoopVerifier) -> Ahead:
    """What ``LoopClosure.after_frame`` would compute of ``frame`` as keyframe ``keyframe_id`` before its dense ICP:
    its features (``extract_features`` with ``vo`` and ``orb``), the database's candidates for it, and each
    candidate's ``check_features``, all of the same inputs as there (the database as the keyframes before it
    left it)."""
    features = extract_features(frame, vo, orb)
    query = Keyframe(keyframe_id, frame.index, frame.timestamp, np.eye(4), features, frame.intrinsics, None, None,
                     np.zeros((0, 3)))
    places = database.query(query)
    return Ahead(frame.index, features, places,
                 [verifier.check_features(query, keyframes[place.keyframe]) for place in places])
