"""Wall-clock timing, the one place for it: per-stage samples (``with timer.stage("track"): ...``), a
``Stopwatch`` for one measurement (``with Stopwatch(result.ms, "log"): ...``, ``lap()``) and the age of the
process."""

from __future__ import annotations

import os
import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Callable

import numpy as np


class Stopwatch:
    """Milliseconds from its start: ``ms`` so far, ``lap()`` since the last lap. As a context manager it starts
    at the block and, at its end, writes the block's milliseconds into ``into[name]`` where given."""

    def __init__(self, into: dict[str, float] | None = None, name: str | None = None):
        self.into, self.name = into, name
        self.t0 = self._lap = time.perf_counter()

    @property
    def ms(self) -> float:
        return (time.perf_counter() - self.t0) * 1e3

    def lap(self) -> float:
        now = time.perf_counter()
        ms, self._lap = (now - self._lap) * 1e3, now
        return ms

    def __enter__(self) -> "Stopwatch":
        self.t0 = self._lap = time.perf_counter()
        return self

    def __exit__(self, *exc) -> bool:
        if self.into is not None:
            self.into[self.name] = self.ms
        return False


class StageTimer:
    """Collects milliseconds per named stage, one sample per ``stage`` block."""

    def __init__(self):
        self.samples: dict[str, list[float]] = defaultdict(list)
        self.last: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str, sync: Callable[[], None] | None = None, into: dict[str, float] | None = None):
        """Times the block. ``sync`` runs before and after it (``ti.sync``: a GPU's queued work then counts
        where it is done, not where it is waited for); ``into`` also gets the milliseconds under ``name``."""
        if sync is not None:
            sync()
        watch = Stopwatch()
        try:
            yield
        finally:
            if sync is not None:
                sync()
            self.add(name, watch.ms)
            if into is not None:
                into[name] = self.last[name]

    def add(self, name: str, ms: float) -> None:
        self.samples[name].append(ms)
        self.last[name] = ms

    def summary(self, skip_first: int = 0) -> dict[str, dict[str, float]]:
        """{stage: {median, mean, max, total}} in ms; ``skip_first`` drops warm-up (JIT) samples."""
        out = {}
        for name, values in self.samples.items():
            v = np.asarray(values[skip_first:] if len(values) > skip_first else values)
            out[name] = {
                "median": round(float(np.median(v)), 3),
                "mean": round(float(v.mean()), 3),
                "max": round(float(v.max()), 3),
                "total": round(float(v.sum()), 3),
            }
        return out


@contextmanager
def timed_stage(timer: StageTimer | None, name: str, **kwargs):
    """``timer.stage(name, **kwargs)``, or nothing where there is no timer."""
    if timer is None:
        yield
        return
    with timer.stage(name, **kwargs):
        yield


# A script that sets up the environment and then execs the command (scripts/run.sh) keeps its process, which the
# kernel dates from the script's start: the script says when it exec'd (seconds since the epoch), read once here.
_EXEC_AT = os.environ.pop("TI_FUSION_EXEC_AT", None)


def process_age_s() -> float | None:
    """Seconds since this process started, from the kernel's record of its start (Linux; 10 ms steps), so
    that the interpreter's start and every import count; from the exec where a script said when it exec'd
    (``TI_FUSION_EXEC_AT``), as a set-up before it is not the command's; None where /proc is missing."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        age = round(uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"), 2)  # field 22: start, in ticks
    except (OSError, ValueError, IndexError):
        return None
    try:
        since_exec = time.time() - float(_EXEC_AT)
    except (TypeError, ValueError):
        return age
    return round(since_exec, 2) if 0.0 <= since_exec <= age else age
