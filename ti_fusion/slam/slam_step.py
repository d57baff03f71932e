"""``ti-fusion slam``'s step in the pipeline: dense SLAM (``DenseSLAM.register_frame``: tracking, fusion and,
with ``slam.loop_closure``, loop closure) on each frame; what the sinks read of it: the /slam/stats message,
the surfel map, the loop edges; and the run's summary fields."""

from __future__ import annotations

import numpy as np

from ti_fusion.config import Config
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.mcap_log import json_field, json_object
from ti_fusion.slam.dense import DenseSLAM, FrameResult
from ti_fusion.status import Tracking
from ti_fusion.tracking.terms import term_classes


# One entry of loop.candidates (LoopCandidate.record(); a value not measured is left out).
LOOP_CANDIDATE_SCHEMA = json_object({
    "query": json_field("integer", "the current keyframe's id", minimum=0),
    "match": json_field("integer", "the earlier keyframe's id", minimum=0),
    "score": json_field("number", "place recognition's score"),
    "verified": json_field("boolean", "passed verification: a loop for the pose graph"),
    "reason": json_field("string", 'why rejected, or "verified"'),
    "consistent": json_field("integer", "matches passing the 3D-distance pre-check", minimum=0),
    "pnp_inliers": json_field("integer", "PnP RANSAC inliers", minimum=0),
    "icp_inlier_ratio": json_field("number", "the keyframes' ICP inlier ratio (left out: ICP did not run)"),
    "icp_residual_mm": json_field("number", "the keyframes' ICP RMS residual, millimetres (left out: ICP did "
                                            "not run)"),
    "ms": json_field("number", "verifying this candidate on the loop's thread, milliseconds (its pre-check and PnP "
                                 "may have run beside the frame: ti_fusion/loop/lookahead.py)"),
}, required=("query", "match", "score", "verified", "reason", "consistent", "pnp_inliers", "ms"))

