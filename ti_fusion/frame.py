"""The RGB-D frame that datasets hand out and tracking, mapping and SLAM consume (a leaf module, so that
tracking need not import the dataset loaders)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ti_fusion.camera import Intrinsics


@dataclass
class Frame:
    """One RGB-D frame as every loader yields it.

    depth: float32 H×W in metres, 0 = invalid.
    color: uint8 H×W×3 RGB, or None when the set has no colour.
    gt_pose: float64 4×4 camera-to-world ground truth, or None.
    color_registered: pixel (u, v) of ``color`` sees the point of ``depth`` at (u, v) (photometric tracking
    uses colour only then); set by the dataset (``Dataset.color_for_tracking``).
    """

    index: int
    timestamp: float
    depth: np.ndarray
    intrinsics: Intrinsics
    color: np.ndarray | None = None
    gt_pose: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    color_registered: bool = False
