#!/usr/bin/env python3
"""Dense SLAM against Open3D's tensor SLAM on the same frames, one table, measured in one run.

    python scripts/bench_slam.py [DATA] [--frames N] [--downsample F] [--arch cpu]

DATA defaults to ../shared/data/redkitchen-7scenes when present, else the synthetic sequence. Each
system runs in its own child process (so each gets its own peak memory and process start). Two rates,
side by side so that neither is read as the other:
- ``fps wall``: frames / wall-clock time of the whole loop, with reading the images, the first frames'
  kernel compilation and logging;
- ``fps proc``: frames / time of tracking + fusion (+ logging for ti-fusion) after the first two frames,
  without reading the images or compiling.
``1st tracked s`` is the child's age when its second frame (the first one tracked) was done: the cold
start with the kernel cache as it is. ``process s`` is its age at the end, outputs written. ti-fusion is
the ``ti-fusion slam`` command itself, run in the child; ``--cold`` adds a run of it with an empty Taichi
kernel cache (a fresh TI_OFFLINE_CACHE_FILE_PATH), and the next ti-fusion run reads that cache (warm, and
independent of the user's cache, which holds other versions of the kernels and has an LRU size limit). Open3D (``pip install open3d-cpu``; Debian's
libusb-1.0-0) is optional: without it the table has ti-fusion alone. Open3D runs
``o3d.t.pipelines.slam.Model`` (frame-to-model TSDF, voxel 0.0059 m, depth max 3 m, truncation 8 voxels,
depth-only point-to-plane) and writes nothing.
"""

from __future__ import annotations

import argparse
import json
import os
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


def run_ti_fusion(args, cold: bool = False) -> dict:
    """``ti-fusion slam`` in this process, as a user runs it (every output written)."""
    from ti_fusion.cli.main import main as cli

    with tempfile.TemporaryDirectory() as tmp:
        argv = ["slam", *([args.data] if args.data else []), "--downsample", str(args.downsample), "--arch",
                args.arch, "--quiet", "--out", str(Path(tmp) / "run")]
        if args.frames:
            argv += ["--frames", str(args.frames)]
        code = cli(argv)
        if code != 0:
            return {"system": "ti-fusion", "error": f"ti-fusion slam exited with {code}"}
        s = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    return {"system": f"ti-fusion ({s['backend']}{', empty kernel cache' if cold else ''})", "frames": s["frames"],
            "fps_wall": s["fps_wall"], "fps": s["fps_processing"], "first_tracked_s": s.get("second_frame_s"),
            "process_s": s.get("process_s"), "ate_rmse_m": s.get("ate_rmse_m"), "rpe_trans_m": s.get("rpe_trans_m"),
            "failures": s["tracking_failures"], "peak_mb": _peak_mb()}


def run_open3d(args) -> dict:
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return {"system": "Open3D", "error": "not installed (pip install open3d-cpu)"}
    from ti_fusion.evaluation.metrics import trajectory_metrics
    from ti_fusion.slam.timing import process_age_s

    _, dataset = _dataset(args)
    K = dataset.intrinsics
    device = o3c.Device("CPU:0")
    intrinsic = o3c.Tensor(K.K, o3c.Dtype.Float64)
    depth_scale, depth_max, voxel = 1000.0, 3.0, 0.0059
    t_loop = time.perf_counter()  # the loop's wall-clock time starts with reading the first frame
    first = dataset[0]
    T = o3c.Tensor(first.gt_pose if first.gt_pose is not None else np.eye(4), o3c.Dtype.Float64)
    model = o3d.t.pipelines.slam.Model(voxel, 16, 50000, T, device)
    input_frame = o3d.t.pipelines.slam.Frame(K.height, K.width, intrinsic, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(K.height, K.width, intrinsic, device)
    poses, gts, times = [], [], []
    first_tracked = None
    for i in range(len(dataset)):
        frame = first if i == 0 else dataset[i]  # reading counts in fps_wall, not in fps
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
        if i == 1:
            first_tracked = process_age_s()
    wall = time.perf_counter() - t_loop
    steady = np.asarray(times[2:])
    out = {"system": f"Open3D {o3d.__version__} (cpu)", "frames": len(poses), "fps_wall": len(poses) / wall,
           "fps": len(steady) / steady.sum(), "first_tracked_s": first_tracked, "process_s": process_age_s(),
           "failures": 0, "peak_mb": _peak_mb()}
    if all(g is not None for g in gts):
        m = trajectory_metrics(np.stack(poses), np.stack(gts))
        out.update(ate_rmse_m=m["ate_rmse_m"], rpe_trans_m=m["rpe_trans_m"])
    return out


def _number(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA) if DEFAULT_DATA.is_dir() else "")
    parser.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--systems", default="ti-fusion,open3d")
    parser.add_argument("--cold", action="store_true",
                        help="also run ti-fusion with an empty Taichi kernel cache (the first run after installing)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = (run_open3d(args) if args.worker == "open3d" else
                  run_ti_fusion(args, cold=args.worker == "ti-fusion-cold"))
        print("RESULT " + json.dumps(result), flush=True)
        return 0

    systems = args.systems.split(",")
    if args.cold and "ti-fusion" in systems:
        systems.insert(systems.index("ti-fusion"), "ti-fusion-cold")
    rows = []
    # --cold: an empty kernel cache of its own, which the cold run fills and the warm run then reads
    cache = tempfile.TemporaryDirectory() if args.cold else None
    for system in systems:
        cmd = [sys.executable, __file__, args.data, "--worker", system, "--downsample", str(args.downsample),
               "--arch", args.arch] + (["--frames", str(args.frames)] if args.frames else [])
        env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": cache.name} if cache and "ti-fusion" in system else None
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        rows.append(json.loads(lines[-1][7:]) if lines else
                    {"system": system, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]})
    if cache:
        cache.cleanup()
    name = args.data or "synthetic"
    print(f"dense SLAM on {name}, downsample {args.downsample}")
    print(f"{'system':<38} {'frames':>6} {'fps wall':>8} {'fps proc':>8} {'1st tracked s':>13} {'process s':>9} "
          f"{'ATE m':>8} {'RPE m':>8} {'fail':>5} {'peak MB':>8}")
    for r in rows:
        if "error" in r:
            print(f"{r['system']:<38} {r['error']}")
            continue
        print(f"{r['system']:<38} {r['frames']:>6} {_number(r['fps_wall'], '8.2f')} {_number(r['fps'], '8.2f')} "
              f"{_number(r['first_tracked_s'], '13.2f')} {_number(r['process_s'], '9.2f')} "
              f"{_number(r.get('ate_rmse_m'), '8.4f')} {_number(r.get('rpe_trans_m'), '8.4f')} {r['failures']:>5} "
              f"{r['peak_mb']:>8.0f}")
    ours = [r for r in rows if "error" not in r and r["system"].startswith("ti-fusion") and "empty" not in r["system"]]
    peers = [r for r in rows if "error" not in r and r["system"].startswith("Open3D")]
    if ours and peers:
        a, b = ours[0], peers[0]
        line = (f"ratios ti-fusion / Open3D: fps wall {a['fps_wall'] / b['fps_wall']:.2f}x, "
                f"fps proc {a['fps'] / b['fps']:.2f}x, process time {b['process_s'] / a['process_s']:.2f}x shorter")
        if a.get("ate_rmse_m") and b.get("ate_rmse_m"):
            line += f", ATE {a['ate_rmse_m'] / b['ate_rmse_m']:.2f}x"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
