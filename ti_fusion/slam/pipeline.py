"""The SLAM run: owns the loop over a dataset, the timing, the MCAP log and the results on disk.

    results = SLAMPipeline(dataset, config, run_dir, backend).run()

Whatever happens (normal end, bad input in frame 300, Ctrl-C), the frames done so far leave a
finalised ``log.mcap`` and a ``trajectory.tum``.
"""

from __future__ import annotations

import time

import numpy as np

from ti_fusion import __version__
from ti_fusion.backend import BackendInfo
from ti_fusion.config import Config
from ti_fusion.io.datasets.base import Dataset
from ti_fusion.evaluation.metrics import evaluate
from ti_fusion.io.mcap_log import RunLogger, software_versions
from ti_fusion.io.outputs import RunDir, progress
from ti_fusion.evaluation.plots import plot_trajectory
from ti_fusion.mapping.views import save_views, view_pose
from ti_fusion.slam.dense import DenseSLAM, FrameResult
from ti_fusion.slam.timing import StageTimer
from ti_fusion.io.trajectory import write_tum

# Stages counted in the frame rate: loading the images is I/O and is reported on its own.
PROCESSING_STAGES = ("maps", "track", "fuse", "log")
# The first two frames compile the kernels (frame 0: maps and fusion; frame 1: rendering and ICP).
WARMUP_FRAMES = 2


def frame_stats(result: FrameResult, surfels: int, ms: dict[str, float]) -> dict:
    """The /slam/stats message of one frame (field names as docs/LOGS.md lists them)."""
    stats = {"frame": result.index, "status": "ok" if result.status in ("ok", "init") else result.status,
             "tracking": result.status, "surfels": surfels, "ms": {k: round(v, 3) for k, v in ms.items()}}
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


class SLAMPipeline:
    """Runs DenseSLAM over a dataset and writes every output of the run into ``run_dir``."""

    def __init__(self, dataset: Dataset, config: Config, run_dir: RunDir, backend: BackendInfo,
                 show_progress: bool = True):
        self.dataset = dataset
        self.config = config
        self.out = run_dir
        self.backend = backend
        self.show_progress = show_progress and config.log.progress
        self.timer = StageTimer()
        self.results: list[FrameResult] = []
        self.gt: list[np.ndarray | None] = []

    def _metadata(self) -> dict:
        return {
            "config": self.config.to_dict(),
            "dataset": self.dataset.describe(),
            "backend": {"arch": self.backend.arch, "requested": self.backend.requested,
                        "reason": self.backend.reason},
            "versions": {**software_versions(), "ti-fusion": __version__},
        }

    def run(self) -> dict:
        slam = DenseSLAM(self.config, self.dataset.intrinsics)
        t_start = time.perf_counter()
        with RunLogger(self.out.file("log.mcap"), self._metadata()) as log:
            try:
                self._loop(slam, log)
            finally:
                self._write_trajectory()
                self._log_map(slam, log, self.results[-1].timestamp if self.results else 0.0)
        wall = time.perf_counter() - t_start
        return self._finish(slam, wall)

    def _loop(self, slam: DenseSLAM, log: RunLogger) -> None:
        cfg = self.config.log
        n = len(self.dataset)
        for i in progress(range(n), n, "slam", self.show_progress):
            with self.timer.stage("load"):
                frame = self.dataset[i]
            result = slam.register_frame(frame)
            t0 = time.perf_counter()
            log.log_pose(frame.timestamp, result.pose, frame.gt_pose)
            if i % cfg.depth_every == 0:
                log.log_depth(frame.timestamp, frame.depth)
            if i > 0 and i % cfg.map_every == 0:
                self._log_map(slam, log, frame.timestamp)
            result.ms["log"] = (time.perf_counter() - t0) * 1e3
            for name, value in result.ms.items():
                self.timer.add(name, value)
            result.ms["load"] = self.timer.last["load"]
            log.log_stats(frame.timestamp, frame_stats(result, slam.surfels, result.ms))
            self.results.append(result)
            self.gt.append(frame.gt_pose)

    def _log_map(self, slam: DenseSLAM, log: RunLogger, t: float) -> None:
        if slam.surfels == 0:
            return
        xyz, rgb = slam.mapper.sample_points(self.config.log.map_max_points)
        log.log_points(t, xyz, rgb, max_points=self.config.log.map_max_points)

    def _write_trajectory(self) -> None:
        if self.results:
            write_tum(self.out.file("trajectory.tum"), [r.timestamp for r in self.results],
                      np.stack([r.pose for r in self.results]))

    # -- after the loop -------------------------------------------------------------------------
    def _frame_rate(self) -> tuple[float | None, float]:
        """(frames per second of processing after warm-up, ms of the warm-up frames)."""
        per_frame = np.array([sum(r.ms.get(name, 0.0) for name in PROCESSING_STAGES) for r in self.results])
        warm = per_frame[:WARMUP_FRAMES].sum()
        steady = per_frame[WARMUP_FRAMES:]
        fps = round(1e3 * len(steady) / steady.sum(), 2) if len(steady) and steady.sum() > 0 else None
        return fps, round(float(warm), 1)

    def _finish(self, slam: DenseSLAM, wall: float) -> dict:
        n = len(self.results)
        fps, warmup_ms = self._frame_rate()
        lost = [r for r in self.results if not r.tracked]
        summary = {
            "frames": n,
            "wall_s": wall,
            "ms_per_stage": self.timer.summary(skip_first=WARMUP_FRAMES),
            "fps_processing": fps,
            "warmup_ms": warmup_ms,
            "dataset": self.dataset.describe(),
            "surfels": slam.surfels,
            "resolution": slam.resolution(),
            "tracking_failures": len(lost),
            "failed_frames": [{"frame": r.index, "reason": r.status} for r in lost][:50],
            "relocalised": sum(r.status == "relocalised" for r in self.results),
        }
        poses = np.stack([r.pose for r in self.results])
        stamps = [r.timestamp for r in self.results]
        has_gt = all(g is not None for g in self.gt)
        metrics = None
        if has_gt and n >= 2:
            gt = np.stack(self.gt)
            metrics = evaluate(stamps, poses, stamps, gt)
            summary.update({k: metrics[k] for k in ("ate_rmse_m", "ate_max_m", "rpe_trans_m", "rpe_rot_deg")})
            path_length = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
            summary["path_length_m"] = round(path_length, 3)
            summary["ate_percent_of_path"] = round(100 * metrics["ate_rmse_m"] / max(path_length, 1e-9), 3)
        plot_trajectory(self.out.file("trajectory.png"), poses, np.stack(self.gt) if has_gt else None,
                        timestamps=stamps, title=f"ti-fusion slam: {self.dataset.name}", metrics=metrics)
        slam.mapper.export_ply(self.out.file("map.ply"))
        save_views(slam.mapper, view_pose(self.results[0].pose, self.config.fusion.view_back), self.out.path)
        return summary
