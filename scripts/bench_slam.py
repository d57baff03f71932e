#!/usr/bin/env python3
"""Dense SLAM against Open3D's tensor SLAM and OpenCV's odometry on the same frames, one table, one run.

    python scripts/bench_slam.py [DATA] [--frames N] [--downsample F] [--arch cpu] [--cold]
                                 [--systems ti-fusion,open3d,opencv] [--open3d-python PY] [--opencv-path DIR]
                                 [--opencv-odometry depth|depth-fast|rgbd|rgb] [--set SECTION.KEY=VALUE ...]

DATA defaults to ../shared/data/redkitchen-7scenes when present, else the synthetic sequence. Each
system runs in its own child process, one after the other, so each has its own process start, its own
peak memory and the cores to itself (apart from other users of the machine). Columns:
- ``process s``: the child's whole wall-clock life as this script measured it (interpreter start, imports,
  reading every frame, compiling, tracking, fusion, logging, writing the outputs, exit), and ``fps
  process`` = frames / that: what a user waits for;
- ``fps loop``: frames / wall-clock time of the frame loop (``fps_wall`` of ti-fusion's summary): with
  reading the images, the first frames' kernel compilation and logging, without start-up and outputs;
- ``fps proc``: frames / time of tracking + fusion (+ logging for ti-fusion) after the first two frames,
  without reading the images or compiling; the JSON's ``fps_loop_steady`` is ti-fusion's whole loop after
  those two frames (waiting for frames and logging included);
- ``1st tracked s``: the child's age (from the kernel's record of its start) when its second frame (the
  first one tracked) was done: the cold start with the kernel cache as it is;
- ``peak MB``: the child's maximum resident set size (``wait4``'s rusage, all of the process's life);
- ``cores``: the cores the child used on average: its CPU time (user + system, its own and its reader
  processes', from the same rusage) over its wall-clock life; for ti-fusion the line after the table also
  gives its main thread's CPU time (the loop's Python and kernel launches; Taichi's CPU workers run the
  kernels while it waits), which no other thread can take over: a lower bound on the process's
  wall-clock time, which other processes' load moves less than the wall-clock time itself (by up to a
  quarter between runs here, through the caches it shares with them);
- ``read wait``: the share of ti-fusion's loop spent waiting for the next frame (the ``load`` stage after
  the first two frames, over the loop's wall-clock time).
ti-fusion is the ``ti-fusion slam`` command itself (every output written; the child ends as the command does,
``end_process``), run in the child, with ``--set``
passed on to it (e.g. ``--set slam.loop_closure=false`` where GTSAM is not installed). ``--cold``
adds a run of it with an empty Taichi kernel cache (a fresh TI_OFFLINE_CACHE_FILE_PATH), and the next
ti-fusion run reads that cache (warm, and independent of the user's cache, which holds other versions of
the kernels and has an LRU size limit).

Peers, both optional and never dependencies of ti-fusion (without one its row says why):
- Open3D (``pip install open3d-cpu``; Debian's libusb-1.0-0): ``o3d.t.pipelines.slam.Model``
  (frame-to-model TSDF, voxel 0.0059 m, depth max 3 m, truncation 8 voxels, depth-only point-to-plane);
  writes nothing.
- OpenCV's RGB-D odometry, frame to frame (an odometry-only trajectory: no map, so no drift correction
  and no fusion time): OpenCV 5's ``cv2.Odometry`` (in the 3d module of the main wheels, so
  ``opencv-python-headless`` 5.x, a ti-fusion dependency, already has it) or OpenCV 4's contrib
  ``cv2.rgbd`` (``opencv-contrib-python-headless`` 4.x, which cannot share an environment with
  ``opencv-python-headless``: install it into a folder of its own with ``pip install --target DIR``
  and pass ``--opencv-path DIR``). ``--opencv-odometry``: ``depth`` (point-to-plane ICP, default),
  ``depth-fast`` (OpenCV's fast ICP variant), ``rgbd`` (ICP + photometric), ``rgb`` (photometric only).
  The colour of 7-Scenes is not registered to its depth, so the colour variants are at a disadvantage there.
Open3D runs in this interpreter unless ``--open3d-python PY`` names another (e.g. a virtual environment
with ``pip install open3d-cpu``), which then finds ti-fusion (for reading the frames and the metrics)
through this interpreter's site-packages, added after its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import site
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from benchlib import OpenCVOdometry, grey_of

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"


def _add_parent_site() -> None:
    """In a peer's own interpreter: this benchmark's interpreter's site-packages (ti-fusion and what it
    reads frames with), after the peer's own, so that the peer's packages win where both have one."""
    for path in filter(None, os.environ.get("BENCH_SLAM_SITE", "").split(os.pathsep)):
        if path not in sys.path:
            site.addsitedir(path)


def _dataset(args):
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import open_dataset

    cfg = Config()
    cfg.dataset.path = args.data
    cfg.dataset.downsample = args.downsample
    cfg.dataset.stop = args.frames
    cfg.log.progress = False
    return cfg, open_dataset(cfg.dataset, cfg.synth)


def slam_run(args, options: list[str]) -> tuple[dict, tuple] | str:
    """``ti-fusion slam [DATA] OPTIONS`` in this process, as a user runs it (every output written, into a
    temporary folder), with ``args``' arch, frames and --set: (its summary.json, its trajectory as
    ``read_tum`` gives it), or the error line when it did not end with 0."""
    from ti_fusion.cli.main import main as cli
    from ti_fusion.io.trajectory import read_tum

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        argv = ["slam", *([args.data] if args.data else []), *options, "--arch", args.arch, "--quiet",
                "--out", str(out)]
        if args.frames:
            argv += ["--frames", str(args.frames)]
        argv += [f"--set={text}" for text in args.set]
        code = cli(argv)
        if code != 0:
            return f"ti-fusion slam exited with {code}"
        return json.loads((out / "summary.json").read_text()), read_tum(out / "trajectory.tum")


def run_ti_fusion(args, cold: bool = False) -> dict:
    """``ti-fusion slam`` in this process, as a user runs it (every output written)."""
    run = slam_run(args, ["--downsample", str(args.downsample)])
    if isinstance(run, str):
        return {"system": "ti-fusion", "error": run}
    s = run[0]
    return {"system": f"ti-fusion ({s['backend']}{', empty kernel cache' if cold else ''})", "frames": s["frames"],
            "fps_wall": s["fps_wall"], "fps": s["fps_processing"], "first_tracked_s": s.get("second_frame_s"),
            "ate_rmse_m": s.get("ate_rmse_m"), "rpe_trans_m": s.get("rpe_trans_m"),
            "failures": s["tracking_failures"], "loop_s": s.get("wall_s"), "age_end_s": s.get("process_s"),
            "warmup_s": s["warmup_ms"] / 1e3 if s.get("warmup_ms") is not None else None,
            "fps_loop_steady": _steady(s), "main_thread_cpu_s": time.thread_time(),
            "stages_s": {k: v["total"] / 1e3 for k, v in (s.get("ms_per_stage") or {}).items()}}


def _steady(s: dict) -> float | None:
    """Frames per second of the whole loop after the first two frames (their kernel compiling or loading left
    out, reading, logging and every stage kept): (frames − 2) / (loop − the two frames' step time)."""
    frames, wall, warmup = s.get("frames", 0), s.get("wall_s"), s.get("warmup_ms")
    if frames <= 2 or not wall or warmup is None or wall <= warmup / 1e3:
        return None
    return round((frames - 2) / (wall - warmup / 1e3), 2)


def _trajectory_result(system, poses, gts, times, wall, first_tracked, failures) -> dict:
    from ti_fusion.evaluation.metrics import trajectory_metrics

    steady = np.asarray(times[2:])
    out = {"system": system, "frames": len(poses), "fps_wall": len(poses) / wall,
           "fps": len(steady) / steady.sum() if len(steady) else None, "first_tracked_s": first_tracked,
           "failures": failures}
    if all(g is not None for g in gts):
        m = trajectory_metrics(np.stack(poses), np.stack(gts))
        out.update(ate_rmse_m=m["ate_rmse_m"], rpe_trans_m=m["rpe_trans_m"])
    return out


def open3d_slam(args):
    """Open3D's tensor SLAM over the frames of ``args`` (module docstring): (poses, ground truths, seconds of
    processing per frame, wall-clock s of the loop, the process's age at the first tracked frame, Open3D's
    version), or a string saying why Open3D is not available."""
    _add_parent_site()
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError as e:
        return f"not available ({e}; pip install open3d-cpu, or --open3d-python PY)"
    from ti_fusion.timing import process_age_s

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
        color = frame.color if frame.color is not None else np.zeros((K.height, K.width, 3), np.uint8)
        t0 = time.perf_counter()
        input_frame.set_data_from_image("depth", depth)
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color))))
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
    return poses, gts, times, time.perf_counter() - t_loop, first_tracked, o3d.__version__


