"""Dense SLAM: frame-to-model point-to-plane ICP and point-based fusion.

    slam = DenseSLAM(config, intrinsics)
    for frame in dataset:
        result = slam.register_frame(frame)      # track against the model, fuse, then loop closure

Loop closure (``slam.loop_closure``, on by default; ``ti_fusion/loop/closure.py``) runs inside
``register_frame`` after fusion: this class hands it the frame's maps and applies what it reports (the new
keyframe's anchor, and on an applied loop the corrections of every pose and surfel); loop closure calls
nothing of this class. ``result.pose`` stays the pose as registered; ``poses.by_frame()`` is the current
trajectory, which a loop moves.

Which cloud is the ICP source, and why
--------------------------------------
The MODEL is the source and the incoming FRAME is the target. Before tracking a frame, the surfel map is
rendered at the last estimated pose into a predicted depth/vertex/normal map (surfel splatting, Keller et
al. 2013) and that prediction is aligned to the new frame by projective association: each model point is
transformed by the current estimate and projected into the frame's image, where its correspondence is
read off in O(1). Projective association needs the target to be an image with intrinsics: the frame is
one, and so is the rendered prediction. Swapping the roles (frame as source, map as target) works just as
well when the map is rendered first, since both are images; what does not work cheaply is associating
against the raw surfel list, which has no image structure: that would need a nearest-neighbour search
(a k-d tree over millions of surfels, rebuilt as the map changes) instead of one projection per point.
Keeping the model as the reference (rather than the previous frame) is what limits drift: every frame is
registered against the fused, denoised surface, not against the last noisy frame.

Resolution: the map is built at ``fusion.level`` of the frame's pyramid (auto: about 320×240), and by
default the frame is averaged down to that level before it is smoothed and tracked. On redkitchen, a map
at 320×240 tracked better than one at 640×480 (more measurements averaged into each surfel, so a less
noisy prediction) at a quarter of the surfels.

Colour (``icp.color_weight`` > 0, docs/PHOTOMETRIC.md): tracking minimises the joint cost, point-to-plane
ICP plus the photometric error between the live frame's intensity and the model's colour rendered with the
prediction (the surfel seen at each pixel), which constrains what depth alone does not (a wall, a floor, a
corridor). Only for frames whose colour is registered to depth (``Frame.color_registered``, set by the
dataset): on others the term stays off, with one warning.

The map starts at the first usable frame: one with depth enough for ICP to track the next frame against
(``usable``); frames before it (a sensor that starts blank) are skipped: no pose, status "skipped: ...".
Hypotheses (``slam.hypotheses``, docs/TRACKING.md). ICP starts from the motion model's guess: the last
tracked motion per second times the time since the last tracked frame (``Frame.timestamp``), from that
frame's pose, halved after a step whose speed changed (``slam.motion_damping``); a lost frame never feeds
it. When that alignment fails the health checks (few inliers,
large residual, ill-conditioned system, implausible jump) or is in doubt (residual above
``slam.doubt_residual_ratio`` × the median residual of the last tracked frames, or another start won the last
tracked frame), ICP runs
again from the last good pose, then from ORB + PnP against the last well-tracked frame
(``slam.relocalise = "features"``), then, as a dense re-localisation, from the last good pose with a wider
basin (``slam.relocalise_iterations``, ``slam.relocalise_level_dist_scale``). Every start aligns the same
prediction to the same frame, so their results compare: of those that pass the checks the one with the
best ``alignment_score`` (inlier ratio × (1 − residual / max_residual)) wins, and ``FrameResult.hypothesis``
says which; after a failure the start from rest (the last good pose) is always tried beside the guess. Only
when none passes is the frame lost: it is not fused, and it reports the motion model's guess.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from ti_fusion.backend import check_usable, current_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config, ICPConfig
from ti_fusion.frame import Frame
from ti_fusion.mapping.mapper import FusionStats, SurfelMapper
from ti_fusion.geometry import invert, pose_error, renormalize, se3_exp, se3_log
from ti_fusion.tracking.icp import ICP, ICPResult
from ti_fusion.kernels.pyramid import FramePyramid, grey_image
from ti_fusion.slam.checks import check_frame
from ti_fusion.slam.poses import PoseStore
from ti_fusion.slam.result import FrameResult
from ti_fusion.slam.session import LOST_FRAMES, localize_frame, odometry_settles
from ti_fusion.status import Tracking, alignment_status
from ti_fusion.timing import StageTimer, Stopwatch

log = logging.getLogger(__name__)

# ICP's coarsest level must hold many times icp.min_inliers pixels: at small sizes only a fifth to a third of
# them find a correspondence (image borders, depth edges and missing normals take a larger share).
COARSE_PIXELS_PER_INLIER = 6
# A guess that misses the step by more than this (twist norm, radians and metres together) and by half the
# step marks the speed as changed.
IRREGULAR_FLOOR = 0.01
# Between starts that converged to about the same pose the scores differ by noise: another start replaces the
# motion model's alignment only when it fits better by more than this.
SCORE_MARGIN = 0.02
# A start moved along a weak direction from the motion start's alignment (``slam.slide_ratio``) is the same guess
# in another minimum of a nearly flat cost: the right one scored 0.006-0.014 above the wrong one on the real TUM
# cabinet keyframes (docs/TRACKING.md), so it replaces the motion start's alignment by this margin instead.
SLIDE_MARGIN = 0.005
# The residual a start is judged against: the median of the last this many tracked frames (doubt is on from the
# first of them: a wrong minimum that passes every check early in a run corrupts the map for the rest of it;
# docs/TRACKING.md).
RECENT_FRAMES = 10
# The last resort before a frame is lost: the turn went on faster than the guess. ICP's basin is about 15 deg
# (measured in docs/BENCHMARKS.md), so the starts add this much rotation to the guess about its own axis (about
# the camera's vertical both ways when it did not turn).
TURN_DEG = (15.0, 30.0, 45.0)
# The starts that follow the motion model's guess (a localisation off the map: odometry from the last frame): a win
# of another start says the guess is in doubt.
GUESSES = ("motion", "slide", "odometry")
# Below this rotation (radians) the guess's step has no axis to turn on.
TURN_FLOOR = np.radians(1.0)


@dataclass
class Hypothesis:
    """One start of ICP for a frame and what came of it."""

    name: str  # "motion" (the motion model), "last" (the last good pose), "features" (ORB + PnP), "wide", "turn"
    icp: ICPResult
    pose: np.ndarray  # camera-to-world
    failure: str  # "" where the alignment passed the checks (``DenseSLAM._health`` against the start)
    score: float = 0.0  # ``DenseSLAM.alignment_score`` where more than one start passed the checks

    @property
    def ok(self) -> bool:
        return not self.failure

    @property
    def status(self) -> str:
        return alignment_status(self.failure)


class DenseSLAM:
    """Frame-to-model tracking and mapping. One verb: ``register_frame``."""

    def __init__(self, config: Config, intrinsics: Intrinsics):
        # Its fields belong to this start of Taichi, on this thread (ti_fusion.backend.check_usable).
        self._generation = current_backend().generation
        check_usable(self._generation, "DenseSLAM")
        self.config = config
        self.intrinsics = intrinsics
        levels = len(config.icp.iterations)
        H, W = intrinsics.height, intrinsics.width
        self.map_level = map_level = config.fusion.map_level(W)
        # The incoming frame: ICP target (averaged down to the map's level first).
        frame_level = config.frame_input_level(W)
        # The map rendered at the last pose: ICP source, at the map's resolution: level l of the model is
        # aligned to level l of the frame maps, at the same resolution. Both in one set of fields where their
        # levels have the same sizes (``FramePyramid.pair``: the same kernel instances build both).
        self.model_intrinsics = intrinsics.downsampled(2**map_level)
        self.frame_pyramid, self.model_pyramid = FramePyramid.pair_lent_to(
            self, config.pyramid, (H, W, max(levels, map_level - frame_level + 1), frame_level),
            (self.model_intrinsics.height, self.model_intrinsics.width, levels))
        self.icp = ICP(config.icp)
        # Dense re-localisation: the same levels with more iterations and wider gates at the coarse ones.
        wide = config.slam.relocalise_iterations
        self.wide_icp = ICP(replace(config.icp, level_dist_scale=config.slam.relocalise_level_dist_scale,
                                    iterations=list(wide) if len(wide) == levels else config.icp.iterations))
        # The comparable measure between starts: one pass at the finest level with a tight gate, where an
        # alignment in a wrong minimum (that the wide gates of tracking let pass) finds few correspondences.
        self.score_icp = ICP(replace(config.icp, iterations=[0] * (levels - 1) + [1],
                                     dist_threshold=config.slam.score_gate))
        self.mapper = SurfelMapper(config.fusion)
        warning = coarse_level_warning(config.icp, self.model_pyramid.shapes[-1],
                                       (self.frame_pyramid.height, self.frame_pyramid.width))
        if warning:
            log.warning(warning)
        self.poses = PoseStore()  # the trajectory, each pose with its keyframe (loop closure corrects it)
        self.skipped: list[tuple[int, str]] = []  # (frame, reason) of the frames before the map started
        self._residuals: deque[float] = deque(maxlen=RECENT_FRAMES)  # ICP residuals of the last tracked frames
        self.seed(None, None)  # tracking's state: from nowhere, at rest
        self._frames_fused = 0
        self._degeneracy_warned = False  # the warning that depth (and colour) leave directions unconstrained
        self.session = None  # a session against a saved map (``start_session``; ti_fusion/slam/session.py)
        self.loop = None  # loop closure: keyframes, place recognition, verification, the pose graph
        # the saved map this one started from (``from_map``), its surfels left out; None for a new map
        self.loaded_map = None
        if config.slam.loop_closure:
            from ti_fusion.loop.closure import LoopClosure  # GTSAM: imported only when loop closure is on

            self.loop = LoopClosure(config)

    # -- the verb -------------------------------------------------------------------------------
    def register_frame(self, frame: Frame) -> FrameResult:
        """Track ``frame`` against the model, fuse it, then loop closure (``result.loop``: its report on a
        frame that became a keyframe; a loop applied has moved ``poses`` and the map)."""
        check_usable(self._generation, "DenseSLAM.register_frame")
        result = self._track_and_fuse(frame)
        if self.loop is not None and not self.localizing:
            with Stopwatch(result.ms, "loop"):
                result.loop = self._close_loops(frame, result)
        return result

    def _close_loops(self, frame: Frame, result: FrameResult):
        """Loop closure's part of the frame, and what it reports applied here."""
        report = self.loop.after_frame(frame, result, self.loop_maps())
        if report is not None:
            self.start_keyframe(report.keyframe)
            if report.corrections is not None:
                watch = Stopwatch()
                self.apply_corrections(report.corrections)
                report.ms["correct"] += watch.ms  # with loop closure's own part of the correction
        return report

    def _frame_maps(self, frame: Frame, terms) -> None:
        """The frame's pyramid: depth, grey where the tracking ``terms`` read intensity, and the colour that
        fusion reads, in one launch."""
        grey = None
        if "intensity" in self.icp.needs(terms):
            grey = grey_image(frame.color)
            if frame.meta.get("color_valid") is not None:  # registered colour: none where the camera saw none
                grey[~frame.meta["color_valid"]] = -1.0
        self.frame_pyramid.compute(frame.depth, frame.intrinsics, grey, frame.color,
                                   self.mapper.frame_level(self.frame_pyramid))

    def warm_up(self, frame: Frame) -> None:
        """Before the first frame, while it is being made in another process: the kernels of a frame's maps,
        of the prediction and of ICP first launched (compiled, with an empty kernel cache) on ``frame``, a
        blank frame of the run's camera, and the map's prediction from the origin; the first frames' maps and
        predictions replace what they leave, and the alignment's result is dropped. Nothing when ``frame`` is
        not of this map's size or a frame was registered already."""
        check_usable(self._generation, "DenseSLAM.warm_up")
        if frame.depth.shape != self.frame_pyramid.input_shape or self.poses or self.skipped:
            return
        terms = self.icp.terms_for(frame)
        self._frame_maps(frame, terms)
        source, _ = self._reference("intensity" in self.icp.needs(terms), at=np.eye(4))
        self.icp.align(source, self.frame_pyramid, init=np.eye(4), terms=self.icp.ready(terms, source,
                                                                                        self.frame_pyramid))

    def _track_and_fuse(self, frame: Frame) -> FrameResult:
        check_frame(self, frame)  # one InputError for a frame this map cannot take (ti_fusion/slam/checks.py)
        timer = StageTimer()  # this frame's stages only: a lost frame has no "fuse" time
        terms = self.icp.terms_for(frame)  # the tracking terms besides the geometry that this frame can use
        if self.loop is not None and self.poses and not self.localizing and not self._lost_streak and \
                (self.session is None or self.session.localised):  # to be tracked (``_track``, below): where the
            # guess makes it a keyframe, its image work for loop closure starts beside the frame (loop/lookahead.py);
            # not after a lost frame, whose guess is the extrapolation that failed
            self.loop.look_ahead(frame, self._guess(frame.timestamp))
        with timer.stage("pyramid"):
            self._frame_maps(frame, terms)
        if self.session is not None and not self.session.localised:  # where in the map? (slam/session.py)
            from ti_fusion.slam.session import find_in_map

            with timer.stage("track"):
                result = find_in_map(self, frame, terms)
            if not result.tracked:
                result.ms = dict(timer.last)
                return result
        elif not self.poses and (problem := self.unusable(frame)):
            self.skipped.append((frame.index, problem))
            return FrameResult(frame.index, frame.timestamp, None, Tracking.SKIPPED, problem, ms=dict(timer.last))
        elif not self.poses:
            pose = frame.gt_pose if frame.gt_pose is not None and self.config.slam.start_at_ground_truth \
                else np.eye(4)
            result = FrameResult(frame.index, frame.timestamp, pose.copy(), Tracking.INIT)
            if self.skipped:
                (first, reason), n = self.skipped[0], len(self.skipped)
                which = f"frame {first} was" if n == 1 else \
                    f"the first {n} frames ({first} to {self.skipped[-1][0]}) were"
                log.warning(f"{which} skipped ({reason}): the map starts at frame {frame.index}")
        elif self.localizing:
            with timer.stage("track"):  # against the map, or by odometry off it (slam/session.py)
                result = localize_frame(self, frame, terms)
        else:
            with timer.stage("track"):
                result = self._track(frame, terms)
        before = self._held_pose() if self.poses else None  # the motion model's pose before this frame
        if result.tracked and not self.localizing:
            with timer.stage("fuse"):
                result.fusion = self.mapper.integrate(self.frame_pyramid, frame.color, result.pose,
                                                      self._frames_fused)
            self._frames_fused += 1
        if result.tracked:
            self.last_good = (frame, result.pose)
            if self.localizing:
                self.session.keep_maps(self, frame)  # the next frame's odometry source, if it leaves the map
        self._update_motion(result, frame.timestamp, before)
        if self.localizing and self._lost_streak >= LOST_FRAMES:
            self.session.lost_track(frame.index)  # off the map: look for itself again (slam/session.py)
            self.seed(None, None)
        result.ms = dict(timer.last)
        return result

    def unusable(self, frame: Frame) -> str | None:
        """Why the map cannot start at ``frame`` (None: it can). The first frame's surfels are what the next
        frame is tracked against: a map with fewer than ``icp.min_inliers`` of them loses every later frame."""
        valid = int(np.count_nonzero(frame.depth > 0))
        needed = self.config.icp.min_inliers * 4**self.map_level  # pixels, for min_inliers at the map's level
        if valid == 0:
            return "no valid depth"
        if valid < needed:
            return (f"{valid} pixels with depth, fewer than the {needed} the map needs to start "
                    f"(icp.min_inliers = {self.config.icp.min_inliers} at its resolution)")
        return None

    # -- tracking -------------------------------------------------------------------------------
    def _held_pose(self) -> np.ndarray:
        """The pose the motion model extrapolates from: the last tracked frame's (never a lost frame's)."""
        return self.last_good[1] if self.last_good is not None else self.poses[-1]

    def _predicted_pose(self, timestamp: float) -> np.ndarray:
        """The motion model's guess at ``timestamp``: the last tracked motion per second over the time since
        the last tracked frame, from that frame's pose (so lost frames never compound it)."""
        guess = self._guess(timestamp)
        return renormalize(guess) if self.config.slam.motion_model else guess.copy()

    def _guess(self, timestamp: float) -> np.ndarray:
        """The motion model's guess at ``timestamp`` before ``_predicted_pose`` renormalises it (the same product,
        worked out once): for loop closure's keyframe test on the guess, which needs no more."""
        last = self._held_pose()
        return self._extrapolate(last, self._elapsed(timestamp)) if self.config.slam.motion_model else last

    def _extrapolate(self, last: np.ndarray, dt: float) -> np.ndarray:
        """``last`` · exp(velocity · dt), not renormalised: the guess and, once the frame is tracked, the motion
        model's check of it take the same product, worked out once (the same pose, velocity and dt)."""
        memo = self.__dict__.get("_extrapolated")
        if memo is not None and memo[0] is last and memo[1] is self._velocity and memo[2] == dt and \
                memo[3] == last.tobytes():
            return memo[4]
        product = last @ se3_exp(self._velocity * dt)
        self._extrapolated = (last, self._velocity, dt, last.tobytes(), product)
        return product

    def _elapsed(self, timestamp: float) -> float:
        """Seconds since the last posed frame, or 1 (a frame) where the timestamps do not increase."""
        dt = timestamp - self._last_stamp if self._last_stamp is not None else 0.0
        return dt if np.isfinite(dt) and dt > 0 else 1.0

    def _reference(self, intensity: bool = False, at: np.ndarray | None = None) -> tuple[FramePyramid, np.ndarray]:
        """The ICP source and the camera-to-world pose of its camera frame (with ``intensity``, its intensity
        too: the model's colour at each pixel of the prediction): the map rendered at the held pose, or ``at``."""
        last = self._held_pose() if at is None else at
        fusion = self.config.fusion
        # Only confirmed surfels predict the surface (Keller's stable points, fusion.render_min_weight),
        # once the map has had time to confirm any: at first every surfel is new, and a prediction
        # without them would be empty, every frame lost and never fused.
        warm = self._frames_fused >= fusion.unstable_age
        # slam.active_window: only the active model (surfels updated lately) is tracked against (ElasticFusion)
        window = 0 if self.session is not None and self.session.whole_map else self.config.slam.active_window
        self.mapper.render_pyramid(self.model_pyramid, last, self.model_intrinsics,
                                   min_weight=fusion.render_min_weight if warm else 0.0,
                                   min_time=self._frames_fused - window if window > 0 else -2**31, intensity=intensity)
        return self.model_pyramid, last

    def _track(self, frame: Frame, terms: tuple[str, ...] = ()) -> FrameResult:
        cfg = self.config.slam
        predicted = self._predicted_pose(frame.timestamp)
        source, last = self._reference("intensity" in self.icp.needs(terms))
        terms = self.icp.ready(terms, source, self.frame_pyramid)
        tried: list[Hypothesis] = []

        def attempt(name: str, guess: np.ndarray, icp: ICP | None = None, depth_first: bool = False) -> Hypothesis:
            # ICP maps source points (camera frame of `last`) into the new camera: T = inv(T_wc_new) · T_wc_last.
            init = invert(guess) @ last
            if depth_first and terms:  # a start far from the frame: the photometric basin is narrower than depth's
                geometry = (icp or self.icp).align(source, self.frame_pyramid, init=init)
                init = init if geometry.failure else geometry.pose
            result = (icp or self.icp).align(source, self.frame_pyramid, init=init, terms=terms)
            pose = renormalize(last @ invert(result.pose))
            tried.append(Hypothesis(name, result, pose, self._health(result, pose, guess, predicted)))
            return tried[-1]

        def settled() -> bool:  # the best so far passes the checks without doubt, and the guess is trusted
            return cfg.hypotheses != "always" and not self._guess_beaten and \
                any(h.ok and not self._doubtful(h) for h in tried)

        first = attempt("motion", predicted)
        self._report_degeneracy(frame, first.icp)
        if cfg.hypotheses != "motion":
            held = self._held_pose()
            apart = pose_error(predicted, held)
            # after a failure the start from rest is tried as well as the guess that coasts on
            if (not settled() or self._lost_streak) and (apart[0] > 0.1 or apart[1] > 1e-3):
                attempt("last", held, depth_first=True)
        if not settled() and cfg.relocalise == "features" and (cfg.hypotheses != "motion" or not first.ok):
            self._relocalise(frame, source, last, terms, tried, predicted)
        if not settled() and cfg.hypotheses != "motion":
            attempt("wide", last, self.wide_icp, depth_first=True)  # dense re-localisation: a wider basin
        if not any(h.ok for h in tried) and cfg.hypotheses != "motion":
            for start in self._turned(predicted):  # a turn faster than the guess's
                attempt("turn", start, depth_first=True)
        if cfg.hypotheses != "motion":
            slid = self._slid(first, last)  # the other minima along a direction depth leaves weak
            if slid and len(tried) == 1 and self.localizing:
                # a localisation's odometry from the last frame, which sees more than the map, settles it cheaper
                # (slam/session.py); it fills the source with that frame's maps, so the map is rendered again
                if odometry_settles(self, frame, first.pose):
                    slid = []
                else:
                    source, last = self._reference("intensity" in self.icp.needs(terms), at=last)
            for start in slid:
                attempt("slide", start)
        passed = [h for h in tried if h.ok]
        if len(passed) > 1:
            for h in passed:
                h.score = self.alignment_score(source, h, terms)
        best = max(passed, key=lambda h: h.score + (SCORE_MARGIN if h is first else SCORE_MARGIN - SLIDE_MARGIN
                                                    if h.name == "slide" else 0.0)) if passed else \
            max(tried, key=lambda h: h.icp.inlier_ratio)
        tracking = Tracking.LOST if not best.ok else \
            Tracking.OK if best.name in ("motion", "last", "slide") else Tracking.RELOCALISED
        pose = best.pose if best.ok else predicted  # a lost frame reports the guess; it is not fused
        return FrameResult(frame.index, frame.timestamp, pose, tracking, best.failure, icp=best.icp,
                           hypothesis=best.name, tried=[f"{h.name}: {h.status}" for h in tried])

    def _slid(self, base: Hypothesis, last: np.ndarray) -> list[np.ndarray]:
        """Starts moved from the motion start's alignment ``base`` along the weakest direction of its geometry,
        where depth leaves that direction weak enough (``slam.slide_ratio``) for projective ICP to stop in
        another minimum along it, and colour does not constrain it (``slam.slide_color_ratio``; docs/TRACKING.md):
        ``slam.slide_steps`` metres of its translation each way."""
        cfg = self.config.slam
        weakest = (base.icp.degeneracy or {}).get("weakest")
        if not base.ok or weakest is None or weakest["ratio"] >= cfg.slide_ratio or \
                weakest["joint_ratio"] >= cfg.slide_color_ratio:
            return []
        twist = np.asarray(weakest["twist"])
        length = np.linalg.norm(twist[3:])
        if length < 0.5:  # mostly a rotation: not a slide
            return []
        return [renormalize(last @ invert(se3_exp(twist * (sign * step / length)) @ base.icp.pose))
                for step in cfg.slide_steps for sign in (1.0, -1.0)]

    def _turned(self, predicted: np.ndarray) -> list[np.ndarray]:
        """Starts that turn TURN_DEG further than the guess ``predicted``: about the axis of its rotation, or
        about the camera's vertical both ways where it hardly turned."""
        held = self._held_pose()
        twist = se3_log(renormalize(invert(held) @ predicted))  # the guess's step (none without the motion model)
        angle = np.linalg.norm(twist[:3])
        axes = [twist[:3] / angle] if angle > TURN_FLOOR else [np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])]
        return [renormalize(held @ se3_exp(np.concatenate([twist[:3] + axis * np.radians(deg), twist[3:]])))
                for axis in axes for deg in TURN_DEG]

    def alignment_score(self, source: FramePyramid, h: Hypothesis, terms: tuple[str, ...] = ()) -> float:
        """How well a start's alignment of this frame's prediction fits the frame, comparable between starts
        (the same prediction and frame): the fraction of the prediction's pixels within slam.score_gate of
        the frame at its pose, times 1 − their RMS residual / slam.score_gate."""
        fit = self.score_icp.align(source, self.frame_pyramid, init=h.icp.pose, terms=terms)
        residual = fit.residual_rms if np.isfinite(fit.residual_rms) else self.config.slam.score_gate
        return float(fit.inlier_ratio * max(0.0, 1.0 - residual / self.config.slam.score_gate))

    def _doubtful(self, h: Hypothesis) -> bool:
        """The alignment failed the checks, or passed them with a residual well above the recent frames'."""
        if not h.ok:
            return True
        if not self._residuals:
            return False
        return h.icp.residual_rms > self.config.slam.doubt_residual_ratio * statistics.median(self._residuals)

    def _health(self, icp: ICPResult, pose: np.ndarray, start: np.ndarray, guess: np.ndarray | None = None) -> str:
        """Why the alignment fails the checks, or "" where it passes them. The jump is measured from the
        alignment's ``start`` and from the motion model's ``guess`` (the same pose for the motion start): a
        pose near either is plausible (from the last pose, a long gap between frames is a long step)."""
        cfg = self.config.slam
        if icp.failure:
            return icp.failure
        if icp.inlier_ratio < cfg.min_inlier_ratio:
            return f"inlier ratio {_beside(icp.inlier_ratio, cfg.min_inlier_ratio, 2)} < {cfg.min_inlier_ratio:g}"
        if icp.residual_rms > cfg.max_residual:
            return (f"residual {_beside(icp.residual_rms * 1e3, cfg.max_residual * 1e3, 1)} mm > "
                    f"{cfg.max_residual * 1e3:g} mm")

        def jump(reference) -> tuple[float, float] | None:  # (degrees, metres) beyond the limits, else None
            rot_deg, trans_m = pose_error(pose, reference)
            return (rot_deg, trans_m) if rot_deg > cfg.max_update_deg or trans_m > cfg.max_update_m else None

        if (far := jump(start)) and (guess is None or jump(guess)):
            rot_deg, trans_m = far
            return (f"jump of {_beside(rot_deg, cfg.max_update_deg, 1)} deg / "
                    f"{_beside(trans_m * 100, cfg.max_update_m * 100, 1)} cm from its start (at most "
                    f"{cfg.max_update_deg:g} deg / {cfg.max_update_m * 100:g} cm)")
        return ""

    def _report_degeneracy(self, frame: Frame, icp: ICPResult) -> None:
        """Log the weak directions of the geometry (debug, every frame that has any), and warn once when
        depth alone leaves some unconstrained and colour did not constrain them all."""
        d = icp.degeneracy
        if not d or not d["weak"]:
            return
        twists = "; ".join(f"{'(colour)' if w['color'] else ''}{w['twist']} at {w['ratio']:.1e}"
                           for w in d["directions"])
        log.debug(f"frame {frame.index}: {d['weak']} weak direction(s) of the geometry (twist (ω, v), λ/λmax), "
                  f"{d['constrained_by_color']} constrained by colour: {twists}")
        if d["constrained_by_color"] < d["weak"] and not self._degeneracy_warned:
            self._degeneracy_warned = True
            hint = "" if self.config.icp.color_weight > 0 else \
                " (icp.color_weight > 0 adds the photometric term where colour is registered to depth)"
            log.warning(f"frame {frame.index}: the depth constrains only {6 - d['weak']} of the 6 directions of "
                        f"the camera's motion, and colour {d['constrained_by_color']} of the other {d['weak']}: "
                        f"tracking may slide{hint}")

    def _relocalise(self, frame: Frame, source: FramePyramid, last: np.ndarray, terms: tuple[str, ...],
                    tried: list[Hypothesis], predicted: np.ndarray) -> None:
        """ICP again, initialised by ORB + PnP against the last well-tracked frame (a "features" hypothesis,
        checked against the PnP estimate)."""
        if self.last_good is None or frame.color is None or self.last_good[0].color is None:
            return
        from ti_fusion.tracking.features import estimate_relative_pose

        reference, reference_pose = self.last_good
        estimate = estimate_relative_pose(reference, frame, self.config.vo)
        if estimate.pose is None:
            return
        # The estimate maps the reference frame's camera into the new one; ICP's source (the prediction) sits
        # at `last`, the reference frame's pose.
        init = estimate.pose @ invert(reference_pose) @ last
        icp = self.icp.align(source, self.frame_pyramid, init=init, terms=terms)
        pose = renormalize(last @ invert(icp.pose))
        rough = renormalize(reference_pose @ invert(estimate.pose))
        tried.append(Hypothesis("features", icp, pose, self._health(icp, pose, rough, predicted)))

    def _update_motion(self, result: FrameResult, timestamp: float, before: np.ndarray | None) -> None:
        """The motion per second of the step just tracked (from the last tracked frame, over the lost ones
        between), damped when the guess missed it by more than half the step (the speed changed); a lost frame
        leaves it as it was."""
        cfg = self.config.slam
        self._lost_streak = self._lost_streak + 1 if result.lost else 0
        if before is not None and result.tracked:
            dt = self._elapsed(timestamp)
            step = se3_log(renormalize(invert(before) @ result.pose))
            predicted = self._extrapolate(before, dt)
            missed = np.linalg.norm(se3_log(renormalize(invert(predicted) @ result.pose)))
            irregular = bool(np.any(self._velocity)) and (  # from rest, a miss says nothing of the speed
                result.hypothesis not in GUESSES or
                missed > max(0.5 * np.linalg.norm(step), IRREGULAR_FLOOR))
            self._velocity = step / dt * (cfg.motion_damping if irregular else 1.0)
            self._guess_beaten = result.hypothesis not in GUESSES
        if result.tracked:
            self._last_stamp = timestamp
            # odometry's residual is against the last frame, not the map: the recent residuals are the map's
            if result.icp is not None and np.isfinite(result.icp.residual_rms) and \
                    result.tracking is not Tracking.ODOMETRY:
                self._residuals.append(float(result.icp.residual_rms))
        self.poses.append(result.pose, result.index, timestamp)

    # -- what loop closure reports, applied ----------------------------------------------------------
    def loop_maps(self):
        """What loop closure reads of this frame (``LoopMaps``): its maps, the scratch maps it may fill, and the
        level of the map's resolution."""
        from ti_fusion.loop.closure import LoopMaps

        return LoopMaps(self.frame_pyramid, self.scratch_pyramid(), self.mapper.frame_level(self.frame_pyramid))

    def scratch_pyramid(self) -> FramePyramid:
        """Maps at the map's resolution that may be filled between frames, until the next
        ``register_frame``: the model prediction's, which the next frame's tracking renders anew. Loop
        verification builds an earlier keyframe's maps here, so its (depth-only) ICP runs the kernels that
        depth-only tracking compiled for this pair of maps instead of compiling (or loading) its own, a
        second or more in the middle of a run."""
        return self.model_pyramid

    def start_keyframe(self, keyframe: int) -> None:
        """The frame just registered became keyframe ``keyframe``: its pose, the poses after it and the
        surfels fused from the next frame on move with it."""
        self.poses.start_keyframe(keyframe)
        self.mapper.anchor = keyframe

    def apply_corrections(self, corrections: np.ndarray) -> None:
        """A loop closed: every pose and surfel moves by its keyframe's correction C_k (K×4×4, world
        frame); with ``slam.active_window`` the corrected confirmed surfels are active again."""
        self.poses.correct(corrections)
        if self.last_good is not None:
            frame = self.last_good[0]
            self.last_good = (frame, self.poses.pose_of(frame.index))
        window = self.config.slam.active_window
        self.mapper.apply_corrections(corrections, reactivate_at=self._frames_fused if window > 0 else None)

    # -- a saved map (ti_fusion/slam/saved_map.py, docs/MAPS.md) ---------------------------------
    @classmethod
    def from_map(cls, source, config: Config | None = None, intrinsics: Intrinsics | None = None) -> "DenseSLAM":
        """A DenseSLAM holding a saved map (a ``SavedMap``, or a path ``load_map`` takes), ready for frames to
        track against it: its surfels, clock and anchor, and with loop closure its keyframes, place recognition
        and pose graph. ``config`` and ``intrinsics`` default to the map's own; others are checked against it
        (``check_camera``: InputError naming both cameras). No pose is registered yet: where the next frame
        is in the map is the caller's to find."""
        from ti_fusion.slam.saved_map import SavedMap, check_camera, load_map, restore

        saved = source if isinstance(source, SavedMap) else load_map(source)
        where = None if isinstance(source, SavedMap) else source
        config = config if config is not None else saved.make_config()
        intrinsics = intrinsics if intrinsics is not None else saved.intrinsics
        check_camera(saved, intrinsics, where, config)
        slam = cls(config, intrinsics)
        restore(slam, saved)
        return slam

    def map_state(self):
        """The map as it is now, as a ``SavedMap`` (copies: the run goes on unchanged)."""
        from ti_fusion.slam.saved_map import capture

        return capture(self)

    def map_trajectory(self) -> tuple:
        """(timestamps, N×4×4 camera-to-world poses) of every posed frame of the map: a loaded map's earlier
        sessions' frames, moved with its keyframes by this run's loops, then this run's (map_trajectory.tum)."""
        from ti_fusion.slam.saved_map import map_trajectory

        return map_trajectory(self)

    def save_map(self, folder):
        """The map as it is now, written into ``folder`` (map.json and map.bin; docs/MAPS.md); returns the folder."""
        return self.map_state().write(folder)

    # -- a session against a saved map (ti_fusion/slam/session.py) -----------------------------------
    @property
    def localizing(self) -> bool:
        """A session that tracks against the map without changing it (``start_session(localize=True)``)."""
        return self.session is not None and self.session.localize

    def start_session(self, localize: bool = False) -> None:
        """The map is a saved one (or this run's, handed over): the camera's pose is unknown from the next frame
        on, each frame looking for itself among the map's keyframes until one finds itself; then the session
        extends the map, or with ``localize`` tracks against it without changing it. Its trajectory
        (``poses``) starts empty, in the map's frame."""
        from ti_fusion.errors import InputError
        from ti_fusion.slam.session import Session

        if localize and self.config.map.unfound == "map-anyway":
            raise InputError(None, "--localize changes no map and --unfound map-anyway maps: give one of them")
        if self.loop is None:
            raise InputError(None, "a session against a map finds itself among the map's keyframes: it needs "
                                   "slam.loop_closure = true")
        if not self.loop.keyframes:
            raise InputError(None, "the map has no keyframes (it was made with slam.loop_closure = false, or from "
                                   "too few frames): a new session has nothing to find itself in")
        cfg = self.config.map
        self.session = Session(localize, cfg.unfound, cfg.find_frames)
        self.poses = PoseStore()
        self.skipped = []
        self.seed(None, None)
        self.__dict__.pop("_frame_checks", None)  # a new session's timestamps start afresh (slam/checks.py)
        self.loop.begin_session()

    def seed(self, frame: Frame | None, pose: np.ndarray | None) -> None:
        """Tracking starts afresh from ``pose`` (the frame that gave it: feature re-localisation's reference), at
        rest, with no recent residuals; None: from nowhere (a session that has not found itself)."""
        self.last_good: tuple[Frame, np.ndarray] | None = None  # for feature re-localisation
        if frame is not None:
            self.last_good = (frame, np.array(pose, dtype=np.float64))
        self._velocity = np.zeros(6)  # last motion per second, twist (ω, v) of the camera-to-camera step
        self._last_stamp: float | None = None  # timestamp of the last tracked frame
        self._lost_streak = 0  # frames lost since the last tracked one
        # Another start than the motion model's won the last tracked frame: the next guess is in doubt too, and
        # every start is tried (a wrong minimum can pass every check with a residual as low as the recent ones).
        self._guess_beaten = False
        self._residuals.clear()

    def reactivate_map(self) -> None:
        """The confirmed surfels of the whole map count as updated now, so the active window renders the place
        a session found itself in whatever its age (as after a loop)."""
        if self.config.slam.active_window > 0:
            self.mapper.map.reactivate(self._frames_fused, self.config.fusion.unstable_weight)

    def own_map(self) -> None:
        """A session that did not find itself maps on in its own frame (``map.unfound = map-anyway``): the
        loaded map, its keyframes and its graph are set aside; the next usable frame starts a new map."""
        # emptied in place: a new mapper would allocate a second map's fields (and their kernels) beside these
        self.mapper.map.count = 0
        self.mapper.anchor = 0
        self.loaded_map = None  # its keyframes and trajectory are not this map's
        self._frames_fused = 0
        self.poses = PoseStore()
        self.seed(None, None)
        if self.loop is not None:
            from ti_fusion.loop.closure import LoopClosure

            self.loop = LoopClosure(self.config)

    # -- results --------------------------------------------------------------------------------
    @property
    def surfels(self) -> int:
        return self.mapper.count

    def resolution(self) -> dict:
        """What the auto settings resolved to: the map's pyramid level and size, the size the frame is
        tracked at, and the depth smoothing radius (pixels at that size)."""
        model, frame = self.model_intrinsics, self.frame_pyramid
        return {"map_level": self.map_level,
                "map_size": [model.width, model.height], "tracked_at": [frame.width, frame.height],
                "depth_smooth_radius": frame.smooth_radius}


