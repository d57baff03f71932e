"""Place recognition: which earlier keyframes see the place the current one sees, by appearance alone.

Every keyframe's ORB descriptors go into one database. A query descriptor's nearest neighbours among all
the eligible keyframes' descriptors (brute-force Hamming k-NN, ``cv2.BFMatcher``) each vote for their
keyframe when closer than ``loop.max_hamming`` bits, at most one vote per query descriptor and keyframe;
a keyframe's score is its votes over the query's descriptor count. This is the nearest-neighbour search of
a bag of binary words without the vocabulary (no training set to build one from, and at the few hundred
keyframes of an indoor sequence the exhaustive search costs a few milliseconds). The search runs over every
keyframe at least ``loop.min_frame_gap`` frames older than the query, wherever the pose estimate puts it.

The cheap geometric pre-check (``precheck``): of the good matches between the two keyframes whose points
have depth in both, how many agree with the largest set of matches whose pairwise 3D distances are
preserved (a rigid motion keeps distances; matches of a different place with a similar texture do not).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ti_fusion.config import LoopConfig, VOConfig
from ti_fusion.loop.keyframes import Keyframe
from ti_fusion.tracking.features import match_features

# Neighbours per query descriptor: the same place is usually seen by a few consecutive keyframes.
NEIGHBOURS = 8
# The pre-check looks at this many matches at most (its cost grows with the square).
PRECHECK_MATCHES = 300


@dataclass
class Place:
    """An earlier keyframe that may see the same place: its id, score (fraction of the query's descriptors
    that voted for it) and votes."""

    keyframe: int
    score: float
    votes: int


class PlaceDatabase:
    """ORB descriptors of every keyframe; ``query`` finds the earlier keyframes that look like a new one."""

    def __init__(self, config: LoopConfig):
        self.config = config
        self._descriptors: list[np.ndarray] = []
        self._owners: list[np.ndarray] = []
        self._frames: list[int] = []  # frame index of each keyframe, by id
        self._stacked: tuple[np.ndarray, np.ndarray] | None = None
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, keyframe: Keyframe) -> None:
        """Add a keyframe (ids in creation order: 0, 1, 2, ...)."""
        if keyframe.id != len(self._frames):
            raise ValueError(f"keyframe {keyframe.id} added as number {len(self._frames)}")
        d = keyframe.features.descriptors
        d = np.zeros((0, 32), np.uint8) if d is None else d
        self._descriptors.append(d)
        self._owners.append(np.full(len(d), keyframe.id, np.int32))
        self._frames.append(keyframe.frame)
        self._stacked = None

    def query(self, keyframe: Keyframe) -> list[Place]:
        """Earlier keyframes at least ``min_frame_gap`` frames before ``keyframe`` with a score of at least
        ``min_score``, best first, ``candidates`` of them at most."""
        cfg = self.config
        eligible = int(np.searchsorted(np.asarray(self._frames), keyframe.frame - cfg.min_frame_gap, side="right"))
        q = keyframe.features.descriptors
        if eligible == 0 or q is None or len(q) == 0:
            return []
        if self._stacked is None:
            self._stacked = (np.concatenate(self._descriptors), np.concatenate(self._owners))
        descriptors, owners = self._stacked
        n = int(sum(len(d) for d in self._descriptors[:eligible]))  # keyframes are stored in frame order
        if n == 0:
            return []
        neighbours = self._matcher.knnMatch(q, descriptors[:n], k=min(NEIGHBOURS, n))
        votes = np.zeros(eligible, np.int64)
        for row in neighbours:
            hit = {owners[m.trainIdx] for m in row if m.distance < cfg.max_hamming}
            for k in hit:
                votes[k] += 1
        scores = votes / len(q)
        order = np.argsort(-scores, kind="stable")
        return [Place(int(k), float(scores[k]), int(votes[k])) for k in order[:cfg.candidates]
                if scores[k] >= cfg.min_score]


def precheck(a: Keyframe, b: Keyframe, vo: VOConfig, tolerance_m: float) -> int:
    """The size of the largest group of good ORB matches between ``a`` and ``b`` (both lifted to 3D) whose
    pairwise distances agree within ``tolerance_m``, as the best match's count of agreeing partners plus
    itself: a lower bound on the matches one rigid motion can explain."""
    _, good = match_features(a.features, b.features, vo)
    if not good:
        return 0
    ia = np.array([m.queryIdx for m in good])
    ib = np.array([m.trainIdx for m in good])
    pa, pb = a.features.points[ia], b.features.points[ib]
    ok = np.isfinite(pa).all(axis=1) & np.isfinite(pb).all(axis=1)
    pa, pb = pa[ok][:PRECHECK_MATCHES], pb[ok][:PRECHECK_MATCHES]
    if len(pa) < 2:
        return int(len(pa))
    da = np.linalg.norm(pa[:, None] - pa[None], axis=2)
    db = np.linalg.norm(pb[:, None] - pb[None], axis=2)
    agree = np.abs(da - db) < tolerance_m
    best = int(np.argmax(agree.sum(axis=1)))
    group = np.flatnonzero(agree[best])
    # keep only members that agree with most of the group, so that two clusters do not count as one
    inner = agree[np.ix_(group, group)].sum(axis=1) >= 0.5 * len(group)
    return int(np.count_nonzero(inner))
