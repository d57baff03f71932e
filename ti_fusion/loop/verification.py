"""Loop verification: is an earlier keyframe really the same place, and what is the relative pose?

Three gates, cheapest first, every outcome recorded with its reason (``LoopCandidate``):
1. the geometric pre-check (``place_recognition.precheck``): enough ORB matches consistent with one
   rigid motion;
2. PnP RANSAC (``ti_fusion.tracking.features.solve_pnp``) on the matches: the earlier keyframe's 3D
   points against the current keyframe's keypoints, at least ``loop.min_pnp_inliers`` inliers;
3. dense point-to-plane ICP (``ti_fusion.tracking.icp.ICP.align``) between the two keyframes' maps (the
   earlier keyframe's stored depth as the source, the current keyframe's maps as the target), from PnP's
   guess: no ICP failure, an inlier ratio of at least ``loop.min_inlier_ratio``, an RMS residual of at most
   ``loop.max_residual``, and a pose within ``loop.max_icp_change_deg`` / ``_m`` of PnP's (both agree).

``verify_dense`` is the third gate alone, from the two keyframes' estimated relative pose instead of PnP's, for
keyframes ORB cannot match (a view whose keypoints lie beyond the depth camera's range): the same ICP gates, the
pose within the same limits of the estimate, and the same pose from starts around the estimate. With no appearance
behind it, where depth does not fix the pose (down a corridor of plain walls ICP stays where it starts, and its
weak-direction test need not say so) ICP would return the estimate as the measurement: ICP from starts
``DENSE_OFFSET_M`` / ``DENSE_OFFSET_DEG`` off the estimate along each axis must all end within ``DENSE_SPREAD_M`` /
``DENSE_SPREAD_DEG`` of the first.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ti_fusion.config import Config
from ti_fusion.geometry import pose_error, se3_exp
from ti_fusion.loop.keyframes import Keyframe
from ti_fusion.loop.place_recognition import precheck
from ti_fusion.tracking.features import PnPEstimate, solve_pnp
from ti_fusion.tracking.icp import ICP
from ti_fusion.timing import Stopwatch


# verify_dense: the starts around the estimate (each axis, both signs, in the query's camera frame), and how far
# apart the poses ICP ends at from them may be. ICP of one place converges to one pose from a few cm and degrees
# off (within a millimetre on the synthetic room); along a corridor of plain walls it ends where it started.
DENSE_OFFSET_M = 0.05
DENSE_OFFSET_DEG = 3.0
DENSE_SPREAD_M = 0.01
DENSE_SPREAD_DEG = 0.5


def dense_starts(init: np.ndarray) -> list[np.ndarray]:
    """``init`` moved by ±``DENSE_OFFSET_M`` along each axis and turned by ±``DENSE_OFFSET_DEG`` about each."""
    starts = []
    for axis in range(6):
        for sign in (-1.0, 1.0):
            twist = np.zeros(6)
            twist[axis] = sign * (np.radians(DENSE_OFFSET_DEG) if axis < 3 else DENSE_OFFSET_M)
            starts.append(se3_exp(twist) @ init)
    return starts


class FeatureCheck(NamedTuple):
    """A candidate's first two gates (``LoopVerifier.check_features``)."""

    consistent: int  # matches passing the pre-check
    pnp: PnPEstimate | None  # PnP's estimate, None where the pre-check rejected the candidate


