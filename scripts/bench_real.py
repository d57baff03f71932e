#!/usr/bin/env python3
"""Accuracy on real cameras: the defaults of ``ti-fusion slam`` against Open3D on every real sequence with
ground truth, and pairwise alignment of consecutive frames, one table per sequence, one run.

    python scripts/bench_real.py [DATA ...] [--frames N] [--open3d-runs 3] [--pairs 60] [--arch cpu]
                                 [--no-slam] [--set SECTION.KEY=VALUE ...] [--json FILE]

DATA defaults to every folder under ../shared/data that opens as a dataset with ground truth (today the TUM
cabinet keyframes and redkitchen); a folder without ground truth is named and left out. Per sequence:

- SLAM: ``ti-fusion slam DATA`` with the defaults (and ``--set``), in a child process, and Open3D's tensor
  SLAM (``bench_slam.py``'s settings: voxel 0.0059 m, depth max 3 m, depth-only point-to-plane) ``--open3d-runs``
  times, each in a child of its own (it is not deterministic: the row "median" is the run of median ATE).
  Columns: ATE (RMSE after alignment, every frame), failures, fps of processing, and the per-step error: the
  translation error of each consecutive frame pair's relative pose against the ground truth's (RPE over
  one frame), its 50th and 90th percentiles and maximum in mm, and its median rotation error.
- Pairwise: each consecutive pair i+1 → i aligned from the identity, as ``ti-fusion icp DATA --source i+1
  --target i`` does but at the resolution ``ti-fusion slam`` tracks at: ours depth only (ICP's defaults),
  ours with the photometric term (``icp.color_weight``, where colour is registered to depth), and Open3D's
  ``rgbd_odometry_multi_scale`` point-to-plane (20/10/5 iterations coarse to fine, depth max 3 m, at the
  input resolution); translation error against the ground truth in mm (``pose_error``, as ``ti-fusion icp``
  prints it). At most ``--pairs`` pairs, evenly spread, per sequence.

Open3D (``pip install open3d-cpu``, the ``bench`` extra; Debian's libusb-1.0-0) is optional: without it its
rows say why. Each system runs in a child process of its own, one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _config(data: str, frames: int | None, overrides: list[str]):
    from ti_fusion.config import load_config

    cfg = load_config(overrides=list(overrides))
    cfg.dataset.path = data
    cfg.dataset.stop = frames
    cfg.log.progress = False
    return cfg


def real_sequences(root: Path) -> tuple[list[str], list[str]]:
    """(folders under ``root`` that open as datasets with ground truth, lines naming the others and why)."""
    from ti_fusion.errors import TiFusionError
    from ti_fusion.io.datasets import open_dataset

    found, left_out = [], []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        try:
            cfg = _config(str(folder), None, [])
            dataset = open_dataset(cfg.dataset, cfg.synth)
        except (TiFusionError, OSError, ValueError) as e:
            left_out.append(f"{folder.name}: not a dataset this benchmark reads ({e})")
            continue
        if not getattr(dataset, "has_ground_truth", False):
            left_out.append(f"{folder.name}: no ground truth")
            continue
        found.append(str(folder))
    return found, left_out


def step_errors(poses, gts) -> dict:
    """Per consecutive pair: translation error (mm) and rotation error (deg) of the relative pose against the
    ground truth's (RPE over one frame), as percentiles."""
    from ti_fusion.evaluation.metrics import rpe_errors

    trans, rot = rpe_errors(np.asarray(poses), np.asarray(gts), delta=1, all_pairs=True)
    trans = trans * 1e3
    return {"step_p50_mm": float(np.percentile(trans, 50)), "step_p90_mm": float(np.percentile(trans, 90)),
            "step_max_mm": float(trans.max()), "step_rot_p50_deg": float(np.median(rot)),
            "steps_mm": [round(float(x), 2) for x in trans]}


# -- children --------------------------------------------------------------------------------------------
def worker_slam(args) -> dict:
    """``ti-fusion slam`` as a user runs it, and its trajectory against the ground truth."""
    import bench_slam  # a sibling: scripts/ is on the path of a script run as a file
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.trajectory import associate

    run = bench_slam.slam_run(args, [])
    if isinstance(run, str):
        return {"system": "ti-fusion", "error": run}
    s, (stamps, poses) = run
    cfg = _config(args.data, args.frames, args.set)
    gt_stamps, gt_poses = open_dataset(cfg.dataset, cfg.synth).ground_truth()
    i, j = associate(stamps, gt_stamps)
    row = {"system": "ti-fusion slam (defaults)" if not args.set else "ti-fusion slam (" + ", ".join(args.set) + ")",
           "frames": s["frames"], "ate_m": s.get("ate_rmse_m"), "failures": s["tracking_failures"],
           "fps": s.get("fps_processing")}
    row.update(step_errors(poses[i], gt_poses[j]))
    return row