def _beside(value: float, limit: float, digits: int) -> str:
    """``value`` with at least ``digits`` decimals, and as many more as it takes to show on which side of
    ``limit`` it is (a ratio of 0.1496 against 0.15 reads 0.1496, not 0.15)."""
    while digits < 12 and round(value, digits) == round(limit, digits):
        digits += 1
    return f"{value:.{digits}f}"


def coarse_level_warning(icp: ICPConfig, coarsest: tuple[int, int], tracked: tuple[int, int]) -> str | None:
    """A line saying that frames tracked at ``tracked`` (height, width) leave ICP's coarsest level
    (``coarsest``) too few pixels for ``icp.min_inliers`` correspondences, so frames will be lost; or None."""
    (h, w), (H, W) = coarsest, tracked
    if h * w >= COARSE_PIXELS_PER_INLIER * icp.min_inliers:
        return None
    return (f"tracking at {W}x{H} leaves ICP's coarsest level ({len(icp.iterations)} levels in icp.iterations) "
            f"{w}x{h} = {h * w} pixels, too few for icp.min_inliers = {icp.min_inliers} correspondences (at this "
            "size a fifth to a third of the pixels find one): expect lost frames. Use a smaller --downsample, "
            "fewer levels in icp.iterations or a lower icp.min_inliers")
