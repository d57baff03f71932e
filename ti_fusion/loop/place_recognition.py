"""Place recognition: which earlier keyframes see the place the current one sees, by appearance alone.

A bag of binary words (Gálvez-López and Tardós's DBoW2 in miniature): each ORB descriptor is quantised to
its nearest word of a vocabulary (Hamming distance), a keyframe becomes a histogram of words weighted by
tf-idf, and its similarity to another is DBoW2's L1 score, 1 − ½‖a/|a| − b/|b|‖₁ (0 = no word in common,
1 = the same histogram). The query scores every earlier keyframe at least ``loop.min_frame_gap`` frames
older, wherever the pose estimate puts it (a K × V table: microseconds per keyframe).

The vocabulary is learnt from the run's own keyframes (there is no training set to ship one from): k-majority
clustering of their descriptors (k-means for bit strings: each word becomes the bitwise majority of its
members), learnt at the fourth keyframe and again whenever the keyframe count doubles, every histogram
then recomputed (amortised, this is a constant cost per keyframe). Before the fourth keyframe (nothing
is old enough to be a loop yet) the keyframes are compared by brute-force nearest-neighbour votes.

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

# Neighbours per query descriptor in the brute-force vote used before the vocabulary exists.
NEIGHBOURS = 4
# The pre-check looks at this many matches at most (its cost grows with the square).
PRECHECK_MATCHES = 300
# The vocabulary: words, k-majority iterations, descriptors it is learnt from at most, and the keyframe
# count it is first learnt at (then relearnt at every doubling).
WORDS = 512
ITERATIONS = 3
TRAINING_DESCRIPTORS = 5_000
FIRST_VOCABULARY = 4
# The frame index a keyframe of an earlier session counts as: before any frame of this one.
EARLIER_SESSION = -(2**62)


@dataclass
class Place:
    """An earlier keyframe that may see the same place: its id and similarity score (0 to 1)."""

    keyframe: int
    score: float


def k_majority(descriptors: np.ndarray, words: int, iterations: int, rng: np.random.Generator) -> np.ndarray:
    """``words`` binary words (uint8 × 32 rows) clustering ``descriptors`` by Hamming distance: start from
    distinct random members, then assign each descriptor to its nearest word and replace each word by the
    bitwise majority of its members (an empty cluster keeps its word)."""
    unique = np.unique(descriptors, axis=0)
    words = min(words, len(unique))
    vocabulary = unique[rng.choice(len(unique), words, replace=False)]
    bits = np.unpackbits(descriptors, axis=1)  # uint8: a quarter of the bytes to gather and add
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for _ in range(iterations):
        assign = np.array([m.trainIdx for m in matcher.match(descriptors, vocabulary)])
        order = np.argsort(assign, kind="stable")
        members, starts = np.unique(assign[order], return_index=True)  # the clusters that have members
        sums = np.add.reduceat(bits[order], starts, axis=0, dtype=np.int32)  # exact: at most len(descriptors)
        counts = np.diff(np.r_[starts, len(order)])
        vocabulary[members] = np.packbits((2 * sums > counts[:, None]).astype(np.uint8), axis=1)
    return vocabulary


class PlaceDatabase:
    """ORB descriptors of every keyframe; ``query`` finds the earlier keyframes that look like a new one."""

    def __init__(self, config: LoopConfig, seed: int = 0):
        self.config = config
        self._descriptors: list[np.ndarray] = []
        self._frames: list[int] = []  # frame index of each keyframe, by id
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
        self._rng = np.random.default_rng(seed)
        self.vocabulary: np.ndarray | None = None
        self._counts = np.zeros((0, 0), np.float32)  # keyframes × words: word counts
        self.trainings = 0  # how often the vocabulary was learnt

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def word_counts(self) -> np.ndarray:
        """Keyframes × words: each keyframe's word counts (0 × 0 before the vocabulary exists)."""
        return self._counts

    def rng_state(self) -> dict:
        """The state of the generator that picks the training descriptors (what ``restore`` takes)."""
        return self._rng.bit_generator.state

    def restore(self, keyframes: list[Keyframe], vocabulary: np.ndarray | None, word_counts: np.ndarray,
                trainings: int, rng_state: dict) -> None:
        """The database as it was after ``keyframes`` were added (a saved map): their descriptors, with the
        vocabulary, word counts, training count and generator state saved with them, not learnt again."""
        self._descriptors = [np.zeros((0, 32), np.uint8) if kf.features.descriptors is None
                             else kf.features.descriptors for kf in keyframes]
        self._frames = [kf.frame for kf in keyframes]
        self.vocabulary = None if vocabulary is None else np.array(vocabulary)
        self._counts = np.array(word_counts, dtype=np.float32)
        self.trainings = int(trainings)
        self._rng.bit_generator.state = rng_state

    def add(self, keyframe: Keyframe) -> None:
        """Add a keyframe (ids in creation order: 0, 1, 2, ...)."""
        if keyframe.id != len(self._frames):
            raise ValueError(f"keyframe {keyframe.id} added as number {len(self._frames)}")
        d = keyframe.features.descriptors
        self._descriptors.append(np.zeros((0, 32), np.uint8) if d is None else d)
        self._frames.append(keyframe.frame)
        n = len(self._frames)
        if n >= FIRST_VOCABULARY and n & (n - 1) == 0:  # 4, 8, 16, ...: learn the vocabulary again
            self._learn()
        elif self.vocabulary is not None:
            self._counts = np.vstack([self._counts, self._histogram(self._descriptors[-1])])

    def _learn(self) -> None:
        every = np.concatenate(self._descriptors)
        if len(every) > TRAINING_DESCRIPTORS:
            every = every[self._rng.choice(len(every), TRAINING_DESCRIPTORS, replace=False)]
        if len(every) < 2:
            return
        self.vocabulary = k_majority(every, WORDS, ITERATIONS, self._rng)
        self._counts = np.stack([self._histogram(d) for d in self._descriptors])
        self.trainings += 1

    def _histogram(self, descriptors: np.ndarray) -> np.ndarray:
        words = len(self.vocabulary)
        if len(descriptors) == 0:
            return np.zeros(words, np.float32)
        assign = [m.trainIdx for m in self._matcher.match(descriptors, self.vocabulary)]
        return np.bincount(assign, minlength=words).astype(np.float32)

    def earlier_session(self) -> None:
        """The keyframes so far are an earlier session's (a saved map): from now on each is old enough to be a
        candidate whatever the frame index of the query (a new session counts its frames from 0 again)."""
        self._frames = [EARLIER_SESSION] * len(self._frames)

    def query(self, keyframe: Keyframe, everything: bool = False, exclude: set[int] = frozenset(),
              min_score: float | None = None) -> list[Place]:
        """Earlier keyframes at least ``min_frame_gap`` frames before ``keyframe`` (``everything``: every
        keyframe), not in ``exclude``, with a score of at least ``min_score`` (default: the config's), best
        first, ``candidates`` of them at most."""
        cfg = self.config
        min_score = cfg.min_score if min_score is None else min_score
        eligible = len(self._frames) if everything else \
            int(np.searchsorted(np.asarray(self._frames), keyframe.frame - cfg.min_frame_gap, side="right"))
        q = keyframe.features.descriptors
        if eligible == 0 or q is None or len(q) == 0:
            return []
        scores = self._bow_scores(q, eligible) if self.vocabulary is not None else self._vote_scores(q, eligible)
        order = np.argsort(-scores, kind="stable")
        return [Place(int(k), float(scores[k])) for k in order
                if scores[k] >= min_score and int(k) not in exclude][:cfg.candidates]

    def _bow_scores(self, q: np.ndarray, eligible: int) -> np.ndarray:
        """DBoW2's L1 score of the query against each of the first ``eligible`` keyframes, tf-idf weighted
        (idf over every keyframe in the database)."""
        counts = self._counts
        df = np.count_nonzero(counts, axis=0)
        # a word no keyframe has cannot match: weight 0, so it does not lower every score alike
        idf = np.where(df > 0, np.log(len(counts) / np.maximum(df, 1)), 0.0).astype(np.float32)
        def normalised(c):
            v = c * idf
            total = np.abs(v).sum(axis=-1, keepdims=True)
            return v / np.maximum(total, 1e-12)
        a = normalised(self._histogram(q))
        b = normalised(counts[:eligible])
        return 1.0 - 0.5 * np.abs(b - a).sum(axis=1)

    def _vote_scores(self, q: np.ndarray, eligible: int) -> np.ndarray:
        """Brute force: each query descriptor votes once for every keyframe among its nearest neighbours
        (closer than ``max_hamming``); the score is the voting fraction of the query's descriptors."""
        descriptors = np.concatenate(self._descriptors[:eligible])
        owners = np.concatenate([np.full(len(d), k, np.int32) for k, d in enumerate(self._descriptors[:eligible])])
        votes = np.zeros(eligible, np.int64)
        if len(descriptors) == 0:
            return votes.astype(np.float64)
        for row in self._matcher.knnMatch(q, descriptors, k=min(NEIGHBOURS, len(descriptors))):
            for k in {owners[m.trainIdx] for m in row if m.distance < self.config.max_hamming}:
                votes[k] += 1
        return votes / len(q)


def pairwise_distances(p: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(p[:, None] - p[None], axis=2)`` with the same sums (each coordinate's squared difference,
    added x, y, z in that order, as NumPy's reduction over the axis of three adds them today), in less time:
    that reduction over an axis of three elements is most of a verification's pre-check."""
    d = None
    for k in range(p.shape[1]):
        c = p[:, k]
        diff = c[:, None] - c[None]
        diff *= diff
        if d is None:
            d = diff
        else:
            d += diff
    return np.sqrt(d, out=d)


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
    da, db = pairwise_distances(pa), pairwise_distances(pb)
    agree = np.abs(da - db) < tolerance_m
    best = int(np.argmax(agree.sum(axis=1)))
    group = np.flatnonzero(agree[best])
    # keep only members that agree with most of the group, so that two clusters do not count as one
    inner = agree[np.ix_(group, group)].sum(axis=1) >= 0.5 * len(group)
    return int(np.count_nonzero(inner))
