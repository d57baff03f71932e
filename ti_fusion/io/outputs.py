"""Where a run writes: its output folder, ``summary.json`` and the terminal progress bar."""

from __future__ import annotations

import json
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Iterable, Iterator, TypeVar

import numpy as np

T = TypeVar("T")


def default_out_dir(command: str) -> Path:
    return Path("logs") / f"{command}-{datetime.now().strftime('%Y%m%d-%H%M%S')}"


class RunDir:
    """The output folder of one run (``--out``, default ``logs/<command>-<timestamp>/``)."""

    def __init__(self, command: str, out: str | Path | None = None):
        self.command = command
        self.path = Path(out) if out else default_out_dir(command)
        self.path.mkdir(parents=True, exist_ok=True)
        self.t_start = time.perf_counter()

    def file(self, name: str) -> Path:
        return self.path / name

    def write_summary(self, summary: dict) -> Path:
        path = self.file("summary.json")
        path.write_text(json.dumps(jsonable(summary), indent=2) + "\n")
        return path


def base_summary(command: str, frames: int, wall_s: float, ms_per_stage: dict) -> dict:
    """The fields every summary.json has."""
    return {
        "command": command,
        "frames": int(frames),
        "wall_s": round(float(wall_s), 3),
        "fps": round(frames / wall_s, 3) if wall_s > 0 else None,
        "ms_per_stage": ms_per_stage,
    }


def jsonable(obj):
    """Plain JSON types: NumPy scalars/arrays unpacked, NaN/inf → null (JSON has no NaN), paths as text."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def progress(items: Iterable[T], total: int, desc: str, enabled: bool = True) -> Iterator[T]:
    """A one-line progress bar on stderr (only on a terminal, and not with --quiet)."""
    enabled = enabled and sys.stderr.isatty()
    t0 = time.perf_counter()
    for i, item in enumerate(items):
        yield item
        if enabled:
            done = i + 1
            rate = done / max(time.perf_counter() - t0, 1e-9)
            bar = "#" * int(30 * done / max(total, 1))
            sys.stderr.write(f"\r{desc} [{bar:<30}] {done}/{total} {rate:5.1f} it/s")
            sys.stderr.flush()
    if enabled:
        sys.stderr.write("\n")