def run_open3d(args) -> dict:
    out = open3d_slam(args)
    if isinstance(out, str):
        return {"system": "Open3D", "error": out}
    poses, gts, times, wall, first_tracked, version = out
    return _trajectory_result(f"Open3D {version} (cpu)", poses, gts, times, wall, first_tracked, 0)


def run_opencv(args) -> dict:
    """Frame-to-frame odometry: each frame against the previous one (prepared once, reused), poses chained;
    a failed frame keeps the previous pose (counted as a failure)."""
    _add_parent_site()
    import cv2

    from ti_fusion.timing import process_age_s

    if not hasattr(cv2.utils, "logging"):  # OpenCV 4 wheels lack it; ti-fusion's image reading silences through it
        import types

        cv2.utils.logging = types.SimpleNamespace(LOG_LEVEL_SILENT=0, getLogLevel=lambda: 0,
                                                  setLogLevel=lambda level: None)
    cfg, dataset = _dataset(args)
    try:
        odometry = OpenCVOdometry(args.opencv_odometry, dataset.intrinsics, cfg.dataset.depth_max)
    except (ImportError, AttributeError) as e:
        return {"system": "OpenCV", "error": f"not available ({e})"}
    t_loop = time.perf_counter()
    poses, gts, times = [], [], []
    first_tracked, failures, previous = None, 0, None
    for i in range(len(dataset)):
        frame = dataset[i]
        t0 = time.perf_counter()
        current = odometry.prepare(frame.depth, grey_of(frame.color) if odometry.uses_grey else None)
        if previous is None:
            T = frame.gt_pose.copy() if frame.gt_pose is not None else np.eye(4)
        else:
            ok, Rt = odometry.compute(current, previous)  # current → previous camera frame
            failures += not ok
            T = T @ Rt
        previous = current
        times.append(time.perf_counter() - t0)
        poses.append(T.copy())
        gts.append(frame.gt_pose)
        if i == 1:
            first_tracked = process_age_s()
    out = _trajectory_result(f"{odometry.name} (frame to frame)", poses, gts, times, time.perf_counter() - t_loop,
                             first_tracked, failures)
    out["api"] = odometry.api
    return out


