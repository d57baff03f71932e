#!/usr/bin/env python3
"""Where a run's CPU time goes, by stage and by thread: the main thread (the loop's Python and Taichi's kernel
launches, during which Taichi's CPU workers run the kernel and the main thread waits) against every other
thread of the process (Taichi's workers, the log's writer, the outputs' threads).

    python scripts/stage_threads.py [ti-fusion slam options, e.g. ../shared/data/redkitchen-7scenes --frames 200]

Runs ``ti-fusion slam`` in this process with each ``StageTimer`` stage (pyramid, track, fuse, load, export, ...),
the first two frames and the whole frame loop timed three ways (the command less the loop is what comes
before and after it): wall-clock, the main thread's CPU time (its ``schedstat``) and the
process's CPU time (all threads, ended ones included); "other" is the difference. The reader processes are not
in either (the last line gives the CPU time of the child processes that ended). On a machine shared with other
work the wall-clock column moves with the load; the two CPU columns move much less. The main thread's CPU
time is work no other thread can take over: on an idle machine a stage takes at least that long, and at most
main + other / 2 on two cores when Taichi's workers split each kernel evenly.
"""

from __future__ import annotations

import collections
import os
import sys
import threading
import time
from contextlib import contextmanager

import ti_fusion.slam.pipeline as pipeline
import ti_fusion.timing as timing

MAIN = threading.get_native_id()
main_s: dict[str, float] = collections.defaultdict(float)
other_s: dict[str, float] = collections.defaultdict(float)
wall_s: dict[str, float] = collections.defaultdict(float)
calls: dict[str, int] = collections.defaultdict(int)


def _snapshot() -> tuple[float, float, float]:
    """(wall s, the main thread's CPU s, the process's CPU s)."""
    with open(f"/proc/self/task/{MAIN}/schedstat") as f:
        main = int(f.read().split()[0]) / 1e9
    return time.perf_counter(), main, time.process_time()


@contextmanager
def _counted(name: str):
    w0, m0, p0 = _snapshot()
    try:
        yield
    finally:
        w1, m1, p1 = _snapshot()
        wall_s[name] += w1 - w0
        main_s[name] += m1 - m0
        other_s[name] += (p1 - p0) - (m1 - m0)
        calls[name] += 1


_stage = timing.StageTimer.stage


@contextmanager
def stage(self, name, sync=None, into=None):
    with _counted(name), _stage(self, name, sync, into):
        yield


_loop = pipeline.Pipeline._loop


def loop(self, sinks):
    register, done = self.step.register_frame, []

    def first_two(frame):  # the first two frames apart: with a warm cache, mostly the kernels' first launches
        if len(done) >= 2:
            return register(frame)
        with _counted("first two"):
            done.append(register(frame))
            return done[-1]

    self.step.register_frame = first_two
    with _counted("the loop"):
        return _loop(self, sinks)


def main() -> int:
    timing.StageTimer.stage = stage
    pipeline.Pipeline._loop = loop
    from ti_fusion.cli.main import main as cli

    with _counted("command"):
        code = cli(["slam", *sys.argv[1:]])
    print(f"{'stage':<10} {'calls':>6} {'wall s':>8} {'main s':>8} {'other s':>8} {'cores':>6}")
    for name in sorted(wall_s, key=lambda k: -wall_s[k]):
        cpu = main_s[name] + other_s[name]
        print(f"{name:<10} {calls[name]:>6} {wall_s[name]:8.2f} {main_s[name]:8.2f} {other_s[name]:8.2f} "
              f"{cpu / max(wall_s[name], 1e-9):6.2f}")
    times = os.times()
    print(f"ended child processes (the frame readers): {times.children_user + times.children_system:.2f} s of CPU; "
          f"load average {os.getloadavg()[0]:.1f}")
    return code


if __name__ == "__main__":
    sys.exit(main())
