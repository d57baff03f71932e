"""``ti-fusion vo``'s step in the pipeline: feature odometry (``FeatureOdometry.register_frame``, ORB + PnP
RANSAC) on each frame, and the accepted frames' depth joined into one coloured cloud.

A rejected frame (too few good matches, too few RANSAC inliers, too large a motion) gets no pose: it is
logged with the reason and left out of trajectory.tum. The joined cloud (``cloud``: every ``vo.cloud_stride``-th
pixel of the accepted frames' depth in world coordinates, on a ``vo.voxel_size`` voxel grid) is what the cloud
sink writes as ``cloud.ply``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.mcap_log import json_field, json_object
from ti_fusion.mapping.pointcloud import VoxelCloud, backproject
from ti_fusion.tracking.features import REASONS, FeatureOdometry, VOResult
from ti_fusion.timing import Stopwatch


# The /vo/stats message, every field (VOResult.stats() and the step's ms; the pipeline adds ms.load and ms.log).
STATS_SCHEMA = json_object({
    "frame": json_field("integer", "index of the frame in the run (0 = the first frame selected)"),
    "keyframe": json_field("integer", "the frame matched against (the last accepted frame); -1: none yet"),
    "keypoints": json_field("integer", "ORB keypoints of the frame", minimum=0),
    "matches": json_field("integer", "keypoint matches with the keyframe", minimum=0),
    "good": json_field("integer", "matches that pass the match test (vo.match: distance or ratio)", minimum=0),
    "inliers": json_field("integer", "PnP RANSAC inliers", minimum=0),
    "motion_norm": json_field("number", "size of the motion from the keyframe, ‖Δt‖ in metres + rotation "
                                        "angle in radians; -1: no motion estimated"),
    "accepted": json_field("boolean", "the frame got a pose"),
    "status": json_field("string", '"accepted" or "rejected: <reason>"'),
    "reason": json_field("string", 'why the frame was rejected ("" when accepted)'),
    "ms": json_object({
        "track": json_field("number", "ORB features, matching and PnP RANSAC, milliseconds"),
        "cloud": json_field("number", "back-projecting the frame into the joined cloud, milliseconds; accepted "
                                      "frames only"),
    }, required=("track",), description="time per stage, milliseconds"),
}, required=("frame", "keyframe", "keypoints", "matches", "good", "inliers", "motion_norm", "accepted", "status",
             "reason", "ms"))


@dataclass
class VOFrame:
    """What the step did with one frame: the odometry's result, and milliseconds per stage."""

    vo: VOResult
    ms: dict[str, float] = field(default_factory=dict)
    loop = None  # no loop closure

    @property
    def status(self) -> str:
        return self.vo.status

    @property
    def index(self) -> int:
        return self.vo.index

    @property
    def timestamp(self) -> float:
        return self.vo.timestamp

    @property
    def pose(self) -> np.ndarray | None:
        return self.vo.pose  # None when rejected


class VOStep:
    """Frame-to-keyframe feature odometry and the joined cloud of the accepted frames."""

    name = "vo"
    stats_channel = "/vo/stats"
    stats_schema = STATS_SCHEMA
    stages = ("track", "cloud")
    warmup_frames = 0  # OpenCV: nothing to compile
    estimates_poses = True
    mapper = None  # no surfel map: the joined cloud instead

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config.vo
        self.root = dataset.root
        self.odometry = FeatureOdometry(config.vo)
        self.cloud = VoxelCloud(config.vo.voxel_size)
        self.rejected = {reason: 0 for reason in REASONS}
        self.rejected_frames: list[tuple[int, str]] = []

    def register_frame(self, frame: Frame) -> VOFrame:
        if frame.color is None:
            raise InputError(self.root, f"frame {frame.index} has no colour image: feature odometry needs colour")
        result = VOFrame(self.odometry.register_frame(frame))
        result.ms["track"] = result.vo.ms
        if result.vo.accepted:
            with Stopwatch(result.ms, "cloud"):
                xyz, rgb = backproject(frame.depth, frame.intrinsics, _color_at_depth(frame), self.config.cloud_stride)
                self.cloud.add(xyz, rgb, result.pose)
        else:
            self.rejected[result.vo.reason] = self.rejected.get(result.vo.reason, 0) + 1
            self.rejected_frames.append((frame.index, result.vo.reason))
        return result

    def stats(self, result: VOFrame) -> dict:
        return {**result.vo.stats(), "ms": {k: round(v, 3) for k, v in result.ms.items()}}

    def map_points(self, max_points: int):
        return self.cloud.points() if len(self.cloud) else None

    def current_poses(self) -> dict:
        return {}  # a pose does not change after its frame

    def loop_edges(self) -> list:
        return []

    def plot_title(self, run) -> str:
        accepted = sum(r.pose is not None for r in run.results)
        return f"Feature odometry (ORB + PnP RANSAC): {accepted}/{len(run.results)} frames accepted"

    def summary(self, run) -> dict:
        done = len(run.results)
        accepted = sum(r.pose is not None for r in run.results)
        track_s = sum(run.timer.samples.get("track", [])) / 1e3
        return {
            "accepted": accepted,
            "rejected": {k: v for k, v in self.rejected.items() if v},
            "rejected_total": done - accepted,
            "rejected_frames": self.rejected_frames[:200],
            "first_pose": self.odometry.first_pose_source,  # ground truth (of the first accepted frame) | identity
            "tracking_fps": round(done / track_s, 3) if track_s > 0 else None,
        }


def _color_at_depth(frame: Frame):
    """The colour image if it has the depth image's size (for the cloud's colours), else None."""
    if frame.color is not None and frame.color.shape[:2] == frame.depth.shape:
        return frame.color
    return None
