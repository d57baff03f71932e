"""The run's trajectory as dense SLAM keeps it: each frame's camera-to-world pose and the keyframe it is
anchored to, so that a loop closure can move every pose with its keyframe through one verb (``correct``)."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ti_fusion.geometry import renormalize


class PoseStore:
    """Poses in frame order (a list's ``append``, ``[i]``, ``len`` and iteration), each with its frame's
    index and an anchor.

    The store keeps its own copy of every pose: ``correct`` moves those, and nothing else, so a reader
    takes the current trajectory from here (``by_frame``), never from an array it was handed earlier.
    A frame is anchored to the latest keyframe when it is appended (keyframe 0 before the first);
    ``start_keyframe(k)`` anchors the frame just appended, and the frames after it, to keyframe k.
    """

    def __init__(self):
        self._poses: list[np.ndarray | None] = []
        self._frames: list[int] = []
        self._stamps: list[float] = []
        self._anchors: list[int] = []
        self.keyframe = 0  # the anchor of the next frame appended

    def append(self, pose: np.ndarray | None, frame: int, timestamp: float = float("nan")) -> None:
        """``pose`` of frame ``frame`` (its index in the run, taken at ``timestamp``), copied."""
        self._poses.append(None if pose is None else np.array(pose, dtype=np.float64))
        self._frames.append(int(frame))
        self._stamps.append(float(timestamp))
        self._anchors.append(self.keyframe)

    def start_keyframe(self, keyframe: int) -> None:
        """The frame appended last became keyframe ``keyframe``: it and the frames after it move with it."""
        if not self._poses:
            raise ValueError("start_keyframe before any pose")
        self._anchors[-1] = self.keyframe = int(keyframe)

    def correct(self, corrections: np.ndarray) -> int:
        """Every pose by its keyframe's world-frame correction C_k = T_k,new · T_k,old⁻¹ (``corrections``
        K×4×4; frames anchored to k ≥ K stay); returns how many poses moved."""
        corrections = np.asarray(corrections, dtype=np.float64)
        moved = 0
        for i, (pose, k) in enumerate(zip(self._poses, self._anchors)):
            if pose is not None and k < len(corrections):
                self._poses[i] = renormalize(corrections[k] @ pose)
                moved += 1
        return moved

    def by_frame(self) -> dict[int, np.ndarray]:
        """Frame index → a copy of its current pose (frames without a pose left out)."""
        return {f: p.copy() for f, p in zip(self._frames, self._poses) if p is not None}

    def posed(self) -> list[tuple[int, float, np.ndarray, int]]:
        """(frame, timestamp, current pose (not a copy), anchor) of every frame with a pose, in order."""
        return [(f, t, p, k) for f, t, p, k in zip(self._frames, self._stamps, self._poses, self._anchors)
                if p is not None]

    def pose_of(self, frame: int) -> np.ndarray | None:
        """The current pose of frame ``frame`` (the last one appended with that index), or None."""
        for f, p in zip(reversed(self._frames), reversed(self._poses)):
            if f == frame:
                return p
        return None

    @property
    def anchors(self) -> list[int]:
        return list(self._anchors)

    def __len__(self) -> int:
        return len(self._poses)

    def __getitem__(self, index):
        return self._poses[index]

    def __iter__(self) -> Iterator[np.ndarray | None]:
        return iter(self._poses)