def worker_open3d(args) -> dict:
    import bench_slam  # a sibling: scripts/ is on the path of a script run as a file

    slam_args = argparse.Namespace(data=args.data, downsample=1, frames=args.frames)
    out = bench_slam.open3d_slam(slam_args)
    if isinstance(out, str):
        return {"system": "Open3D tensor SLAM", "error": out}
    poses, gts, times, _, _, version = out
    from ti_fusion.evaluation.metrics import trajectory_metrics

    keep = [k for k, g in enumerate(gts) if g is not None]
    poses, gts = np.stack([poses[k] for k in keep]), np.stack([gts[k] for k in keep])
    steady = np.asarray(times[2:])
    row = {"system": f"Open3D {version} tensor SLAM", "frames": len(times),
           "ate_m": trajectory_metrics(poses, gts)["ate_rmse_m"], "failures": 0,
           "fps": len(steady) / steady.sum() if len(steady) else None}
    row.update(step_errors(poses, gts))
    return row


def pair_indices(n_frames: int, most: int) -> list[int]:
    """The first frames i of the consecutive pairs (i + 1 → i) measured: all, or ``most`` evenly spread."""
    n = n_frames - 1
    if n <= most:
        return list(range(n))
    return sorted({int(round(k)) for k in np.linspace(0, n - 1, most)})


def worker_pairs(args) -> dict:
    from ti_fusion.backend import init_backend
    from ti_fusion.geometry import invert, pose_error
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.kernels.pyramid import FramePyramid, grey_image
    from ti_fusion.tracking.icp import ICP

    init_backend(args.arch)
    cfg = _config(args.data, args.frames, args.set)
    dataset = open_dataset(cfg.dataset, cfg.synth)
    K = dataset.intrinsics
    levels = len(cfg.icp.iterations)
    # two pyramids, filled anew for each pair: each pyramid's fields are its kernels' template arguments
    maps = [FramePyramid(cfg.pyramid, K.height, K.width, levels, input_level=cfg.frame_input_level(K.width))
            for _ in range(2)]
    icp = ICP(cfg.icp)
    try:
        import open3d as o3d
        import open3d.core as o3c

        odometry = o3d.t.pipelines.odometry
        criteria = [odometry.OdometryConvergenceCriteria(n) for n in (20, 10, 5)]
        intrinsic = o3c.Tensor(K.K, o3c.Dtype.Float64)
        open3d_note = f"Open3D {o3d.__version__}"
    except ImportError as e:
        o3d, open3d_note = None, f"Open3D not available ({e})"

    def rgbd(frame):
        depth = o3d.t.geometry.Image(o3c.Tensor(np.round(frame.depth * 1000.0).astype(np.uint16)))
        color = frame.color if frame.color is not None else np.zeros((K.height, K.width, 3), np.uint8)
        return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color))), depth)

    rows = []
    for i in pair_indices(len(dataset), args.pairs):
        target, source = dataset[i], dataset[i + 1]
        if source.gt_pose is None or target.gt_pose is None:
            continue
        reference = invert(target.gt_pose) @ source.gt_pose
        color = cfg.icp.color_weight > 0 and source.color is not None and source.color_registered
        for pyramid, frame in zip(maps, (source, target)):
            pyramid.compute(frame.depth, frame.intrinsics, grey_image(frame.color) if color else None)
        step_deg, step_m = pose_error(np.eye(4), reference)
        row = {"source": source.index, "target": target.index, "step_mm": step_m * 1e3, "step_deg": step_deg}
        depth_only = icp.align(maps[0], maps[1], None)
        row["ours_depth_mm"] = pose_error(depth_only.pose, reference)[1] * 1e3
        if color:
            joint = icp.align(maps[0], maps[1], None, terms=("photometric",))
            row["ours_joint_mm"] = pose_error(joint.pose, reference)[1] * 1e3
        if o3d is not None:
            result = odometry.rgbd_odometry_multi_scale(rgbd(source), rgbd(target), intrinsic,
                                                        o3c.Tensor(np.eye(4)), 1000.0, 3.0, criteria,
                                                        odometry.Method.PointToPlane)
            row["open3d_mm"] = pose_error(result.transformation.numpy(), reference)[1] * 1e3
        rows.append(row)
    return {"pairs": rows, "open3d": open3d_note}


WORKERS = {"slam": worker_slam, "open3d": worker_open3d, "pairs": worker_pairs}


# -- the parent ------------------------------------------------------------------------------------------
def _child(args, data: str, worker: str) -> dict:
    from bench_slam import run_child

    cmd = [sys.executable, __file__, data, "--worker", worker, "--arch", args.arch, "--pairs", str(args.pairs)] + \
        (["--frames", str(args.frames)] if args.frames else []) + [f"--set={text}" for text in args.set]
    result, last_err = run_child(cmd, dict(os.environ))[:2]
    return result if result is not None else {"system": worker, "error": last_err}