@dataclass
class LoopCandidate:
    """One candidate loop and its verdict. ``T``: p_query = T p_match (the earlier keyframe's camera
    coordinates into the current one's), set once PnP has found one (ICP's refinement when it ran)."""

    query: int  # the current keyframe's id
    match: int  # the earlier keyframe's id
    score: float  # place recognition's score
    verified: bool = False  # passed the three gates: a loop for the pose graph, which may still refuse it
    reason: str = ""  # why rejected, or "verified"
    consistent: int = 0  # matches passing the pre-check
    pnp_inliers: int = 0
    icp_inlier_ratio: float | None = None
    icp_residual_m: float | None = None
    T: np.ndarray | None = None
    free: list = dataclasses.field(default_factory=list)  # unit twists (ω, v) ICP's depth could not fix (the
    # weak directions of its AᵀA not lifted by colour): the loop edge leaves them to odometry
    ms: float = 0.0

    def record(self) -> dict:
        """The candidate for the log and summary.json."""
        return {"query": self.query, "match": self.match, "score": round(self.score, 4),
                "verified": self.verified, "reason": self.reason, "consistent": self.consistent,
                "pnp_inliers": self.pnp_inliers,
                "icp_inlier_ratio": None if self.icp_inlier_ratio is None else round(self.icp_inlier_ratio, 4),
                "icp_residual_mm": None if self.icp_residual_m is None else round(self.icp_residual_m * 1e3, 3),
                "ms": round(self.ms, 3)}


