"""Per-stage wall-clock timing (``with timer.stage("track"): ...``) and the age of the process."""

from __future__ import annotations

import os
import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np


class StageTimer:
    """Collects milliseconds per named stage, one sample per ``stage`` block."""

    def __init__(self):
        self.samples: dict[str, list[float]] = defaultdict(list)
        self.last: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            self.samples[name].append(ms)
            self.last[name] = ms

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


def process_age_s() -> float | None:
    """Seconds since this process started, from the kernel's record of its start (Linux; 10 ms steps), so
    that the interpreter's start and every import count; None where /proc is missing."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return round(uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"), 2)  # field 22: start, in ticks
    except (OSError, ValueError, IndexError):
        return None