# The /slam/stats message, every field (docs/LOGS.md shows one; the pipeline adds ms.load and ms.log).
STATS_SCHEMA = json_object({
    "frame": json_field("integer", "index of the frame in the run (0 = the first frame selected)"),
    "status": json_field("string", '"ok" (a tracked frame, the map\'s first one included), "relocalised", '
                                   '"lost: <reason>" (not fused; its pose is the motion model\'s guess), "skipped: '
                                   '<reason>" (before the map started: no depth enough to start it on; no pose) or '
                                   '"unlocalised: <reason>" (a session against a saved map that has not found itself '
                                   'in it yet; no pose)'),
    "tracking": json_field("string", 'the tracker\'s own word: "init" for the map\'s first frame, else as status'),
    "surfels": json_field("integer", "surfels in the map after this frame"),
    "hypothesis": json_field("string", 'the start of ICP whose alignment was kept: "motion" (the motion model), '
                                       '"last" (the last good pose), "features" (ORB + PnP), "wide" (dense '
                                       're-localisation), "turn" (the guess turned further) or "slide" (the '
                                       'motion start\'s alignment moved along a weak direction); every frame but '
                                       'the first'),
    "hypotheses_tried": json_field("array", "every start tried for the frame, in order, each with its outcome "
                                            '("motion: ok", "last: lost: <reason>", ...)', items={"type": "string"}),
    "ms": json_object({
        "pyramid": json_field("number", "the frame's depth, vertex and normal pyramids, milliseconds"),
        "track": json_field("number", "rendering the model and ICP (with feature relocalisation when it runs), "
                                      "milliseconds; every frame but the first"),
        "fuse": json_field("number", "fusing the frame into the map, milliseconds; fused frames only"),
        "loop": json_field("number", "loop closure: keyframe, place recognition, verification, and on a "
                                     "verified loop the pose graph and the correction, milliseconds; with "
                                     "slam.loop_closure only"),
    }, required=("pyramid",), description="time per stage, milliseconds"),
    "icp": json_object({
        "iterations": json_field("array", "iterations run at each pyramid level, coarse → fine (the order of "
                                          "the setting icp.iterations)", items={"type": "integer", "minimum": 0}),
        "residual_rms_m": json_field("number", "RMS point-to-plane residual of the inliers, metres (left out: "
                                               "no inliers)"),
        "inliers": json_field("integer", "correspondences of the last iteration", minimum=0),
        "inlier_ratio": json_field("number", "inliers / valid pixels of the rendered model, 0 to 1",
                                   minimum=0, maximum=1),
        "condition": json_field("number", "condition number of AᵀA, dimensionless (left out: not computed or "
                                          "infinite)"),
        "update_norm": json_field("number", "norm of the last se(3) update (radians and metres together), the "
                                            "convergence test's value (left out: no update computed)"),
        **{key: json_field(kind, text, **({"minimum": 0} if kind == "integer" else {}))  # each tracking term's
           for cls in term_classes() for key, (kind, text, _) in cls.stats_fields.items()},
        "weak_directions": json_field("integer", "eigen-directions of the geometric AᵀA below icp.weak_ratio of "
                                                 "its largest: what depth alone leaves unconstrained", minimum=0),
        "weak_constrained_by_color": json_field("integer", "of those, the ones the photometric term lifted above "
                                                           "icp.weak_ratio", minimum=0),
    }, required=("iterations", "inliers", "inlier_ratio"),
        description="the frame's ICP against the model, of its last iteration; every frame but the first"),
    "merged": json_field("integer", "pixels averaged into an existing surfel; fused frames only", minimum=0),
    "added": json_field("integer", "new surfels; fused frames only", minimum=0),
    "covered": json_field("integer", "valid pixels neither merged nor added, because a neighbour's merged surfel "
                                     "covers them; fused frames only", minimum=0),
    "removed": json_field("integer", "surfels removed (unstable, or in front of the measured surface); fused "
                                     "frames only", minimum=0),
    "loop": json_object({
        "keyframe": json_field("integer", "the keyframe's id (0, 1, 2, ...)", minimum=0),
        "why": json_field("string", '"first", "moved", "turned", "overlap" (too little of the last keyframe seen) or '
                                    '"found" (a session\'s frame that found itself in its saved map)'),
        "candidates": json_field("array", "earlier keyframes place recognition proposed, each with its decision",
                                 items=LOOP_CANDIDATE_SCHEMA),
        "applied": json_field("array", "[earlier keyframe, this keyframe] of a loop applied, else []",
                              items={"type": "integer"}),
        "outcome": json_field("string", 'for a verified candidate: "applied" or why the pose graph refused it'),
        "ms": json_object({name: json_field("number", what + ", milliseconds") for name, what in (
            ("keyframe", "choosing the keyframe and its features"), ("detect", "place recognition"),
            ("warmup", "compiling the verification's kernels, at the first keyframe"),
            ("verify", "verifying the candidates"), ("optimise", "the pose graph, on a verified candidate"),
            ("correct", "moving the poses and the map, on an applied loop"))}, description="loop closure's stages"),
    }, required=("keyframe", "why", "candidates", "applied", "outcome", "ms"),
        description="loop closure, on frames that became keyframes (slam.loop_closure)"),
    "localised": json_field("boolean", "a session against a saved map (--map): the frame has a pose in the map's "
                                       "frame (false: not found in the map yet, mapping in its own frame, or off the "
                                       "map in a localisation, posed by odometry: status \"odometry\")"),
    "found": json_object({
        "frame": json_field("integer", "this frame's index in the run", minimum=0),
        "keyframe": json_field("integer", "the map's keyframe it matched", minimum=0),
        "map_frame": json_field("integer", "that keyframe's frame in the run that made the map", minimum=0),
        "score": json_field("number", "place recognition's score"),
        "pnp_inliers": json_field("integer", "PnP RANSAC inliers of the match", minimum=0),
        "icp_inlier_ratio": json_field("number", "the match's dense ICP inlier ratio"),
        "unlocalised_before": json_field("integer", "frames of the session not localised before this one", minimum=0),
    }, required=("frame", "keyframe", "map_frame", "score", "pnp_inliers", "unlocalised_before"),
        description="the event of a session against a saved map: this frame found itself in the map (once)"),
}, required=("frame", "status", "tracking", "surfels", "ms"))


# (stats key, term name, entry of its sums) of every registered term's fields, as STATS_SCHEMA lists them
TERM_STATS = tuple((key, cls.name, entry) for cls in term_classes() for key, (_, _, entry) in cls.stats_fields.items())


def frame_stats(result: FrameResult, surfels: int) -> dict:
    """The /slam/stats message of one frame (``STATS_SCHEMA``)."""
    stats = {"frame": result.index, "status": "ok" if result.tracking is Tracking.INIT else result.status,
             "tracking": result.status, "surfels": surfels, "ms": {k: round(v, 3) for k, v in result.ms.items()}}
    if result.hypothesis is not None:
        stats["hypothesis"] = result.hypothesis
        stats["hypotheses_tried"] = list(result.tried)
    icp = result.icp
    if icp is not None:
        per_level = [0] * (max((it.level for it in icp.iterations), default=-1) + 1)
        for it in icp.iterations:
            per_level[it.level] += 1
        stats["icp"] = {
            "iterations": per_level[::-1],  # coarse → fine, as the setting icp.iterations lists them
            "residual_rms_m": icp.residual_rms,
            "inliers": icp.inliers,
            "inlier_ratio": icp.inlier_ratio,
            "condition": icp.condition,
            "update_norm": icp.update_norm,
            # each registered term's fields (TrackingTerm.stats_fields): 0 rows where it did not run
            **{key: icp.terms.get(term, {}).get(entry, 0) for key, term, entry in TERM_STATS},
        }
        if icp.degeneracy is not None:
            stats["icp"]["weak_directions"] = icp.degeneracy["weak"]
            stats["icp"]["weak_constrained_by_color"] = icp.degeneracy["constrained_by_color"]
    if result.fusion is not None:
        stats.update({"merged": result.fusion.merged, "added": result.fusion.added,
                      "covered": result.fusion.covered, "removed": result.fusion.removed})
    if result.loop is not None:
        stats["loop"] = result.loop.stats()
        stats["loop"]["applied"] = stats["loop"]["applied"] or []  # no loop applied: [], one type for Foxglove
    return stats


