"""``ti-fusion vo DATA``: feature-based RGB-D odometry (ORB + PnP RANSAC), the classic tutorial's tracker.

Each frame is matched against the keyframe (the last accepted frame); frames failing a rejection rule
(too few good matches, too few RANSAC inliers, too large a motion) are logged with the reason and
skipped. The first accepted frame takes its ground-truth pose when the dataset has one (so the
trajectory is directly comparable with ground truth), else the identity. The pipeline runs ``VOStep``.

Writes to ``--out``:
    trajectory.tum   camera-to-world poses of the ACCEPTED frames (rejected frames have no pose)
    cloud.ply        the accepted frames' depth (every ``vo.cloud_stride``-th pixel) in world coordinates,
                     joined on a ``vo.voxel_size`` voxel grid
    matches.png      for ``--pair I J``: all matches / good matches / RANSAC inliers, stacked vertically
    log.mcap         /tf, /camera/pose, /gt/pose, /camera/depth (as the dense SLAM), /vo/stats per frame,
                     /map/points (the joined cloud)
    trajectory.png   top view and x, y, z over time, against ground truth when there is one
    summary.json     frames, accepted, rejected by reason, ATE/RPE (with ground truth), fps
On an exception or Ctrl-C the trajectory of the frames done so far and the log are still written.
fps_processing counts tracking, cloud joining and logging, not image loading (reported as ``load`` in
``ms_per_stage``), as the dense SLAM's does.
"""

from __future__ import annotations

import logging

import cv2

from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.outputs import write_image
from ti_fusion.sinks import add_switches, chosen
from ti_fusion.slam.pipeline import Pipeline
from ti_fusion.slam.vo_step import VOStep
from ti_fusion.tracking.features import draw_match_panels

log = logging.getLogger(__name__)

HELP = "feature-based RGB-D odometry (ORB + PnP RANSAC): trajectory, joined cloud, match image, log"
USES_DATASET = True
USES_TAICHI = False


def add_arguments(parser) -> None:
    parser.add_argument("--pair", nargs=2, type=int, metavar=("I", "J"), default=None,
                        help="dataset frame numbers of the pair drawn in matches.png (default: the first two frames)")
    add_switches(parser, "vo")  # the optional outputs' own switches (ti_fusion.sinks)


def run(ctx) -> dict:
    cfg = ctx.config
    dataset = open_dataset(cfg.dataset, cfg.synth)
    summary = Pipeline(dataset, cfg, ctx.out, VOStep(cfg, dataset), ctx.backend, show_progress=not ctx.quiet,
                       outputs=chosen(ctx.args, "vo")).run()
    summary["pair"] = _write_matches(ctx, dataset)
    _print_summary(summary)
    return summary


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
    write_image(ctx.out.file("matches.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return {"frames": [int(a.index), int(b.index)], "keypoints": list(est.keypoints), "matches": est.matches,
            "good": est.good, "inliers": est.inliers, "reason": est.reason}


def _print_summary(s: dict) -> None:
    from ti_fusion.cli.slam import _tracked_only

    rej = ", ".join(f"{k} {v}" for k, v in s["rejected"].items()) or "none"
    line = f"vo: {s['accepted']}/{s['frames']} frames accepted (rejected: {rej})"
    if "ate_rmse_m" in s:
        line += f"  ATE {s['ate_rmse_m']:.4f} m over all {s['ate_frames']} frames"
        line += _tracked_only(s, 1, "m") + f"  RPE {s['rpe_trans_m']:.4f} m"
    line += f"  tracking {s['tracking_fps']} fps" if s["tracking_fps"] is not None else ""
    print(line, flush=True)
    if s.get("gt_note"):
        log.warning(s["gt_note"])