def _number(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _read_wait(r: dict) -> str:
    """The share of ti-fusion's loop spent waiting for the next frame (its ``load`` stage after the warm-up
    frames, over the whole loop's wall-clock time); "-" for a peer, which reads its frames in its loop."""
    load = (r.get("stages_s") or {}).get("load")
    return "-".rjust(9) if load is None or not r.get("loop_s") else f"{100 * load / r['loop_s']:8.1f}%"


def run_child(cmd: list[str], env: dict | None) -> tuple[dict | None, str, float, float, float]:
    """(RESULT of the child or None, its last line of stderr, its wall-clock life in s, its peak RSS in MB, its
    CPU seconds: user + system, its own and those of the processes it waited for, e.g. its frame readers)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    outs, errs = [], []
    readers = [threading.Thread(target=lambda s, into: into.append(s.read()), args=(stream, into))
               for stream, into in ((proc.stdout, outs), (proc.stderr, errs))]
    for t in readers:
        t.start()
    # the child's own rusage (RUSAGE_CHILDREN would be the maximum over every child so far)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    for t in readers:
        t.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    out, err = "".join(outs), "".join(errs)
    lines = [line for line in out.splitlines() if line.startswith("RESULT ")]
    return (json.loads(lines[-1][7:]) if lines else None, (err.strip().splitlines() or ["failed"])[-1], wall,
            usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime)


def byte_compile_ti_fusion() -> None:
    """ti_fusion's modules byte-compiled (into ``__pycache__``, where missing or stale), as pip compiles an installed
    package and the peers' packages are: an editable install leaves it to the first import, which
    PYTHONDONTWRITEBYTECODE=1 turns off, and every run would then compile its ~125 modules again (0.2-0.3 s of CPU,
    docs/PERFORMANCE.md)."""
    import compileall
    import importlib.util

    for name in ("ti_fusion", "ti_fusion.kernels"):
        spec = importlib.util.find_spec(name)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            compileall.compile_dir(folder, quiet=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA) if DEFAULT_DATA.is_dir() else "")
    parser.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--systems", default="ti-fusion,open3d,opencv")
    parser.add_argument("--cold", action="store_true",
                        help="also run ti-fusion with an empty Taichi kernel cache (the first run after installing)")
    parser.add_argument("--open3d-python", default=None, metavar="PY",
                        help="an interpreter with open3d installed, when this one has none")
    parser.add_argument("--opencv-path", default=None, metavar="DIR",
                        help="a folder with another cv2 (pip install --target DIR opencv-contrib-python-headless==4.*), "
                             "put before this interpreter's packages for the OpenCV run")
    parser.add_argument("--opencv-odometry", default="depth", choices=OpenCVOdometry.KINDS)
    parser.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a config override for ti-fusion, as ti-fusion slam's --set (repeatable)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        workers = {"open3d": run_open3d, "opencv": run_opencv,
                   "ti-fusion": run_ti_fusion, "ti-fusion-cold": lambda a: run_ti_fusion(a, cold=True)}
        print("RESULT " + json.dumps(workers[args.worker](args)), flush=True)
        if args.worker.startswith("ti-fusion"):  # the process ends as the ti-fusion command's does
            try:
                from ti_fusion.cli.main import end_process
            except ImportError:  # (a ti_fusion from before it, on PYTHONPATH: its command ended the usual way)
                return 0
            end_process(0)
        return 0

    systems = args.systems.split(",")
    if any(system.startswith("ti-fusion") for system in systems):
        byte_compile_ti_fusion()
    if args.cold and "ti-fusion" in systems:
        systems.insert(systems.index("ti-fusion"), "ti-fusion-cold")
    rows = []
    # --cold: an empty kernel cache of its own, which the cold run fills and the warm run then reads
    cache = tempfile.TemporaryDirectory() if args.cold else None
    parent_site = os.pathsep.join(site.getsitepackages() + [str(Path(__file__).resolve().parents[1])])
    for system in systems:
        python = args.open3d_python if system == "open3d" and args.open3d_python else sys.executable
        cmd = [python, __file__, args.data, "--worker", system, "--downsample", str(args.downsample),
               "--arch", args.arch, "--opencv-odometry", args.opencv_odometry] + \
            (["--frames", str(args.frames)] if args.frames else []) + [f"--set={text}" for text in args.set]
        env = dict(os.environ)
        if cache and "ti-fusion" in system:
            env["TI_OFFLINE_CACHE_FILE_PATH"] = cache.name
        if python != sys.executable:
            env["BENCH_SLAM_SITE"] = parent_site
        if system == "opencv" and args.opencv_path:
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [args.opencv_path, env.get("PYTHONPATH")]))
        result, last_err, wall, peak, cpu = run_child(cmd, env)
        if result is None:
            result = {"system": system, "error": last_err}
        result.update(process_s=wall, peak_mb=peak, cpu_s=cpu)
        rows.append(result)
    if cache:
        cache.cleanup()
    name = args.data or "synthetic"
    print(f"dense SLAM on {name}, downsample {args.downsample}, {os.cpu_count()} CPUs; "
          f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC")
    print(f"{'system':<48} {'frames':>6} {'process s':>9} {'fps process':>11} {'fps loop':>8} {'fps proc':>8} "
          f"{'1st tracked s':>13} {'ATE m':>8} {'RPE m':>8} {'fail':>5} {'peak MB':>8} {'cores':>5} {'read wait':>9}")
    for r in rows:
        if "error" in r:
            print(f"{r['system']:<48} {r['error']}")
            continue
        print(f"{r['system']:<48} {r['frames']:>6} {r['process_s']:9.2f} {r['frames'] / r['process_s']:11.2f} "
              f"{_number(r['fps_wall'], '8.2f')} {_number(r['fps'], '8.2f')} "
              f"{_number(r['first_tracked_s'], '13.2f')} "
              f"{_number(r.get('ate_rmse_m'), '8.4f')} {_number(r.get('rpe_trans_m'), '8.4f')} {r['failures']:>5} "
              f"{r['peak_mb']:>8.0f} {r['cpu_s'] / r['process_s']:5.2f} {_read_wait(r)}")
    for r in rows:
        if r.get("stages_s"):
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r["stages_s"].items())
            main_cpu = r.get("main_thread_cpu_s")
            on_main = "" if main_cpu is None else \
                f", {main_cpu:.2f} s of it on the loop's thread (Python and launches; Taichi's workers wait)"
            print(f"{r['system']}: {r['cpu_s']:.2f} s of CPU in {r['process_s']:.2f} s ({r['cpu_s'] / r['process_s']:.2f} "
                  f"cores){on_main}; the loop waited {r['stages_s'].get('load', 0.0):.2f} s for frames "
                  f"({_read_wait(r).strip()} of it) and the readers read for {r['stages_s'].get('read', 0.0):.2f} s")
            print(f"{r['system']}: where the {r['process_s']:.2f} s went: before the loop and after it "
                  f"{r['process_s'] - r['loop_s']:.2f} s, the loop {r['loop_s']:.2f} s, of which its first two frames "
                  f"(compiling) {_number(r.get('warmup_s'), '.2f')} s; stage totals after them (s): {stages}")
    ok = [r for r in rows if "error" not in r]
    ours = [r for r in ok if r["system"].startswith("ti-fusion") and "empty" not in r["system"]]
    for prefix in ("Open3D", "OpenCV"):
        peers = [r for r in ok if r["system"].startswith(prefix)]
        if ours and peers:
            a, b = ours[0], peers[0]
            line = (f"ti-fusion / {prefix}: whole process {b['process_s'] / a['process_s']:.2f}x shorter, "
                    f"fps process {(a['frames'] / a['process_s']) / (b['frames'] / b['process_s']):.2f}x, "
                    f"fps loop {a['fps_wall'] / b['fps_wall']:.2f}x, fps proc {a['fps'] / b['fps']:.2f}x")
            if a.get("ate_rmse_m") and b.get("ate_rmse_m"):
                line += f", ATE {a['ate_rmse_m'] / b['ate_rmse_m']:.2f}x"
            print(line)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
