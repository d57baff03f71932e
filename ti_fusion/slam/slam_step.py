"""``ti-fusion slam``'s step in the pipeline: dense SLAM (``DenseSLAM.register_frame``) on each frame,
the /slam/stats message, the surfel map for /map/points, and the map's files after the loop."""

from __future__ import annotations

from ti_fusion.config import Config
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.mapping.views import save_views, view_pose
from ti_fusion.slam.dense import DenseSLAM, FrameResult


def frame_stats(result: FrameResult, surfels: int) -> dict:
    """The /slam/stats message of one frame (field names as docs/LOGS.md lists them)."""
    stats = {"frame": result.index, "status": "ok" if result.status in ("ok", "init") else result.status,
             "tracking": result.status, "surfels": surfels, "ms": {k: round(v, 3) for k, v in result.ms.items()}}
    icp = result.icp
    if icp is not None:
        per_level: dict[int, int] = {}
        for it in icp.iterations:
            per_level[it.level] = per_level.get(it.level, 0) + 1
        stats.update({
            "icp_iterations": [per_level.get(level, 0) for level in sorted(per_level)],
            "residual_rms_m": icp.residual_rms,
            "inliers": icp.inliers,
            "inlier_ratio": icp.inlier_ratio,
            "condition": icp.condition,
            "update_norm": icp.update_norm,
        })
    if result.fusion is not None:
        stats.update({"merged": result.fusion.merged, "added": result.fusion.added,
                      "covered": result.fusion.covered, "removed": result.fusion.removed})
    return stats


class SLAMStep:
    """Frame-to-model tracking and mapping of each frame; writes map.ply and the map's PNG views."""

    name = "slam"
    stats_channel = "/slam/stats"
    stages = ("maps", "track", "fuse")
    warmup_frames = 2  # frame 0 compiles the maps and fusion kernels, frame 1 rendering and ICP
    estimates_poses = True

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config
        self.dataset_name = dataset.name
        self.slam = DenseSLAM(config, dataset.intrinsics)

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
        save_views(slam.mapper, view_pose(run.results[0].pose, self.config.fusion.view_back), run.out.path)
        lost = [r for r in run.results if not r.tracked]
        return {
            "surfels": slam.surfels,
            "resolution": slam.resolution(),
            "tracking_failures": len(lost),
            "failed_frames": [{"frame": r.index, "reason": r.status} for r in lost][:50],
            "relocalised": sum(r.status == "relocalised" for r in run.results),
        }
