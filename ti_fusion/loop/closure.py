"""Loop closure inside dense SLAM: ``DenseSLAM.register_frame`` runs ``LoopClosure.after_frame`` after each frame
(with ``slam.loop_closure``) and applies what it returns.

    loop = LoopClosure(config)
    report = loop.after_frame(frame, result, maps)   # None, or what this frame did (keyframe, candidates, loop)
    # the owner then anchors to report.keyframe, and moves poses and map by report.corrections when not None

For a tracked frame that the selector makes a keyframe (``keyframes.py``): its ORB features and depth
summary are kept, the pose graph gets the keyframe and an odometry edge, and place recognition
(``place_recognition.py``) proposes earlier keyframes, the candidates, checked best first (``verification.py``)
until one is verified. A verified loop goes into the pose graph (``pose_graph.py``); if the optimisation keeps
it (not an outlier of the robust kernel, and within ``loop.max_loop_error`` of the optimised poses), every
keyframe k gets its world-frame correction C_k = T_k,new · T_k,old⁻¹, returned in the report for the owner
to move every frame pose and every surfel anchored to k with. Tracking then goes on from the corrected last
pose against the corrected map; the motion model is a relative motion and needs nothing.

A second session against a saved map (``begin_session``): the map's keyframes are an earlier session's, loop
candidates of every keyframe of the new one; until the new session has found itself, ``find_place`` looks for
each frame among them (place recognition over every keyframe, then verification as for a loop), and the
frame that found itself becomes the session's first keyframe, tied to the keyframe it matched (``found``). That
keyframe's loop candidates are the map's other visits of the place (outside the tie's frame gap); when ORB verifies
none of them, the map's keyframes nearest it by the estimated poses are tried by dense ICP alone
(``LoopVerifier.verify_dense``): where the first session ended just before its start came back into view, its last
keyframes see the place with keypoints beyond the depth camera's range, and this tie is what closes its loop.

Loop closure calls nothing of SLAM: the owner hands it, per frame, the frame's maps (``LoopMaps``: the
frame's pyramid, read only, the target of verification and the keyframe's depth; and maps it may fill
until the next frame, where verification builds the earlier keyframe's maps), and applies the report.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from functools import partial

import cv2
import numpy as np

from ti_fusion.config import Config
from ti_fusion.geometry import invert, pose_error, renormalize
from ti_fusion.loop.keyframes import Keyframe, KeyframeSelector, grid_points
from ti_fusion.loop.in_order import InOrder, Job
from ti_fusion.loop.lookahead import look_ahead
from ti_fusion.loop.place_recognition import PlaceDatabase
from ti_fusion.loop.pose_graph import PoseGraph, edge_covariance, frame_covariance
from ti_fusion.loop.verification import LoopCandidate, LoopVerifier, fill
from ti_fusion.tracking.features import extract_features, solve_pnp
from ti_fusion.timing import Stopwatch

log = logging.getLogger(__name__)

# A session's first keyframe tries, when ORB verifies none of its candidates, the map's keyframes (outside the tie's
# frame gap) whose estimated pose is within this distance and angle of its own, nearest first, at most DENSE_TRIES:
# they see most of what it sees (keyframes are 0.25 m / 20 degrees apart); verify_dense then accepts an estimate
# off by at most loop.max_icp_change_m / _deg (the map's drift between the two visits).
DENSE_TIE_M = 0.3
DENSE_TIE_DEG = 20.0
DENSE_TRIES = 3


def candidate_gap(config: Config) -> int:
    """Frames a loop candidate is older than the current keyframe at least: ``loop.min_frame_gap``, and with
    ``slam.active_window`` the window too, whose surfels tracking aligns to already (a loop to them repeats
    odometry with the loop's own error added)."""
    return max(config.loop.min_frame_gap, config.slam.active_window)


@dataclass
class LoopMaps:
    """What loop closure needs of the frame just registered: handed over by its owner each frame."""

    frame: object  # FramePyramid: the frame's maps, read only (verification's target, the keyframe's depth)
    scratch: object  # FramePyramid at the map's resolution that may be filled until the next frame
    level: int  # the level of ``frame`` at the map's resolution


@dataclass
class Placement:
    """Where a frame found itself among the keyframes (``LoopClosure.find_place``)."""

    candidate: LoopCandidate  # the verified candidate: ``T`` maps the keyframe's camera into the frame's
    keyframe: Keyframe  # the keyframe it matched
    pose: np.ndarray  # the frame's camera-to-world pose that the match gives
    frame: int = -1  # the frame's index
    features: object = None  # its ORB features (FrameFeatures), which its keyframe takes instead of extracting again


@dataclass
class LoopReport:
    """What loop closure did after one frame (only frames that became keyframes have one). The owner anchors
    the frame just registered, the frames after it and the surfels fused from the next frame on to
    ``keyframe``, then moves every pose and surfel by ``corrections`` when a loop was applied."""

    keyframe: int  # the new keyframe's id
    why: str  # "first", "moved", "turned", "overlap", "found" (a session's first: it found itself in the map)
    candidates: list[LoopCandidate] = field(default_factory=list)
    applied: tuple[int, int] | None = None  # (earlier keyframe, this keyframe) of a loop applied
    outcome: str = ""  # for a verified candidate: "applied", or why the pose graph refused it
    ms: dict[str, float] = field(default_factory=dict)  # keyframe, detect, verify, optimise, correct
    corrections: np.ndarray | None = None  # K×4×4 world-frame C_k of each keyframe, on an applied loop

    def stats(self) -> dict:
        """The frame's ``loop`` entry in /slam/stats."""
        return {"keyframe": self.keyframe, "why": self.why,
                "candidates": [c.record() for c in self.candidates],
                "applied": None if self.applied is None else list(self.applied), "outcome": self.outcome,
                "ms": {k: round(v, 3) for k, v in self.ms.items()}}


class LoopClosure:
    """Keyframes, place recognition, verification, the pose graph and the correction of poses and map."""

    def __init__(self, config: Config):
        self.config = config
        self.selector = KeyframeSelector(config.loop)
        self.gap = candidate_gap(config)
        self._database = PlaceDatabase(dataclasses.replace(config.loop, min_frame_gap=self.gap))
        # on threads beside the loop's, in order (loop/in_order.py): each keyframe's addition to the database, which
        # only the next keyframe's query reads (``database`` waits for it), and frames' looks ahead (loop/lookahead.py)
        self._beside = InOrder("ti-fusion-loop-closure")
        self._ahead: tuple[int, Job] | None = None  # (frame index, its look ahead) of the last frame that had one
        self._ahead_orb = cv2.ORB_create(config.loop.n_features)  # the looks ahead's own: theirs run beside ``_orb``
        self.graph = PoseGraph(config.loop)
        self.verifier = LoopVerifier(config)
        self.keyframes: list[Keyframe] = []
        self._orb = cv2.ORB_create(config.loop.n_features)
        self._vo = dataclasses.replace(config.vo, n_features=config.loop.n_features)
        self._since: list[tuple[np.ndarray, np.ndarray]] = []  # loop.odometry_from_icp: (pose, covariance) of the
        # frames since the last keyframe, for the next odometry edge
        self.candidates: list[LoopCandidate] = []  # every candidate checked, in order
        self.applied: list[tuple[int, int]] = []  # loops applied
        self.refused: list[tuple[int, int, str]] = []  # verified loops the pose graph refused, and why
        self.kept: list[tuple[int, int]] = []  # verified loops within loop.min_loop_error of the poses: in the graph,
        # nothing moved
        self.ms: dict[str, list[float]] = {"detect": [], "verify": [], "optimise": []}
        self._corrected: list[LoopReport] = []  # the reports of loops applied: their ms["correct"] is whole once
        # the owner has moved the poses and the map
        self._warmed_up = False  # the kernels that build maps from a stored depth are loaded (``after_frame``)
        self.session_start = 0  # the first keyframe of this session (``begin_session``): the ones before are the map's
        # where the frame that found itself in a saved map matched (``found``): the next keyframe is tied to that
        # keyframe instead of odometry, and takes that frame's features
        self._found: Placement | None = None

    @property
    def database(self) -> PlaceDatabase:
        """Place recognition's database, once the additions handed to the threads before are in it."""
        self._beside.settle()
        return self._database

    # -- the verb -------------------------------------------------------------------------------
    def look_ahead(self, frame, guess: np.ndarray) -> None:
        """Before ``frame`` is tracked: where the motion model's ``guess`` of its pose makes it a keyframe, what
        verifying it needs of its images alone (ORB, candidates, their pre-check and PnP) starts on a thread
        (loop/lookahead.py), for ``after_frame`` to take if the tracked pose makes it one."""
        self._drop_ahead()  # an earlier frame's, not taken: not started, it does not run
        if self._found is not None or len(self.keyframes) <= self.session_start or frame.color is None or \
                self.selector.why(self.keyframes[-1], guess, frame.index) is None:
            return
        self._ahead = frame.index, self._beside.submit(partial(
            look_ahead, frame, len(self.keyframes), self._vo, self._ahead_orb, self._database, self.keyframes,
            self.verifier), quiet=True)

    def after_frame(self, frame, result, maps: LoopMaps) -> LoopReport | None:
        """Loop closure's part of one frame, after tracking and fusion gave ``result`` for it."""
        if result.pose is None:
            return None
        if self.config.loop.odometry_from_icp and self.keyframes:
            self._since.append((np.array(result.pose, dtype=np.float64),
                                frame_covariance(self._information(result), self.config.loop)))
        why = "found" if self._found is not None and result.tracking.tracked else None
        if why is None and (not result.tracking.tracked or (why := self.selector.why(
                self.keyframes[-1] if len(self.keyframes) > self.session_start else None, result.pose,
                frame.index)) is None):
            return None
        watch = Stopwatch()
        tied = None if self._found is None else self._found.keyframe.id
        # the look ahead of this frame, if its guess made it a keyframe too (the same features, candidates and checks)
        ahead = None
        if self._ahead is not None and self._ahead[0] == frame.index and tied is None:
            ahead = self._beside.take(self._ahead[1])
        kf = self._make_keyframe(frame, result.pose, maps, None if ahead is None else ahead.features)
        report = LoopReport(kf.id, why)
        report.ms["keyframe"] = watch.lap()
        exclude = set()
        if tied is not None:  # the tie is this keyframe's measurement of the place it found: loops from here are
            # to the map's other visits of it (a lap's end where it met its start), which can undo the map's drift
            near = self.keyframes[tied].frame
            exclude = {k for k in range(self.session_start) if abs(self.keyframes[k].frame - near) < self.gap}
        places = ahead.places if ahead is not None else self.database.query(kf, exclude=exclude)
        self._beside.submit(partial(self._database.add, kf))  # the next keyframe's query waits for it
        report.ms["detect"] = watch.lap()
        self.ms["detect"].append(report.ms["keyframe"] + report.ms["detect"])
        if not self._warmed_up and kf.frame - self.keyframes[0].frame >= self.gap - self.gap // 4:
            # Load what building maps from a stored depth needs beyond tracking's kernels (the depth's upload
            # into the scratch maps) now, three quarters of the candidates' frame gap in (no keyframe can have
            # a candidate before the gap), not at the first candidate, and not in a run too short to have
            # candidates at all (a short run, a test, the default 120-frame run pays none of it); not counted
            # as detection.
            with Stopwatch(report.ms, "warmup"):
                fill(maps.scratch, kf)
            self._warmed_up = True
        verified = None
        for k, place in enumerate(places):
            c = self.verifier.verify(kf, self.keyframes[place.keyframe], place.score, maps.scratch, maps.frame,
                                     target_ready=True, checked=None if ahead is None else ahead.checks[k])
            report.candidates.append(c)
            self.candidates.append(c)
            # on by default: a rejected candidate is routine (debug; every candidate is in summary.json)
            say = log.info if c.verified else log.debug
            say(f"loop candidate: keyframe {c.query} (frame {kf.frame}) with keyframe {c.match} (frame "
                f"{self.keyframes[c.match].frame}), score {c.score:.3f}: "
                f"{'verified' if c.verified else 'rejected'} ({c.reason})")
            if c.verified:
                verified = c
                break
        if verified is None and tied is not None:
            verified = self._dense_tie(kf, exclude, report, maps)
        if report.candidates:
            report.ms["verify"] = sum(c.ms for c in report.candidates)
            self.ms["verify"].append(report.ms["verify"])
        if verified is not None:
            self._close(verified, report)
        return report

    # -- keyframes ------------------------------------------------------------------------------
    def _information(self, result) -> np.ndarray | None:
        """The tracked frame's AᵀA of ICP's last iteration ((ω, v) in the new camera's frame: ICP's left update
        of T = T_wc_new⁻¹ T_wc_last is a right perturbation of the new pose), the other tracking terms' added where
        they ran (each × its weight), or None."""
        icp = result.icp
        if not result.tracking.tracked or icp is None or icp.sums is None:
            return None
        from ti_fusion.kernels.icp import combined_system, unpack_sums

        if any(t["count"] > 0 for t in icp.terms.values()):
            return combined_system(icp.sums, icp.weights)[0]
        return unpack_sums(icp.sums)["AtA"]

    def _make_keyframe(self, frame, pose: np.ndarray, maps: LoopMaps, features=None) -> Keyframe:
        """``features``: the frame's ORB features where its look ahead has them."""
        depth, K = maps.frame.depth[maps.level].to_numpy(), maps.frame.intrinsics[maps.level]  # the map's resolution
        found, self._found = self._found, None
        # the frame that found itself in a saved map has its features from ``find_place``
        if features is None:
            features = found.features if found is not None and found.frame == frame.index else \
                extract_features(frame, self._vo, self._orb)
        kf = Keyframe(len(self.keyframes), frame.index, frame.timestamp, pose.copy(), features, frame.intrinsics,
                      depth, K, grid_points(depth, K))
        self.keyframes.append(kf)
        covariance = None
        if self.config.loop.odometry_from_icp and self._since:
            covariance = edge_covariance(self._since, pose)
        self._since = []
        self.graph.add_keyframe(pose, covariance, chained=found is None)
        if found is not None:  # no odometry from the map's last keyframe: the match is this keyframe's tie to the map
            self.graph.add_relative(found.keyframe.id, kf.id, renormalize(invert(found.candidate.T)))
        elif self.config.loop.keyframe_pnp and kf.id > self.session_start:
            self._pnp_edge(self.keyframes[-2], kf)
        return kf

    # -- a session against a saved map ----------------------------------------------------------
    def begin_session(self) -> None:
        """The keyframes so far are an earlier session's (a saved map): each is a loop candidate of the new
        session's keyframes from the first on, and the new session's first keyframe is the frame that
        ``find_place`` placed (``found``), with no odometry edge from the map's last keyframe."""
        self.session_start = len(self.keyframes)
        self.database.earlier_session()
        self._since = []
        self._found = None

    def find_place(self, frame, maps: LoopMaps) -> tuple[Placement | None, list[LoopCandidate]]:
        """Where ``frame`` (tracked by nothing yet: its pose is unknown) is among the keyframes: place recognition
        over all of them, then the candidates verified best first as a loop's are (pre-check, PnP, dense ICP
        between the keyframe's stored depth and the frame's maps, ``maps.frame``). Returns the first verified
        one's placement, or None, and every candidate checked."""
        features = extract_features(frame, self._vo, self._orb)
        # verification reads the frame's maps where they are (target_ready): the query needs no depth of its own
        query = Keyframe(len(self.keyframes), frame.index, frame.timestamp, np.eye(4), features, frame.intrinsics,
                         None, maps.frame.intrinsics[maps.level], np.zeros((0, 3)))
        checked = []
        # a shortlist, not a gate: in a small map tf-idf scores every keyframe low (a word in each of them weighs
        # nothing), and a frame that is not found tries again next frame, so the best few are verified whatever
        # their score (PnP and dense ICP decide)
        for place in self.database.query(query, everything=True, min_score=0.0):
            c = self.verifier.verify(query, self.keyframes[place.keyframe], place.score, maps.scratch, maps.frame,
                                     target_ready=True)
            checked.append(c)
            if c.verified:
                match = self.keyframes[c.match]
                return Placement(c, match, renormalize(match.pose @ invert(c.T)), frame.index, features), checked
        return None, checked

    def found(self, placement: Placement) -> None:
        """The frame just registered found itself at ``placement``: it becomes the session's first keyframe,
        tied to the keyframe it matched by the relative pose verification measured between the two (the keyframe's
        stored depth against the frame), not by the pose tracking gave the frame: where the map saw the place twice
        with its drift between (a lap's start and end), tracking against the map rendered there mixes both visits'
        surfels, and the tie would pull the loop to the other visit towards that mix."""
        self._found = placement

    def _dense_tie(self, kf: Keyframe, exclude: set, report: LoopReport, maps: LoopMaps) -> LoopCandidate | None:
        """A session's first keyframe against the map's keyframes near it by the estimated poses (``DENSE_TIE_M``,
        ``DENSE_TIE_DEG``; not those of ``exclude``, the tie's own visit), dense ICP alone, nearest first: the
        first verified, or None."""
        near = []
        for k in range(self.session_start):
            if k in exclude:
                continue
            rot_deg, trans_m = pose_error(self.keyframes[k].pose, kf.pose)
            if trans_m <= DENSE_TIE_M and rot_deg <= DENSE_TIE_DEG:
                near.append((trans_m, k))
        for trans_m, k in sorted(near)[:DENSE_TRIES]:
            match = self.keyframes[k]
            c = self.verifier.verify_dense(kf, match, renormalize(invert(kf.pose) @ match.pose), maps.scratch,
                                           maps.frame)
            report.candidates.append(c)
            self.candidates.append(c)
            say = log.info if c.verified else log.debug
            say(f"dense tie: keyframe {kf.id} (frame {kf.frame}) with the map's keyframe {k} (frame {match.frame}), "
                f"{trans_m * 100:.1f} cm away by the estimates: {c.reason}")
            if c.verified:
                return c
        return None

    def _pnp_edge(self, previous: Keyframe, kf: Keyframe) -> None:
        """``loop.keyframe_pnp``: the two keyframes' relative pose from PnP RANSAC on their ORB features (the
        previous keyframe's 3D points against this one's keypoints) as a pose-graph edge, when it has at least
        ``loop.min_pnp_inliers`` inliers."""
        pnp = solve_pnp(previous.features, kf.features, kf.intrinsics, self.verifier.vo, check_motion=False)
        if pnp.T is not None and pnp.inliers >= self.config.loop.min_pnp_inliers:
            self.graph.add_relative(previous.id, kf.id, invert(pnp.T))  # pnp.T: p_kf = T p_previous

    # -- closing a loop -------------------------------------------------------------------------
    def _close(self, c: LoopCandidate, report: LoopReport) -> None:
        i, j = c.match, c.query
        # T: p_j = T p_i, so keyframe j's pose in keyframe i's frame is T⁻¹
        self.graph.poses = [kf.pose.copy() for kf in self.keyframes]
        self.graph.add_loop(i, j, invert(c.T), free=c.free)  # c.T's left twist = a right twist of its inverse
        before = self.graph.loop_error(self.graph.edges[-1], self.graph.poses)
        if before < self.config.loop.min_loop_error:
            # Where tracking is already better than the loop's own measurement (a short loop after accurate
            # tracking), solving would only add that measurement's error; the edge stays for a later loop's solve.
            report.outcome = (f"kept in the graph: {before:.2f} sigma from the poses < "
                              f"{self.config.loop.min_loop_error:g}")
            self.kept.append((i, j))
            log.info(f"loop {i}-{j} {report.outcome}")
            return
        opt = self.graph.optimise()
        report.ms["optimise"] = opt.ms
        self.ms["optimise"].append(opt.ms)
        error = opt.loop_errors[(i, j)]
        if (i, j) in opt.outliers or error > self.config.loop.max_loop_error:
            self.graph.remove_loop(i, j)
            why = "an outlier of the robust kernel" if (i, j) in opt.outliers else \
                f"{error:.1f} sigma from the optimised poses > {self.config.loop.max_loop_error:g}"
            report.outcome = f"refused by the pose graph: {why}"
            self.refused.append((i, j, why))
            log.info(f"loop {i}-{j} {report.outcome}")
            return
        with Stopwatch(report.ms, "correct"):  # the owner adds its moving of the poses and the map
            corrections = np.stack([renormalize(new @ invert(kf.pose)) for new, kf in zip(opt.poses, self.keyframes)])
            for kf, C in zip(self.keyframes, corrections):  # a keyframe's pose is its frame's: moved the same way
                kf.pose = renormalize(C @ kf.pose)
            self.graph.set_poses(opt.poses)
        report.corrections = corrections
        self._corrected.append(report)
        report.applied, report.outcome = (i, j), "applied"
        self.applied.append((i, j))
        moved = float(np.linalg.norm(corrections[-1][:3, 3]))
        log.info(f"loop {i}-{j} applied: {opt.iterations} iterations, error {opt.error_before:.1f} → "
                 f"{opt.error_after:.2f}, the current keyframe moved {moved * 100:.1f} cm")

    # -- results --------------------------------------------------------------------------------
    def loop_segments(self, candidates: list[LoopCandidate]) -> list[tuple[np.ndarray, np.ndarray, bool]]:
        """(camera centre of the earlier keyframe, of the current one, applied) of each candidate: applied =
        the loop moved the poses and the map; a verified candidate the pose graph refused
        (a look-alike place) is drawn as not applied, as one verification rejected."""
        applied = set(self.applied)
        return [(self.keyframes[c.match].centre, self.keyframes[c.query].centre, (c.match, c.query) in applied)
                for c in candidates]

    def edges(self) -> list[tuple[np.ndarray, np.ndarray, bool]]:
        """Every candidate checked, as a segment between the two keyframes' current centres."""
        return self.loop_segments(self.candidates)

    def settle(self) -> None:
        """Wait for the work handed to threads (loop/in_order.py): a look ahead not taken is dropped, and a failed
        database addition raises here, not at a next keyframe that a run's end never brings."""
        self._drop_ahead()
        self._beside.settle()

    def _drop_ahead(self) -> None:
        """The last look ahead will not be taken (``InOrder.drop``)."""
        if self._ahead is not None:
            self._beside.drop(self._ahead[1])
        self._ahead = None

    def summary(self) -> dict:
        """The counts for summary.json, and what each part cost per call (milliseconds: mean, max), once the
        threads' work is done (``settle``)."""
        self.settle()
        ms = {**self.ms, "correct": [r.ms["correct"] for r in self._corrected]}
        cost = {name: {"calls": len(v), "mean": round(float(np.mean(v)), 2), "max": round(float(np.max(v)), 2)}
                for name, v in ms.items() if v}
        return {"keyframes": len(self.keyframes), "loop_candidates": len(self.candidates),
                "loops_applied": len(self.applied),
                "loops": [{"from": i, "to": j, "frames": [self.keyframes[i].frame, self.keyframes[j].frame]}
                          for i, j in self.applied][:50],
                "loops_refused": [{"from": i, "to": j, "why": why} for i, j, why in self.refused][:50],
                "loops_kept": len(self.kept),
                "loop_candidates_log": [c.record() for c in self.candidates][:200],
                "loop_ms": cost}
