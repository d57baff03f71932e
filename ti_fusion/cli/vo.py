"""``ti-fusion vo DATA``: feature-based RGB-D odometry (ORB + PnP RANSAC), the classic tutorial's tracker.

Each frame is matched against the keyframe (the last accepted frame); frames failing a rejection rule
(too few good matches, too few RANSAC inliers, too large a motion) are logged with the reason and
skipped. The first accepted frame takes its ground-truth pose when the dataset has one (so the
trajectory is directly comparable with ground truth), else the identity.

Writes to ``--out``:
    trajectory.tum   camera-to-world poses of the ACCEPTED frames (rejected frames have no pose)
    cloud.ply        the accepted frames' depth (every ``vo.cloud_stride``-th pixel) in world coordinates,
                     joined on a ``vo.voxel_size`` voxel grid
    matches.png      for ``--pair I J``: all matches / good matches / RANSAC inliers, stacked vertically
    log.mcap         /tf, /camera/pose, /gt/pose (as the dense SLAM), /vo/stats per frame, /map/points
    trajectory.png   top view and x, y, z over time, against ground truth when there is one
    summary.json     frames, accepted, rejected by reason, ATE/RPE (with ground truth), fps
On an exception or Ctrl-C the trajectory of the frames done so far and the log are still written.
fps counts tracking, cloud joining and logging, not image loading (reported as ``load`` in
``ms_per_stage``), as the dense SLAM's does.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from ti_fusion.io.datasets import open_dataset
from ti_fusion.errors import InputError
from ti_fusion.tracking.features import REASONS, FeatureOdometry, VOResult, draw_match_panels
from ti_fusion.io.outputs import progress
from ti_fusion.mapping.pointcloud import VoxelCloud, backproject
from ti_fusion.slam.timing import StageTimer

HELP = "feature-based RGB-D odometry (ORB + PnP RANSAC): trajectory, joined cloud, match image, log"
USES_DATASET = True
USES_TAICHI = False

STATS_CHANNEL = "/vo/stats"


def add_arguments(parser) -> None:
    parser.add_argument("--pair", nargs=2, type=int, metavar=("I", "J"), default=None,
                        help="dataset frame numbers of the pair drawn in matches.png (default: the first two frames)")


def run(ctx) -> dict:
    cfg = ctx.config
    dataset = open_dataset(cfg.dataset, cfg.synth)
    if len(dataset) == 0:
        raise InputError(dataset.root, "no frames selected (check --start/--stop/--frames)")
    tracker = FeatureOdometry(cfg.vo)
    cloud = VoxelCloud(cfg.vo.voxel_size)
    timer = StageTimer()
    stamps, poses, gt_pairs = [], [], []  # gt_pairs: (estimate, ground truth) of accepted frames with GT
    rejected = {reason: 0 for reason in REASONS}
    rejected_frames: list[tuple[int, str]] = []
    done, t_last = 0, None
    log = _open_log(ctx, dataset)
    try:
        frames = progress(dataset, len(dataset), "vo", cfg.log.progress and not ctx.quiet)
        t_load = time.perf_counter()
        for frame in frames:
            timer.add("load", (time.perf_counter() - t_load) * 1e3)
            if frame.color is None:
                raise InputError(dataset.root, f"frame {frame.index} has no colour image: feature odometry needs colour")
            result = tracker.register_frame(frame)
            timer.add("track", result.ms)
            if result.accepted:
                stamps.append(frame.timestamp)
                poses.append(result.pose)
                if frame.gt_pose is not None:
                    gt_pairs.append((result.pose, frame.gt_pose))
                with timer.stage("cloud"):
                    xyz, rgb = backproject(frame.depth, frame.intrinsics, _color_at_depth(frame), cfg.vo.cloud_stride)
                    cloud.add(xyz, rgb, result.pose)
            else:
                rejected[result.reason] = rejected.get(result.reason, 0) + 1
                rejected_frames.append((frame.index, result.reason))
            with timer.stage("log"):
                log_frame(log, frame, result, cloud if _cloud_due(done, cfg.log.map_every) else None,
                          cfg.log.map_max_points)
            done, t_last = done + 1, frame.timestamp
            t_load = time.perf_counter()
    finally:
        # Whatever happened, keep what was done: the trajectory so far and a finalised log.
        if poses:
            from ti_fusion.io.trajectory import write_tum

            write_tum(ctx.out.file("trajectory.tum"), stamps, np.array(poses))
        if log is not None:
            if len(cloud):
                xyz, rgb = cloud.points()
                log.log_points(t_last, xyz, rgb, max_points=cfg.log.map_max_points)
            log.close()

    with timer.stage("export"):
        xyz, rgb = cloud.points()
        _write_cloud(ctx.out.file("cloud.ply"), xyz, rgb)
        pair = _write_matches(ctx, dataset)
        metrics = _evaluate(gt_pairs)
        _plot(ctx, stamps, poses, gt_pairs, metrics, len(dataset))

    ms = timer.summary()
    processing_s = sum(sum(timer.samples.get(s, [])) for s in ("track", "cloud", "log")) / 1e3
    accepted = len(poses)
    summary = {
        "frames": done,
        "wall_s": processing_s,
        "ms_per_stage": ms,
        "dataset": dataset.describe(),
        "accepted": accepted,
        "rejected": {k: v for k, v in rejected.items() if v},
        "rejected_total": done - accepted,
        "rejected_frames": rejected_frames[:200],
        "first_pose": tracker.anchor,  # ground truth (of the first accepted frame) | identity
        "tracking_fps": round(done / (sum(timer.samples["track"]) / 1e3), 3) if timer.samples.get("track") else None,
        "cloud_points": int(len(xyz)),
        "pair": pair,
    }
    if metrics:
        summary.update({k: metrics[k] for k in ("ate_rmse_m", "ate_mean_m", "ate_max_m", "rpe_trans_m",
                                                "rpe_rot_deg", "pairs")})
    _print_summary(summary)
    return summary


# --------------------------------------------------------------------------------------------------
# Logging: the one place that knows the log's channels
# --------------------------------------------------------------------------------------------------
def _open_log(ctx, dataset):
    from ti_fusion.io.mcap_log import RunLogger, software_versions

    metadata = {"config": ctx.config.to_dict(), "dataset": dataset.describe(), "versions": software_versions(),
                "backend": {"arch": "none (OpenCV on the CPU)"}}
    return RunLogger(ctx.out.file("log.mcap"), metadata)


def log_frame(log, frame, result: VOResult, cloud: VoxelCloud | None = None, max_points: int = 200_000) -> None:
    """One frame's messages: pose (accepted frames) with ground truth, /vo/stats, and the cloud when given."""
    if log is None:
        return
    t = frame.timestamp
    if result.accepted:
        log.log_pose(t, result.pose, frame.gt_pose)
    log.log_stats(t, result.stats(), channel=STATS_CHANNEL)
    if cloud is not None and len(cloud):
        xyz, rgb = cloud.points()
        log.log_points(t, xyz, rgb, max_points=max_points)


