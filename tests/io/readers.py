"""Datasets for the reader-process tests (``tests/io/test_prefetch.py``): small, picklable, and importable
without Taichi, since a reader process imports this module to unpickle them."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError
from ti_fusion.frame import Frame
from ti_fusion.io.datasets.synthetic import SyntheticDataset


class Items:
    """``n`` items (item i is i). Reading item ``bad`` raises ``error``; reading item ``die_at`` kills the
    reading process (SIGKILL, as the kernel's OOM killer would). Each read appends its index to ``log``."""

    reads_in_process = True
    concurrent_reads = True

    def __init__(self, n: int, log: str | Path | None = None, bad: int = -1, error: BaseException | None = None,
                 die_at: int = -1, slow_every: int = 0, sleep_s: float = 0.0):
        self.n, self.log, self.bad, self.error, self.die_at = n, log, bad, error, die_at
        self.slow_every, self.sleep_s = slow_every, sleep_s

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        if self.log is not None:
            with open(self.log, "a") as f:  # one short append per read: whole lines from several processes
                f.write(f"{i}\n")
        if i == self.die_at:
            os.kill(os.getpid(), signal.SIGKILL)
        if i == self.bad:
            raise self.error
        if self.sleep_s or (self.slow_every and i % self.slow_every == 0):
            time.sleep(self.sleep_s or 0.001)  # reads of uneven length: the order must not depend on them
        return i


def read_indices(log: Path) -> list[int]:
    return [int(line) for line in Path(log).read_text().split()] if Path(log).exists() else []


class Frames:
    """Frames of ``width`` × ``height`` with depth and colour made from their index (``big``: a colour image
    of four times the pixels, more than a shared-memory slot holds)."""

    reads_in_process = True
    concurrent_reads = True

    def __init__(self, n: int, width: int = 64, height: int = 48, big: int = -1):
        self.n, self.big = n, big
        self.intrinsics = Intrinsics(50.0, 50.0, width / 2, height / 2, width, height)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> Frame:
        K = self.intrinsics
        rng = np.random.default_rng(i)
        scale = 2 if i == self.big else 1
        depth = rng.random((K.height, K.width), dtype=np.float32)
        color = rng.integers(0, 256, (K.height * scale, K.width * scale, 3), dtype=np.uint8)
        return Frame(index=i, timestamp=float(i), depth=depth, intrinsics=K, color=color, gt_pose=np.eye(4),
                     meta={"i": i})



class Synthetic(SyntheticDataset):
    """The synthetic sequence, whose reading of frame ``bad`` raises an ``InputError`` and of frame ``die_at``
    kills the reading process (SIGKILL)."""

    def __init__(self, *args, bad: int = -1, die_at: int = -1, **kwargs):
        super().__init__(*args, **kwargs)
        self.bad, self.die_at = bad, die_at

    def __getitem__(self, i: int):
        if i == self.die_at:
            os.kill(os.getpid(), signal.SIGKILL)
        if i == self.bad:
            raise InputError(f"frame {i}", "cannot render the frame")
        return super().__getitem__(i)