class LoopVerifier:
    """Verifies candidates with the run's ICP settings and ``loop`` thresholds.

    ``source`` and ``target`` are ``FramePyramid`` to fill: the earlier keyframe's maps are built in
    ``source`` from its stored depth, and the current keyframe's in ``target`` unless the caller says
    they are already there (the SLAM loop passes the maps it just tracked the frame with).
    """

    def __init__(self, config: Config):
        self.config = config
        self.icp = ICP(config.icp)
        self.vo = dataclasses.replace(config.vo, n_features=config.loop.n_features, match="min_distance")

    def verify(self, query: Keyframe, match: Keyframe, score: float, source, target,
               target_ready: bool = False, checked: FeatureCheck | None = None) -> LoopCandidate:
        """``checked``: the first two gates' ``check_features(query, match)`` where the caller has it already."""
        watch = Stopwatch()
        candidate = LoopCandidate(query.id, match.id, score)
        try:
            self._verify(candidate, query, match, source, target, target_ready,
                         checked if checked is not None else self.check_features(query, match))
        finally:
            candidate.ms = watch.ms
        return candidate

    def check_features(self, query: Keyframe, match: Keyframe) -> FeatureCheck:
        """The first two gates, which read the keyframes' ORB features only (no Taichi, no pose): the pre-check's
        consistent matches, and PnP's estimate where the pre-check passes."""
        consistent = precheck(match, query, self.vo, self.config.loop.consistent_m)
        if consistent < self.config.loop.min_consistent:
            return FeatureCheck(consistent, None)
        return FeatureCheck(consistent, solve_pnp(match.features, query.features, query.intrinsics, self.vo,
                                                  check_motion=False))

    def _verify(self, c: LoopCandidate, query: Keyframe, match: Keyframe, source, target,
                target_ready: bool, checked: FeatureCheck) -> None:
        cfg = self.config.loop
        c.consistent, pnp = checked
        if pnp is None:
            c.reason = f"pre-check: {c.consistent} consistent matches < {cfg.min_consistent}"
            return
        c.pnp_inliers = pnp.inliers
        if pnp.T is None or pnp.inliers < cfg.min_pnp_inliers:
            c.reason = f"PnP: {pnp.inliers} inliers < {cfg.min_pnp_inliers}"
            return
        c.T = pnp.T
        fill(source, match)
        if not target_ready:
            fill(target, query)
        icp = self.icp.align(source, target, init=pnp.T)
        c.reason = self._icp_gates(c, icp, pnp.T, "PnP's pose")
        if not c.reason:
            self._verified(c, icp, "verified")

    def _icp_gates(self, c: LoopCandidate, icp, start: np.ndarray, what: str) -> str:
        """ICP's figures into ``c``; "" where ``icp`` passes the ICP gates (no failure, ``loop.min_inlier_ratio``,
        ``loop.max_residual``, within ``loop.max_icp_change_deg`` / ``_m`` of ``start``, ``what``), else why not."""
        cfg = self.config.loop
        c.icp_inlier_ratio, c.icp_residual_m = float(icp.inlier_ratio), float(icp.residual_rms)
        if icp.failure:
            return f"ICP: {icp.failure}"
        if not icp.inlier_ratio >= cfg.min_inlier_ratio:
            return f"ICP: inlier ratio {icp.inlier_ratio:.3f} < {cfg.min_inlier_ratio:g}"
        if not icp.residual_rms <= cfg.max_residual:
            return f"ICP: residual {icp.residual_rms * 1e3:.1f} mm > {cfg.max_residual * 1e3:g} mm"
        rot_deg, trans_m = pose_error(icp.pose, start)
        if rot_deg > cfg.max_icp_change_deg or trans_m > cfg.max_icp_change_m:
            return (f"ICP moved {what} by {rot_deg:.1f} deg / {trans_m * 100:.1f} cm (at most "
                    f"{cfg.max_icp_change_deg:g} deg / {cfg.max_icp_change_m * 100:g} cm)")
        return ""

    @staticmethod
    def _verified(c: LoopCandidate, icp, reason: str) -> None:
        """``c`` verified at ICP's pose."""
        c.T = icp.pose
        # ICP slides freely along a weak direction (a plain wall: along it), so its pose there is whatever the
        # iterations left, often worse than its start: the loop must not pull the graph that way.
        c.free = [np.asarray(d["twist"], dtype=np.float64) for d in (icp.degeneracy or {}).get("directions", [])
                  if not d["color"]]
        c.verified, c.reason = True, reason

    def verify_dense(self, query: Keyframe, match: Keyframe, init: np.ndarray, source, target) -> LoopCandidate:
        """``match`` against ``query`` (whose maps are in ``target`` already) by dense ICP alone, from ``init``
        (p_query = init p_match, the two keyframes' estimated poses); score 0: place recognition had no say."""
        watch = Stopwatch()
        c = LoopCandidate(query.id, match.id, 0.0)
        fill(source, match)
        icp = self.icp.align(source, target, init=init)
        gates = self._icp_gates(c, icp, init, "the estimate")
        c.reason = f"dense: {gates}" if gates else self._spread(icp.pose, init, source, target)
        if not c.reason:
            self._verified(c, icp, "verified (dense, from the estimated poses)")
        c.ms = watch.ms
        return c

    def _spread(self, pose: np.ndarray, init: np.ndarray, source, target) -> str:
        """"" when ICP from every start of ``dense_starts(init)`` ends within DENSE_SPREAD_M / _DEG of ``pose``,
        else why not."""
        for start in dense_starts(init):
            other = self.icp.align(source, target, init=start)
            rot_deg, trans_m = pose_error(other.pose, pose)
            if other.failure or rot_deg > DENSE_SPREAD_DEG or trans_m > DENSE_SPREAD_M:
                return (f"dense: ICP from a start {DENSE_OFFSET_M * 100:g} cm / {DENSE_OFFSET_DEG:g} deg off the "
                        f"estimate ends {trans_m * 100:.1f} cm / {rot_deg:.1f} deg from where it ends from the "
                        f"estimate (at most "
                        f"{DENSE_SPREAD_M * 100:g} cm / {DENSE_SPREAD_DEG:g} deg): the place does not fix the pose"
                        + (f" ({other.failure})" if other.failure else ""))
        return ""


def fill(pyramid, keyframe: Keyframe) -> None:
    """Build ``pyramid`` (a ``FramePyramid`` whose level 0 has the shape of ``keyframe.depth``) from the
    keyframe's stored depth, without smoothing it again."""
    if tuple(pyramid.shapes[0]) != keyframe.depth.shape:
        raise ValueError(f"maps of level-0 shape {pyramid.shapes[0]} for a keyframe depth of {keyframe.depth.shape}")
    pyramid.depth[0].from_numpy(keyframe.depth)
    pyramid.compute_from_field(keyframe.depth_intrinsics)