def _num(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_sequence(name: str, slam_rows: list[dict], pairs: dict | None) -> None:
    print(f"\n{name}")
    print(f"  {'system':<40} {'frames':>6} {'ATE cm':>7} {'fail':>4} {'fps proc':>8}   "
          f"{'step error mm p50 / p90 / max':>30} {'rot p50':>8}")
    o3d_runs = [r for r in slam_rows if "error" not in r and r["system"].startswith("Open3D")]
    for r in slam_rows:
        if "error" in r:
            print(f"  {r['system']:<40} {r['error']}")
            continue
        steps = f"{r['step_p50_mm']:.1f} / {r['step_p90_mm']:.1f} / {r['step_max_mm']:.1f}"
        print(f"  {r['system']:<40} {r['frames']:>6} {_num(r['ate_m'] and r['ate_m'] * 100, '7.2f')} "
              f"{r['failures']:>4} {_num(r.get('fps'), '8.2f')}   {steps:>30} {r['step_rot_p50_deg']:7.2f}°")
    if len(o3d_runs) > 1:
        ates = sorted(r["ate_m"] * 100 for r in o3d_runs)
        print(f"  Open3D over {len(ates)} runs: ATE {', '.join(f'{a:.2f}' for a in ates)} cm, "
              f"median {np.median(ates):.2f} cm")
    ours = [r for r in slam_rows if "error" not in r and r["system"].startswith("ti-fusion")]
    if ours and o3d_runs:
        median = float(np.median([r["ate_m"] for r in o3d_runs]))
        print(f"  ti-fusion / Open3D median: ATE {ours[0]['ate_m'] / median:.2f}x")
    if pairs is None:
        return
    if "error" in pairs:
        print(f"  pairwise: {pairs['error']}")
        return
    rows = pairs["pairs"]
    if not rows:
        print("  pairwise: no consecutive pair with ground truth")
        return
    columns = [("ours_depth_mm", "ours depth"), ("ours_joint_mm", "ours joint"), ("open3d_mm", "Open3D p2p")]
    columns = [(k, title) for k, title in columns if any(k in r for r in rows)]
    print(f"  pairwise, consecutive pairs from the identity, translation error against ground truth (mm); "
          f"{pairs['open3d']}")
    print(f"  {'pair':>9} {'step':>14} " + " ".join(f"{title:>11}" for _, title in columns))
    for r in rows:
        step = f"{r['step_mm'] / 10:.1f} cm {r['step_deg']:.1f}°"
        print(f"  {r['source']:>4}→{r['target']:<4} {step:>14} " +
              " ".join(_num(r.get(k), "11.1f") for k, _ in columns))
    for stat, f in (("median", np.median), ("mean", np.mean), ("p90", lambda x: np.percentile(x, 90))):
        print(f"  {stat:>9} {'':>14} " + " ".join(
            _num(f([r[k] for r in rows if k in r]) if any(k in r for r in rows) else None, "11.1f")
            for k, _ in columns))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="*", help=f"sequence folders (default: every one with ground truth under "
                                                f"{SHARED})")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each (default: all)")
    parser.add_argument("--open3d-runs", type=int, default=3, help="Open3D SLAM runs per sequence (0: none)")
    parser.add_argument("--pairs", type=int, default=60, help="at most this many consecutive pairs per sequence "
                                                              "(0: no pairwise table)")
    parser.add_argument("--no-slam", action="store_true", help="no ti-fusion slam run (pairwise and Open3D only)")
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a config override for ti-fusion (slam and pairwise), as ti-fusion slam's --set")
    parser.add_argument("--json", metavar="FILE", help="also write every row as JSON")
    parser.add_argument("--worker", choices=tuple(WORKERS), help=argparse.SUPPRESS)
    args = parser.parse_args()
    for option, value, least in (("--open3d-runs", args.open3d_runs, 0), ("--pairs", args.pairs, 0),
                                 ("--frames", args.frames, 2)):
        if value is not None and value < least:
            parser.exit(2, f"bench_real.py: {option} {value}: give at least {least}\n")
    if args.worker:
        args.data = args.data[0]
        print("RESULT " + json.dumps(WORKERS[args.worker](args)), flush=True)
        return 0
    if args.set:  # a bad override is one line here, not once per child
        from ti_fusion.errors import TiFusionError

        try:
            _config("", None, args.set)
        except TiFusionError as e:
            parser.exit(2, f"bench_real.py: --set: {e}\n")
    data, left_out = (args.data, []) if args.data else real_sequences(SHARED)
    for line in left_out:
        print(f"left out: {line}")
    if not data:
        parser.exit(2, f"bench_real.py: no real sequence with ground truth under {SHARED}; name one\n")
    import time

    print(f"real sequences, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC"
          + (f"; ti-fusion with {' '.join(args.set)}" if args.set else ""))
    everything = {}
    for path in data:
        rows = [] if args.no_slam else [_child(args, path, "slam")]
        rows += [_child(args, path, "open3d") for _ in range(args.open3d_runs)]
        pairs = _child(args, path, "pairs") if args.pairs else None
        print_sequence(Path(path).name + (f", first {args.frames} frames" if args.frames else ""), rows, pairs)
        everything[path] = {"slam": rows, "pairs": pairs}
    if args.json:
        Path(args.json).write_text(json.dumps(everything, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
