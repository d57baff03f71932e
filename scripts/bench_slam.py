#!/usr/bin/env python3
"""Dense SLAM against Open3D's tensor SLAM on the same frames, one table, measured in one run.

    python scripts/bench_slam.py [DATA] [--frames N] [--downsample F] [--arch cpu]

DATA defaults to ../shared/data/redkitchen-7scenes when present, else the synthetic sequence. Each
system runs in its own child process (so each gets its own peak memory figure). Frames per second count
tracking + fusion (+ logging for ti-fusion), excluding image loading and the first frames' kernel
compilation, which is reported on its own. Open3D (``pip install open3d-cpu``; Debian's libusb-1.0-0)
is optional: without it the table has ti-fusion alone. Open3D runs ``o3d.t.pipelines.slam.Model``
(frame-to-model TSDF, voxel 0.0059 m, depth max 3 m, truncation 8 voxels, depth-only point-to-plane).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _dataset(args):
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import open_dataset

    cfg = Config()
    cfg.dataset.path = args.data
    cfg.dataset.downsample = args.downsample
    cfg.dataset.stop = args.frames
    cfg.log.progress = False
    return cfg, open_dataset(cfg.dataset, cfg.synth)


def run_ti_fusion(args) -> dict:
    from ti_fusion.backend import init_backend
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    backend = init_backend(args.arch)
    cfg, dataset = _dataset(args)
    with tempfile.TemporaryDirectory() as tmp:
        s = SLAMPipeline(dataset, cfg, RunDir("slam", tmp), backend, show_progress=False).run()
    return {"system": f"ti-fusion ({backend.arch})", "frames": s["frames"], "fps": s["fps_processing"],
            "warmup_s": s["warmup_ms"] / 1e3, "ate_rmse_m": s.get("ate_rmse_m"), "rpe_trans_m": s.get("rpe_trans_m"),
            "failures": s["tracking_failures"], "peak_mb": _peak_mb()}


def run_open3d(args) -> dict:
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return {"system": "Open3D", "error": "not installed (pip install open3d-cpu)"}
    from ti_fusion.evaluation.metrics import trajectory_metrics

    _, dataset = _dataset(args)
    K = dataset.intrinsics
    device = o3c.Device("CPU:0")
    intrinsic = o3c.Tensor(K.K, o3c.Dtype.Float64)
    depth_scale, depth_max, voxel = 1000.0, 3.0, 0.0059
    first = dataset[0]
    T = o3c.Tensor(first.gt_pose if first.gt_pose is not None else np.eye(4), o3c.Dtype.Float64)
    model = o3d.t.pipelines.slam.Model(voxel, 16, 50000, T, device)
    input_frame = o3d.t.pipelines.slam.Frame(K.height, K.width, intrinsic, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(K.height, K.width, intrinsic, device)
    poses, gts, times = [], [], []
    for i in range(len(dataset)):
        frame = dataset[i]  # loading is not timed
        depth = o3d.t.geometry.Image(o3c.Tensor(np.round(frame.depth * depth_scale).astype(np.uint16)))
        colour = frame.color if frame.color is not None else np.zeros((K.height, K.width, 3), np.uint8)
        t0 = time.perf_counter()
        input_frame.set_data_from_image("depth", depth)
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colour))))
        if i > 0:
            result = model.track_frame_to_model(input_frame, raycast_frame, depth_scale, depth_max)
            T = T @ result.transformation
        model.update_frame_pose(i, T)
        model.integrate(input_frame, depth_scale, depth_max, 8.0)
        model.synthesize_model_frame(raycast_frame, depth_scale, 0.1, depth_max, 8.0, False)
        times.append(time.perf_counter() - t0)
        poses.append(T.cpu().numpy())
        gts.append(frame.gt_pose)
    steady = np.asarray(times[2:])
    out = {"system": f"Open3D {o3d.__version__} (cpu)", "frames": len(poses), "fps": len(steady) / steady.sum(),
           "warmup_s": float(sum(times[:2])), "failures": 0, "peak_mb": _peak_mb()}
    if all(g is not None for g in gts):
        m = trajectory_metrics(np.stack(poses), np.stack(gts))
        out.update(ate_rmse_m=m["ate_rmse_m"], rpe_trans_m=m["rpe_trans_m"])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA) if DEFAULT_DATA.is_dir() else "")
    parser.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--systems", default="ti-fusion,open3d")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = run_ti_fusion(args) if args.worker == "ti-fusion" else run_open3d(args)
        print("RESULT " + json.dumps(result), flush=True)
        return 0

    rows = []
    for system in args.systems.split(","):
        cmd = [sys.executable, __file__, args.data, "--worker", system, "--downsample", str(args.downsample),
               "--arch", args.arch] + (["--frames", str(args.frames)] if args.frames else [])
        proc = subprocess.run(cmd, capture_output=True, text=True)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        rows.append(json.loads(lines[-1][7:]) if lines else
                    {"system": system, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]})
    name = args.data or "synthetic"
    print(f"dense SLAM on {name}, downsample {args.downsample}")
    print(f"{'system':<24} {'frames':>6} {'fps':>7} {'warm-up s':>9} {'ATE m':>8} {'RPE m':>8} {'fail':>5} {'peak MB':>8}")
    for r in rows:
        if "error" in r:
            print(f"{r['system']:<24} {r['error']}")
            continue
        ate = f"{r['ate_rmse_m']:.4f}" if r.get("ate_rmse_m") is not None else "-"
        rpe = f"{r['rpe_trans_m']:.4f}" if r.get("rpe_trans_m") is not None else "-"
        print(f"{r['system']:<24} {r['frames']:>6} {r['fps']:>7.2f} {r['warmup_s']:>9.1f} {ate:>8} {rpe:>8} "
              f"{r['failures']:>5} {r['peak_mb']:>8.0f}")
    ok = [r for r in rows if "error" not in r]
    if len(ok) == 2:
        a, b = ok
        print(f"ratios ti-fusion / Open3D: fps {a['fps'] / b['fps']:.2f}x, ATE {a['ate_rmse_m'] / b['ate_rmse_m']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
