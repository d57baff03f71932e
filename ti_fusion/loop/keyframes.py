"""Keyframes: when the loop closer keeps one (by motion and by overlap with the last one), and what it keeps.

A keyframe holds its pose (the current estimate, corrected when a loop is applied), its ORB
features (``ti_fusion.tracking.features``: descriptors for place recognition, 3D points for PnP), its depth
at the map's resolution (the compact summary that dense verification rebuilds vertex and normal maps from)
and a coarse grid of its 3D points (the overlap test).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import LoopConfig
from ti_fusion.geometry import invert, pose_error
from ti_fusion.tracking.features import FrameFeatures

# The overlap test's grid: every SAMPLE_STEP-th pixel of the summary depth in u and v.
SAMPLE_STEP = 8


@dataclass
class Keyframe:
    """One keyframe. ``pose``: camera-to-world 4×4 float64, the current estimate (``LoopClosure`` corrects it)."""

    id: int  # 0, 1, 2, ... in creation order: the anchor written into the surfels fused after it
    frame: int  # the frame's index in the run
    timestamp: float
    pose: np.ndarray
    features: FrameFeatures  # ORB keypoints of the colour image, lifted with the frame's depth
    intrinsics: Intrinsics  # of the full-resolution depth (the features' pixel grid)
    depth: np.ndarray  # float32 H×W metres at the map's resolution (0 = invalid): the dense summary
    depth_intrinsics: Intrinsics  # of ``depth``
    samples: np.ndarray  # M×3 camera-frame points of ``depth`` on a coarse grid

    @property
    def centre(self) -> np.ndarray:
        """The camera centre in the world frame."""
        return self.pose[:3, 3].copy()


def grid_points(depth: np.ndarray, intrinsics: Intrinsics, step: int = SAMPLE_STEP) -> np.ndarray:
    """M×3 camera-frame points of the valid pixels of ``depth`` on a grid of every ``step``-th pixel."""
    v, u = np.mgrid[step // 2:depth.shape[0]:step, step // 2:depth.shape[1]:step]
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    u, v, z = u[ok], v[ok], z[ok]
    K = intrinsics
    return np.column_stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z])


def overlap(keyframe: Keyframe, pose: np.ndarray) -> float:
    """Fraction of ``keyframe``'s grid points that a camera at ``pose`` (same intrinsics) sees in front of it
    and inside its image: 1 at the keyframe itself, falling as the camera moves away or turns."""
    if len(keyframe.samples) == 0:
        return 0.0
    T = invert(pose) @ keyframe.pose  # keyframe camera → current camera
    p = keyframe.samples @ T[:3, :3].T + T[:3, 3]
    K = keyframe.depth_intrinsics
    z = p[:, 2]
    front = z > 0.05
    u = K.fx * p[front, 0] / z[front] + K.cx
    v = K.fy * p[front, 1] / z[front] + K.cy
    inside = (u >= 0) & (u <= K.width - 1) & (v >= 0) & (v <= K.height - 1)
    return float(np.count_nonzero(inside)) / len(keyframe.samples)


class KeyframeSelector:
    """Says whether a tracked frame becomes a keyframe: the first one does; later ones when the camera has
    moved or turned enough since the last keyframe, or sees too little of it, and not sooner than
    ``keyframe_min_frames`` frames after it."""

    def __init__(self, config: LoopConfig):
        self.config = config

    def why(self, last: Keyframe | None, pose: np.ndarray, frame: int) -> str | None:
        """The reason ``frame`` at ``pose`` is a keyframe ("first", "moved", "turned", "overlap"), or None."""
        cfg = self.config
        if last is None:
            return "first"
        if frame - last.frame < cfg.keyframe_min_frames:
            return None
        rot_deg, trans_m = pose_error(pose, last.pose)
        if trans_m > cfg.keyframe_translation:
            return "moved"
        if rot_deg > cfg.keyframe_rotation_deg:
            return "turned"
        if overlap(last, pose) < cfg.keyframe_overlap:
            return "overlap"
        return None