def _cloud_due(done: int, every: int) -> bool:
    return every > 0 and done > 0 and done % every == 0


# --------------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------------
def _color_at_depth(frame):
    """The colour image if it has the depth image's size (for the cloud's colours), else None."""
    if frame.color is not None and frame.color.shape[:2] == frame.depth.shape:
        return frame.color
    return None


def _write_cloud(path, xyz, rgb) -> None:
    from ti_fusion.io.ply import write_ply

    write_ply(path, xyz, None, rgb)


def _write_matches(ctx, dataset) -> dict:
    """matches.png for --pair I J (dataset frame numbers), default the first two selected frames."""
    if ctx.args.pair is not None:
        i, j = ctx.args.pair
        try:
            if min(i, j) < 0:
                raise IndexError
            a, b = dataset.frame_by_raw_index(i), dataset.frame_by_raw_index(j)
        except IndexError:
            raise InputError(dataset.root, f"--pair {i} {j}: no such frame in the sequence") from None
    elif len(dataset) >= 2:
        a, b = dataset[0], dataset[1]
    else:
        return {}
    image, est = draw_match_panels(a, b, ctx.config.vo)
    cv2.imwrite(str(ctx.out.file("matches.png")), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return {"frames": [int(a.index), int(b.index)], "keypoints": list(est.keypoints), "matches": est.matches,
            "good": est.good, "inliers": est.inliers, "reason": est.reason}


def _evaluate(gt_pairs) -> dict | None:
    if len(gt_pairs) < 2:
        return None
    from ti_fusion.evaluation.metrics import trajectory_metrics

    est, gt = (np.array(x) for x in zip(*gt_pairs))
    return trajectory_metrics(est, gt)


def _plot(ctx, stamps, poses, gt_pairs, metrics, n_frames) -> None:
    if len(poses) < 2:
        return
    from ti_fusion.evaluation.plots import plot_trajectory

    title = f"Feature odometry (ORB + PnP RANSAC): {len(poses)}/{n_frames} frames accepted"
    if metrics and len(gt_pairs) == len(poses):
        est, gt = (np.array(x) for x in zip(*gt_pairs))
        plot_trajectory(ctx.out.file("trajectory.png"), est, gt, stamps, title=title, metrics=metrics)
    else:
        plot_trajectory(ctx.out.file("trajectory.png"), np.array(poses), None, stamps, title=title)


def _print_summary(s: dict) -> None:
    rej = ", ".join(f"{k} {v}" for k, v in s["rejected"].items()) or "none"
    line = f"vo: {s['accepted']}/{s['frames']} frames accepted (rejected: {rej})"
    if "ate_rmse_m" in s:
        line += f"  ATE {s['ate_rmse_m']:.4f} m  RPE {s['rpe_trans_m']:.4f} m"
    line += f"  tracking {s['tracking_fps']} fps"
    print(line, flush=True)
