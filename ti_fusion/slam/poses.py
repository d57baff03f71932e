"""The run's trajectory as dense SLAM keeps it: each frame's camera-to-world pose and the keyframe it is
anchored to, so that a loop closure can move every pose with its keyframe through one verb (``correct``)."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ti_fusion.geometry import renormalize


class PoseStore:
    """Poses in frame order (a list's ``append``, ``[i]``, ``len`` and iteration) with an anchor each.

    A frame is anchored to the latest keyframe when it is appended (keyframe 0 before the first);
    ``start_keyframe(k)`` anchors the frame just appended, and the frames after it, to keyframe k.
    ``correct`` moves the stored arrays in place: the pose a ``FrameResult`` holds is the stored array, so
    the run's results and the trajectory written from them see the correction.
    """

    def __init__(self):
        self._poses: list[np.ndarray | None] = []
        self._anchors: list[int] = []
        self.keyframe = 0  # the anchor of the next frame appended

    def append(self, pose: np.ndarray | None) -> None:
        self._poses.append(pose)
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
        seen: set[int] = set()  # an array appended twice (a test's list, a caller's alias) moves once
        for pose, k in zip(self._poses, self._anchors):
            if pose is not None and k < len(corrections) and id(pose) not in seen:
                seen.add(id(pose))
                pose[:] = renormalize(corrections[k] @ pose)
        return len(seen)

    @property
    def anchors(self) -> list[int]:
        return list(self._anchors)

    def __len__(self) -> int:
        return len(self._poses)

    def __getitem__(self, index):
        return self._poses[index]

    def __iter__(self) -> Iterator[np.ndarray | None]:
        return iter(self._poses)
