"""``ti-fusion slam``'s step in the pipeline: dense SLAM (``DenseSLAM.register_frame``) on each frame,
the /slam/stats message, the surfel map for /map/points, and the map's files after the loop."""

from __future__ import annotations

import logging

from ti_fusion.config import Config
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.mcap_log import json_field, json_object
from ti_fusion.mapping.views import save_views, view_pose
from ti_fusion.slam.dense import DenseSLAM, FrameResult

log = logging.getLogger(__name__)


# The /slam/stats message, every field (docs/LOGS.md shows one; the pipeline adds ms.load and ms.log).
STATS_SCHEMA = json_object({
    "frame": json_field("integer", "index of the frame in the run (0 = the first frame selected)"),
    "status": json_field("string", '"ok" (a tracked frame, the map\'s first one included), "relocalised", '
                                   '"lost: <reason>" (not fused; its pose is the motion model\'s) or "skipped: '
                                   '<reason>" (before the map started: no depth enough to start it on; no pose)'),
    "tracking": json_field("string", 'the tracker\'s own word: "init" for the map\'s first frame, else as status'),
    "surfels": json_field("integer", "surfels in the map after this frame"),
    "ms": json_object({
        "maps": json_field("number", "the frame's depth, vertex and normal pyramids, milliseconds"),
        "track": json_field("number", "rendering the model and ICP (with feature relocalisation when it runs), "
                                      "milliseconds; every frame but the first"),
        "fuse": json_field("number", "fusing the frame into the map, milliseconds; fused frames only"),
    }, required=("maps",), description="time per stage, milliseconds"),
    "icp": json_object({
        "iterations": json_field("array", "iterations run at each pyramid level, index = level (0 = finest)",
                                 items={"type": "integer", "minimum": 0}),
        "residual_rms_m": json_field(["number", "null"], "RMS point-to-plane residual of the inliers, metres "
                                                         "(null: no inliers)"),
        "inliers": json_field("integer", "correspondences of the last iteration", minimum=0),
        "inlier_ratio": json_field("number", "inliers / valid pixels of the rendered model, 0 to 1",
                                   minimum=0, maximum=1),
        "condition": json_field(["number", "null"], "condition number of AᵀA, dimensionless (null: not "
                                                    "computed or infinite)"),
        "update_norm": json_field(["number", "null"], "norm of the last se(3) update (radians and metres "
                                                      "together), the convergence test's value"),
    }, required=("iterations", "residual_rms_m", "inliers", "inlier_ratio", "condition", "update_norm"),
        description="the frame's ICP against the model, of its last iteration; every frame but the first"),
    "merged": json_field("integer", "pixels averaged into an existing surfel; fused frames only", minimum=0),
    "added": json_field("integer", "new surfels; fused frames only", minimum=0),
    "covered": json_field("integer", "valid pixels neither merged nor added, because a neighbour's merged surfel "
                                     "covers them; fused frames only", minimum=0),
    "removed": json_field("integer", "surfels removed (unstable, or in front of the measured surface); fused "
                                     "frames only", minimum=0),
}, required=("frame", "status", "tracking", "surfels", "ms"))


def frame_stats(result: FrameResult, surfels: int) -> dict:
    """The /slam/stats message of one frame (``STATS_SCHEMA``)."""
    stats = {"frame": result.index, "status": "ok" if result.status in ("ok", "init") else result.status,
             "tracking": result.status, "surfels": surfels, "ms": {k: round(v, 3) for k, v in result.ms.items()}}
    icp = result.icp
    if icp is not None:
        per_level = [0] * (max((it.level for it in icp.iterations), default=-1) + 1)
        for it in icp.iterations:
            per_level[it.level] += 1
        stats["icp"] = {
            "iterations": per_level,
            "residual_rms_m": icp.residual_rms,
            "inliers": icp.inliers,
            "inlier_ratio": icp.inlier_ratio,
            "condition": icp.condition,
            "update_norm": icp.update_norm,
        }
    if result.fusion is not None:
        stats.update({"merged": result.fusion.merged, "added": result.fusion.added,
                      "covered": result.fusion.covered, "removed": result.fusion.removed})
    return stats


class SLAMStep:
    """Frame-to-model tracking and mapping of each frame; writes map.ply and the map's PNG views."""

    name = "slam"
    stats_channel = "/slam/stats"
    stats_schema = STATS_SCHEMA
    stages = ("maps", "track", "fuse")
    estimates_poses = True

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config
        self.dataset_name = dataset.name
        self.slam = DenseSLAM(config, dataset.intrinsics)

    @property
    def warmup_frames(self) -> int:
        """The map's first frame compiles the maps and fusion kernels, the next one rendering and ICP; frames
        skipped before the map started come first."""
        return len(self.slam.skipped) + 2

    def register_frame(self, frame: Frame) -> FrameResult:
        return self.slam.register_frame(frame)

    def stats(self, result: FrameResult) -> dict:
        return frame_stats(result, self.slam.surfels)

    def map_points(self, max_points: int):
        return self.slam.mapper.sample_points(max_points) if self.slam.surfels else None

    def plot_title(self, run) -> str:
        return f"ti-fusion slam: {self.dataset_name}"

    def outputs(self, run) -> dict:
        slam = self.slam
        slam.mapper.export_ply(run.out.file("map.ply"))
        first = next((r for r in run.results if r.pose is not None), None)
        if first is not None:
            save_views(slam.mapper, view_pose(first.pose, self.config.fusion.view_back), run.out.path)
        else:
            log.warning(f"no frame had depth enough to start the map ({slam.skipped[0][1]} in the first): the map "
                        "is empty, and there are no views of it")
        lost = [r for r in run.results if r.lost]
        return {
            "surfels": slam.surfels,
            "resolution": slam.resolution(),
            "tracking_failures": len(lost),
            "failed_frames": [{"frame": r.index, "reason": r.status} for r in lost][:50],
            "relocalised": sum(r.status == "relocalised" for r in run.results),
            "map_started_at": None if first is None else first.index,
            "skipped_frames": [{"frame": f, "reason": reason} for f, reason in slam.skipped][:50],
        }
