"""``ti-fusion fuse``'s step in the pipeline: point-based fusion of each frame at its ground-truth pose.

The classic assignment's fusion experiment: integrate every frame at its ground-truth pose, then report
the surfel count against the naive count (every valid input point concatenated) and their ratio. The map
sink writes ``map.ply`` (positions, normals, colours), and the views sink, unless told not to,
``map_color.png`` and ``map_normals.png`` (the map from the first camera pulled back ``fusion.view_back`` metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.mcap_log import json_field, json_object
from ti_fusion.kernels.pyramid import FramePyramid
from ti_fusion.mapping.mapper import FusionStats, SurfelMapper
from ti_fusion.timing import StageTimer


_MS = "milliseconds, a part of fuse"

# The /fuse/stats message, every field (the pipeline adds ms.load and ms.log).
STATS_SCHEMA = json_object({
    "frame": json_field("integer", "index of the frame in the run (0 = the first frame selected)"),
    "status": json_field("string", '"ok": every frame is fused, at its ground-truth pose'),
    "surfels": json_field("integer", "surfels in the map after this frame", minimum=0),
    "merged": json_field("integer", "pixels averaged into an existing surfel", minimum=0),
    "added": json_field("integer", "new surfels", minimum=0),
    "covered": json_field("integer", "valid pixels neither merged nor added, because a neighbour's merged surfel "
                                     "covers them", minimum=0),
    "removed": json_field("integer", "surfels removed (unstable, or in front of the measured surface)",
                          minimum=0),
    "ms": json_object({
        "pyramid": json_field("number", "the frame's depth, vertex and normal pyramids, milliseconds"),
        "project": json_field("number", "projecting the map into the frame and associating, " + _MS),
        "merge": json_field("number", "averaging associated pixels into their surfels, " + _MS),
        "add": json_field("number", "adding unassociated pixels as new surfels, " + _MS),
        "remove": json_field("number", "removing unstable and free-space surfels, " + _MS),
        "fuse": json_field("number", "fusing the frame into the map (project to remove), milliseconds"),
    }, required=("pyramid", "project", "merge", "add", "remove", "fuse"),
        description="time per stage, milliseconds"),
}, required=("frame", "status", "surfels", "merged", "added", "covered", "removed", "ms"))


@dataclass
class FuseFrame:
    """What the step did with one frame."""

    index: int
    timestamp: float
    pose: np.ndarray  # the ground-truth camera-to-world pose it was fused at
    fusion: FusionStats
    ms: dict[str, float] = field(default_factory=dict)
    loop = None  # no loop closure


class FuseStep:
    """Fuses each frame at its ground-truth pose into a surfel map (``mapper``, which the map and views sinks write)."""

    name = "fuse"
    stats_channel = "/fuse/stats"
    stats_schema = STATS_SCHEMA
    stages = ("pyramid", "fuse")  # "fuse" is the sum of the mapper's stages (project ... remove)
    warmup_frames = 1  # the first frame compiles the kernels
    estimates_poses = False

    def __init__(self, config: Config, dataset: Dataset):
        if not dataset.has_ground_truth:
            raise InputError(dataset.root, "this sequence has no ground-truth poses, which fuse needs "
                                           "(ti-fusion slam estimates poses instead)")
        self.config = config
        self.root = dataset.root
        K = self.intrinsics = dataset.intrinsics
        # The frame maps that the SLAM loop fuses: averaged down to the map's level on input (by default),
        # the same smoothed depth and normals.
        input_level = config.frame_input_level(K.width)
        self.pyramid = FramePyramid.lent_to(self, config.pyramid, K.height, K.width,
                                            config.fusion.map_level(K.width) - input_level + 1, input_level)
        self.mapper = SurfelMapper(config.fusion)
        self.fused = 0  # frames fused so far: the time stamp the surfels store
        self.naive = 0  # valid depth pixels of every frame: the points a map without fusion would hold

    def register_frame(self, frame: Frame) -> FuseFrame:
        if frame.gt_pose is None:
            raise InputError(self.root, f"frame {frame.index} has no ground-truth pose")
        timer = StageTimer()  # this frame's stages, each synchronised with the backend
        with timer.stage("pyramid"):
            # the colour that fusion reads crosses with the depth (FramePyramid.packed_color)
            self.pyramid.compute(frame.depth, frame.intrinsics, None, frame.color,
                                 self.mapper.frame_level(self.pyramid))
        stats = self.mapper.integrate(self.pyramid, frame.color, frame.gt_pose, self.fused, timer)
        self.fused += 1
        self.naive += int((frame.depth > 0).sum())
        return FuseFrame(frame.index, frame.timestamp, frame.gt_pose, stats,
                         {**timer.last, "fuse": sum(stats.ms.values())})

    def stats(self, result: FuseFrame) -> dict:
        f = result.fusion
        return {"frame": result.index, "status": "ok", "surfels": f.surfels, "merged": f.merged, "added": f.added,
                "covered": f.covered, "removed": f.removed, "ms": {k: round(v, 3) for k, v in result.ms.items()}}

    def map_points(self, max_points: int):
        return self.mapper.sample_points(max_points) if self.mapper.count else None

    def current_poses(self) -> dict:
        return {}  # the poses are the dataset's

    def loop_edges(self) -> list:
        return []

    def plot_title(self, run) -> str:
        return f"ti-fusion fuse: {run.dataset.name}"

    def summary(self, run) -> dict:
        mapper, results = self.mapper, run.results
        surfels = mapper.count
        all_pixels = len(results) * self.intrinsics.width * self.intrinsics.height
        total = {k: sum(getattr(r.fusion, k) for r in results) for k in ("merged", "added", "removed", "covered")}
        return {
            "surfels": surfels,
            "naive_points": self.naive,
            "compression_ratio": surfels / self.naive if self.naive else None,
            "all_pixels": all_pixels,
            "compression_ratio_all_pixels": surfels / all_pixels,
            **total,
            "capacity": mapper.map.capacity,
        }