class SLAMStep:
    """Frame-to-model tracking, mapping and loop closure of each frame (``DenseSLAM``)."""

    name = "slam"
    stats_channel = "/slam/stats"
    stats_schema = STATS_SCHEMA
    stages = ("pyramid", "track", "fuse", "loop")
    estimates_poses = True

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config
        self.dataset_name = dataset.name
        if config.map.map:  # a second session: the saved map's camera is checked against the data's here
            self.slam = DenseSLAM.from_map(config.map.map, config, dataset.intrinsics)
            self.slam.start_session(localize=config.map.localize)
        else:
            self.slam = DenseSLAM(config, dataset.intrinsics)

    def warm_up(self, dataset: Dataset) -> None:
        """While the first frame is being rendered in a reader process: the kernels of its maps, on a blank
        frame of ``dataset``'s camera (``DenseSLAM.warm_up``)."""
        K = dataset.intrinsics
        blank = Frame(-1, 0.0, np.zeros((K.height, K.width), np.float32), K,
                      np.zeros((K.height, K.width, 3), np.uint8), color_registered=dataset.color_registered)
        self.slam.warm_up(blank)

    @property
    def warmup_frames(self) -> int:
        """The map's first frame compiles the maps and fusion kernels, the next one rendering and ICP; frames
        skipped before the map started come first."""
        session = self.slam.session  # a session's frames before it found itself do not count either
        before = 0 if session is None else \
            session.found["unlocalised_before"] if session.found is not None else len(session.unlocalised)
        return len(self.slam.skipped) + before + 2

    @property
    def mapper(self):
        return self.slam.mapper

    def register_frame(self, frame: Frame) -> FrameResult:
        return self.slam.register_frame(frame)  # on a loop, also corrects the trajectory and the map

    def loop_edges(self) -> list:
        """Every loop candidate checked, as (from, to, applied) world points (/loop_closures, trajectory.png)."""
        return self.slam.loop.edges() if self.slam.loop is not None else []

    def stats(self, result: FrameResult) -> dict:
        stats = frame_stats(result, self.slam.surfels)
        session = self.slam.session
        if session is not None:
            stats["localised"] = result.pose is not None and session.own_map_at is None and \
                result.tracking is not Tracking.ODOMETRY
            if result.found is not None:
                stats["found"] = result.found
        return stats

    def map_points(self, max_points: int):
        return self.slam.mapper.sample_points(max_points) if self.slam.surfels else None

    def current_poses(self) -> dict[int, np.ndarray]:
        return self.slam.poses.by_frame()  # loop closure moves them after their frames

    def plot_title(self, run) -> str:
        return f"ti-fusion slam: {self.dataset_name}"

    def summary(self, run) -> dict:
        slam = self.slam
        first = next((r for r in run.results if r.pose is not None), None)
        lost = [r for r in run.results if r.lost]
        return {
            "surfels": slam.surfels,
            "resolution": slam.resolution(),
            "tracking_failures": len(lost),
            "failed_frames": [{"frame": r.index, "reason": r.status} for r in lost][:50],
            "relocalised": sum(r.tracking is Tracking.RELOCALISED for r in run.results),
            "hypotheses_won": {name: sum(r.hypothesis == name and r.tracked for r in run.results)
                               for name in ("motion", "last", "features", "wide", "turn", "slide")},
            "frames_with_second_start": sum(len(r.tried) > 1 for r in run.results),
            "map_started_at": None if first is None else first.index,
            "skipped_frames": [{"frame": f, "reason": reason} for f, reason in slam.skipped][:50],
            **self.loop_summary(),
            **(slam.session.summary() if slam.session is not None else {}),
        }

    def loop_summary(self) -> dict:
        """summary.json's loop closure fields: the counts (0 with slam.loop_closure off), the loops, the
        candidates with their decisions, and the milliseconds per call of each part."""
        if self.slam.loop is None:
            return {"keyframes": 0, "loop_candidates": 0, "loops_applied": 0}
        return self.slam.loop.summary()
