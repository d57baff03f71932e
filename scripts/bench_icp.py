#!/usr/bin/env python
"""Benchmark: projective point-to-plane ICP, Taichi kernels against NumPy and Open3D, in one run.

For one frame pair at 640×480 and at 320×240 it prints
- ms per ICP iteration at the finest level (association + linearisation + reduction + the 6×6 solve):
  the iteration as ``ICP.align`` runs it (on the CPU one launch of ``PointToPlane.iterate``, which also
  solves and updates the pose; the replay of the checks afterwards, about 12 µs per iteration, is not
  timed) against a lean vectorised NumPy float64 version of the same math (``icp_numpy.LevelIteration``:
  the source masked once per level, no status image, then the NumPy solve), and their ratio, both with the
  robust weights ``ICP.align`` uses. Taichi is timed over 5 iterations back to back (as within one pyramid
  level), NumPy one at a time, alternately, each after one untimed call (threads awake, as within ICP),
  with a pause after each NumPy iteration so that OpenBLAS's spinning threads are not timed as part of
  Taichi's iteration;
- ms per frame pair (maps of both frames + coarse-to-fine ICP with ``icp.iterations``) against Open3D's
  ``t.pipelines.odometry.rgbd_odometry_multi_scale`` with ``Method.PointToPlane`` and the same iteration
  counts (Open3D builds its own pyramids, vertex and normal maps inside that call), with both errors
  against the reference relative pose when the data has one.

Each table is printed twice: wall-clock, and CPU time of each process (all its threads). The machine
this was written on is shared by several jobs: with another process on one of its two cores, Taichi's
two halves of a loop and Open3D's worker threads all share one core and wall-clock ratios swing from run
to run, while CPU time (the work done) is steadier. Ours and Open3D run in alternating blocks of 5
back-to-back frame pairs (each system's threads awake, as when it processes a sequence; the first pair of
a block untimed), with 0.2 s between blocks so that neither is timed while the other's threads still spin.
Run one pair at a time right after the other system instead, Open3D (whose OpenMP threads then had to
wake) took 12.3 ms at 320×240 instead of 7.2: how the runs are interleaved matters as much as the code.

Freed memory is kept for reuse (``benchlib.keep_freed_memory``): by default glibc unmaps NumPy's large
temporaries when they are freed, in some processes and not in others, and the page faults of the
next call made one NumPy iteration 17.5 instead of 13 ms at 320×240 (70 instead of 52 at 640×480).

Data: the redkitchen frames ``--pair S T`` (default 100 110) from DATA or ../shared/data when present,
else two renders of the synthetic room 3° and 5 cm apart.

Open3D is optional: when ``import open3d`` fails it is skipped, unless ``--open3d-python PY`` names an
interpreter that has it (e.g. a throwaway venv with ``pip install open3d-cpu``); that interpreter then
runs this file's worker on the same depth images, within the same benchmark run.

The photometric term (``icp.color_weight``, docs/PHOTOMETRIC.md): its cost per frame on the synthetic
room (colour registered to depth), 640×480 input tracked at 320×240 as the SLAM loop does: the live
frame's intensity pyramid and gradients, the model's intensity (gathered per pixel, timed here as a second
intensity pyramid), and the joint ICP against the depth-only ICP with the same iterations (``--photometric 0``
skips it).

OpenCV's RGB-D odometry (``benchlib.OpenCVOdometry``: OpenCV 5's ``cv2.Odometry``, which the
``opencv-python-headless`` 5.x that ti-fusion depends on already has, or OpenCV 4 contrib's ``cv2.rgbd``) is
the second peer, in this interpreter (skipped when its cv2 has neither): ``--opencv-odometry`` (default
``depth``, point-to-plane ICP) with OpenCV's own settings (its pyramid of 4 levels with 7, 7, 7, 10
iterations from the finest, depth up to ``dataset.depth_max``); a frame pair is ``prepareFrame`` of both
frames (its pyramids and normals) + ``compute``, timed in blocks alternated with the others'.

Then, on real data, each system runs once from the identity on ``--accuracy-pairs`` pairs ``--accuracy-gap``
frames apart spread over the sequence, and the table gives median / mean / max pose error of each.

usage: scripts/bench_icp.py [DATA] [--pair S T] [--repeats N (20)] [--open3d-python PY] [--set icp.KEY=VALUE]
                            [--accuracy-pairs N] [--accuracy-gap G] [--opencv-odometry KIND]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchlib import BLAS_SETTLE_S, OpenCVOdometry, grey_of, keep_freed_memory, numpy_conditions

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"


# -- Open3D (runs in whichever interpreter has it) ---------------------------------------------------------
class Open3DPair:
    """One frame pair set up for Open3D's multi-scale point-to-plane odometry; ``run()`` aligns it once."""

    def __init__(self, depth_mm: list, K: list, iterations: list[int], depth_max: float):
        import numpy as np
        import open3d as o3d

        self.o3d, self.np = o3d, np
        odo = o3d.t.pipelines.odometry
        self.images = []
        for d in depth_mm:
            d = np.ascontiguousarray(d, dtype=np.uint16)
            color = o3d.t.geometry.Image(np.zeros(d.shape + (3,), np.uint8))
            self.images.append(o3d.t.geometry.RGBDImage(color, o3d.t.geometry.Image(d)))
        self.K = o3d.core.Tensor(np.asarray(K, dtype=np.float64))
        self.criteria = [odo.OdometryConvergenceCriteria(n) for n in iterations]  # coarse → fine, as ours
        self.depth_max = depth_max
        self.version = o3d.__version__

    def run(self) -> tuple[float, float, list]:
        """(wall ms, CPU ms of this process, 4×4 pose source → target) of one call from the identity."""
        odo = self.o3d.t.pipelines.odometry
        t0, c0 = time.perf_counter(), time.process_time()
        result = odo.rgbd_odometry_multi_scale(self.images[0], self.images[1], self.K,
                                               self.o3d.core.Tensor(self.np.eye(4)), 1000.0, self.depth_max,
                                               self.criteria, odo.Method.PointToPlane)
        ms, cpu = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
        return ms, cpu, result.transformation.numpy().tolist()


def _worker(folder: str) -> None:
    """Serve ``Open3DPair.run`` over stdin/stdout: one JSON line per "run" line."""
    import numpy as np

    spec = json.loads(Path(folder, "spec.json").read_text())
    pair = Open3DPair([np.load(Path(folder, f"depth{i}.npy")) for i in (0, 1)], spec["K"], spec["iterations"],
                      spec["depth_max"])
    print(json.dumps({"version": pair.version}), flush=True)
    for line in sys.stdin:
        if line.strip() != "run":
            break
        ms, cpu, pose = pair.run()
        print(json.dumps({"ms": ms, "cpu": cpu, "pose": pose}), flush=True)


class Open3DRunner:
    """Open3D in this interpreter, or in ``python`` (a worker process) when this one has none."""

    def __init__(self, depth_s, depth_t, K, iterations, depth_max, python: str | None):
        import numpy as np

        mm = [np.round(np.asarray(d) * 1000.0).astype(np.uint16) for d in (depth_s, depth_t)]
        Km = [[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]]
        self.pair = self.proc = None
        if python is None:
            self.pair = Open3DPair(mm, Km, iterations, depth_max)  # ImportError when absent
            self.version = self.pair.version
            return
        self._folder = tempfile.TemporaryDirectory()
        for i, d in enumerate(mm):
            np.save(Path(self._folder.name, f"depth{i}.npy"), d)
        Path(self._folder.name, "spec.json").write_text(json.dumps(
            {"K": Km, "iterations": iterations, "depth_max": depth_max}))
        self.proc = subprocess.Popen([python, __file__, "--open3d-worker", self._folder.name], text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        line = self.proc.stdout.readline()
        if not line:
            raise ImportError(f"{python} could not run Open3D")
        self.version = json.loads(line)["version"]

    def run(self) -> tuple[float, float, list]:
        if self.pair is not None:
            return self.pair.run()
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        out = json.loads(self.proc.stdout.readline())
        return out["ms"], out["cpu"], out["pose"]

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
            self._folder.cleanup()


def open3d_runner(depth_s, depth_t, K, iterations, depth_max, python) -> "Open3DRunner | None":
    try:
        return Open3DRunner(depth_s, depth_t, K, iterations, depth_max, python)
    except ImportError:
        return None


class OpenCVPair:
    """One frame pair for OpenCV's odometry (this interpreter's cv2); ``run()`` aligns it once."""

    def __init__(self, depth_s, depth_t, K, depth_max: float, kind: str, color_s=None, color_t=None):
        self.odometry = OpenCVOdometry(kind, K, depth_max)  # ImportError when this cv2 has none
        self.version, self.api = self.odometry.name, self.odometry.api
        grey = self.odometry.uses_grey
        self.inputs = [(d, grey_of(c) if grey else None) for d, c in ((depth_s, color_s), (depth_t, color_t))]

    def run(self) -> tuple[float, float, list]:
        """(wall ms, CPU ms of this process, 4×4 pose source → target; the identity when it failed)."""
        t0, c0 = time.perf_counter(), time.process_time()
        src, dst = (self.odometry.prepare(d, g) for d, g in self.inputs)
        _, Rt = self.odometry.compute(src, dst)
        return 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0), Rt.tolist()

    def close(self) -> None:
        pass


def opencv_pair(depth_s, depth_t, K, depth_max, kind, color_s=None, color_t=None) -> "OpenCVPair | None":
    try:
        return OpenCVPair(depth_s, depth_t, K, depth_max, kind, color_s, color_t)
    except (ImportError, AttributeError):
        return None


# -- the benchmark ------------------------------------------------------------------------------------
def load_pair(args, cfg):
    """(source depth, target depth, intrinsics, reference pose or None, description)."""
    import numpy as np

    from ti_fusion.config import DatasetConfig, SynthConfig
    from ti_fusion.geometry import invert, make_pose, so3_exp

    if args.data and not Path(args.data).is_dir():
        raise SystemExit(f"bench_icp: {args.data}: not a folder")
    data = Path(args.data) if args.data else DEFAULT_DATA
    if data.is_dir():
        from ti_fusion.io.datasets import open_dataset

        dataset = open_dataset(DatasetConfig(path=str(data), depth_max=cfg.dataset.depth_max))
        s, t = (dataset.frame_by_raw_index(i) for i in args.pair)
        reference = invert(t.gt_pose) @ s.gt_pose if s.gt_pose is not None and t.gt_pose is not None else None
        return s.depth, t.depth, s.intrinsics, reference, f"{data.name} frames {args.pair[0]} → {args.pair[1]}"
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig())
    G = make_pose(so3_exp(np.radians(3.0) * np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])),
                  [0.03, -0.02, 0.035])
    pose = seq.poses[40]
    depth_s, _ = seq.render(pose, seed=1)
    depth_t, _ = seq.render(pose @ invert(G), seed=2)
    return depth_s, depth_t, seq.intrinsics, G, "synthetic room, 3° and 5 cm apart (no redkitchen data found)"


WARMUP_RUNS = 5  # untimed frame pairs of each system before the timed ones
RUNS_PER_BLOCK = 5  # timed frame pairs per block (see bench_resolution)
SWITCH_SETTLE_S = 0.2  # pause between blocks of one system and the other
ITERATIONS_PER_RUN = 5  # Taichi iterations timed back to back, as within one pyramid level of ICP


def timed(fn, repeats: int = 1) -> tuple[float, float]:
    """(wall ms, CPU ms of this process) per call, averaged over ``repeats`` calls."""
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        fn()
    return 1e3 * (time.perf_counter() - t0) / repeats, 1e3 * (time.process_time() - c0) / repeats


def compute_maps(src, tgt, depth_s, depth_t, K, icp_cfg) -> None:
    """The source and target ``FramePyramid`` of a pair, as the pipeline computes them for ICP."""
    for pyramid, depth in ((src, depth_s), (tgt, depth_t)):
        pyramid.compute(depth, K)


class FinestIteration:
    """One ICP iteration at the finest level of a pair, from ``pose`` (the converged pose: the association
    of the last iterations), as each system runs it. ``taichi()``: as ``ICP.align`` runs it here (on the
    CPU one launch that also solves and updates the pose, ``PointToPlane.iterate``; on float32 backends
    the sums and a NumPy solve), after ``start()``, which goes back to ``pose`` (``iterate`` moves it, by
    little there). ``numpy()``: ``icp_numpy.LevelIteration`` and the NumPy solve."""

    def __init__(self, icp, src, tgt, pose):
        from ti_fusion.reference import icp as icp_numpy

        c = icp.config
        self.icp, self.pose = icp, pose
        self.fields = (src.vertex[0], src.normal[0], tgt.vertex[0], tgt.normal[0])
        self.K = tgt.intrinsics[0].as_tuple()
        self.thresholds = (icp.dist_threshold(0), c.normal_threshold_deg)
        self.terms = [icp.terms[0].kernel_pass(src, tgt, 0)]  # the geometric term, as ICP.align runs it
        self.kernels = icp._kernels(src.shapes[0][0] * src.shapes[0][1])
        self.in_kernel = self.kernels.solves_in_kernel  # as ICP.align decides
        self.numpy_level = icp_numpy.LevelIteration(*(f.to_numpy() for f in self.fields), self.K, *self.thresholds,
                                                    icp.terms[0].robust, c.robust_scale)

    def start(self) -> None:
        if self.in_kernel:
            self.kernels.begin_iterations(self.pose, ITERATIONS_PER_RUN + 1)
            self.kernels.begin_level(*self.fields, self.K, *self.thresholds, 0, self.icp.config.min_inliers, 0.0,
                                     self.terms)

    def taichi(self):
        if self.in_kernel:
            return self.kernels.iterate(0)
        return self._solve(self.kernels.reduce(*self.fields, self.pose, self.K, *self.thresholds, self.terms))

    def numpy(self):
        return self._solve(self.numpy_level.sums(self.pose))

    def taichi_delta(self):
        """δξ of one Taichi iteration from ``pose`` (for the agreement check, not timed)."""
        from ti_fusion.geometry import invert, se3_log

        self.start()
        if not self.in_kernel:
            return self.taichi()
        self.taichi()
        return se3_log(self.kernels.pose() @ invert(self.pose))

    @staticmethod
    def _solve(sums):
        from ti_fusion.kernels.icp import unpack_sums
        from ti_fusion.tracking.solve import solve_normal_equations

        s = unpack_sums(sums)
        return solve_normal_equations(s["AtA"], s["Atb"])


def _peer_block(peer, times: list) -> np.ndarray:
    """One block of a peer's frame pairs: the pause, one untimed run, then RUNS_PER_BLOCK timed ones whose
    (ms, CPU ms) go to ``times``; the last run's pose."""
    time.sleep(SWITCH_SETTLE_S)
    peer.run()
    for _ in range(RUNS_PER_BLOCK):
        ms, cpu, pose = peer.run()
        times.append((ms, cpu))
    return pose


def bench_resolution(depth_s, depth_t, K, reference, cfg, args) -> dict:
    import numpy as np

    from ti_fusion.geometry import pose_error
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.pyramid import FramePyramid

    c = cfg.icp
    levels = len(c.iterations)
    src, tgt = (FramePyramid(cfg.pyramid, K.height, K.width, levels) for _ in range(2))
    icp = ICP(c)

    def frame_pair():
        compute_maps(src, tgt, depth_s, depth_t, K, c)
        return icp.align(src, tgt)

    for _ in range(WARMUP_RUNS):  # the first compiles every kernel; the next few were still ~20% slower
        result = frame_pair()
    o3d = open3d_runner(depth_s, depth_t, K, list(c.iterations), cfg.dataset.depth_max, args.open3d_python)
    cv = opencv_pair(depth_s, depth_t, K, cfg.dataset.depth_max, args.opencv_odometry)
    ours, theirs, o3d_pose, cv_times, cv_pose = [], [], None, [], None
    for peer in (o3d, cv):
        for _ in range(WARMUP_RUNS if peer is not None else 0):
            peer.run()
    # Each system runs in blocks of back-to-back frame pairs (its threads stay awake, as when processing a
    # sequence), the first of each block untimed; blocks alternate with a pause between them, so that
    # neither is timed while the other's threads still spin (OpenMP's do, for a while after each call).
    for _ in range(max(1, args.repeats // RUNS_PER_BLOCK)):
        time.sleep(SWITCH_SETTLE_S)
        frame_pair()
        ours.extend(timed(frame_pair) for _ in range(RUNS_PER_BLOCK))
        if o3d is not None:
            o3d_pose = _peer_block(o3d, theirs)
        if cv is not None:
            cv_pose = _peer_block(cv, cv_times)
    result = frame_pair()
    if o3d is not None:
        o3d.close()

    one = FinestIteration(icp, src, tgt, result.pose)
    one.start()
    one.taichi()
    one.numpy()
    ti_t, np_t = [], []
    for _ in range(max(3, args.repeats // 2)):  # alternate, as above; each after one untimed call
        one.numpy()
        np_t.append(timed(one.numpy, 1))
        # NumPy's matrix products wake OpenBLAS's worker threads, which then spin for tens of ms (measured
        # here: 12 ms of CPU in a 10 ms sleep right after one): timed in that window, Taichi's threads
        # share the cores with them and one iteration took twice as long. Wait until they sleep again.
        time.sleep(BLAS_SETTLE_S)
        one.start()
        one.taichi()
        one.start()
        ti_t.append(timed(one.taichi, ITERATIONS_PER_RUN))
    (ms_taichi, cpu_taichi), (ms_numpy, cpu_numpy) = np.median(ti_t, axis=0), np.median(np_t, axis=0)
    delta_t, delta_n = one.taichi_delta(), one.numpy()
    out = {
        "resolution": f"{K.width}x{K.height}",
        "iteration_ms": {"taichi": ms_taichi, "numpy": ms_numpy, "ratio": ms_numpy / ms_taichi},
        "iteration_cpu_ms": {"taichi": cpu_taichi, "numpy": cpu_numpy, "ratio": cpu_numpy / cpu_taichi},
        "iteration_delta_agreement": float(np.abs(delta_t - delta_n).max()),
        "frame_ms": {"taichi": float(np.median([t[0] for t in ours]))},
        "frame_cpu_ms": {"taichi": float(np.median([t[1] for t in ours]))},
        "taichi_error": pose_error(result.pose, reference) if reference is not None else None,
        "taichi_failure": result.failure,
    }
    if o3d is not None:
        for key, i in (("frame_ms", 0), ("frame_cpu_ms", 1)):
            out[key]["open3d"] = float(np.median([t[i] for t in theirs]))
            out[key]["ratio"] = out[key]["open3d"] / out[key]["taichi"]
        out["open3d_version"] = o3d.version
        out["open3d_error"] = pose_error(np.asarray(o3d_pose), reference) if reference is not None else None
    if cv is not None:
        for key, i in (("frame_ms", 0), ("frame_cpu_ms", 1)):
            out[key]["opencv"] = float(np.median([t[i] for t in cv_times]))
            out[key]["opencv_ratio"] = out[key]["opencv"] / out[key]["taichi"]
        out["opencv_version"], out["opencv_api"] = cv.version, cv.api
        out["opencv_error"] = pose_error(np.asarray(cv_pose), reference) if reference is not None else None
    return out


def accuracy_over_pairs(cfg, args) -> dict | None:
    """Pose error of ours and of Open3D (once each, from the identity, 640×480) on ``--accuracy-pairs``
    frame pairs ``--accuracy-gap`` frames apart, spread over the sequence: one pair is too few to rank
    two methods whose errors are this close to the reference's own error (about 1 cm)."""
    import numpy as np

    from ti_fusion.config import DatasetConfig
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.geometry import invert, pose_error
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.pyramid import FramePyramid

    data = Path(args.data) if args.data else DEFAULT_DATA
    if args.accuracy_pairs <= 0 or not data.is_dir():
        return None
    dataset = open_dataset(DatasetConfig(path=str(data), depth_max=cfg.dataset.depth_max))
    gap = args.accuracy_gap
    starts = np.linspace(0, len(dataset) - 1 - gap, args.accuracy_pairs).round().astype(int)
    c = cfg.icp
    K = dataset[0].intrinsics
    src, tgt = (FramePyramid(cfg.pyramid, K.height, K.width, len(c.iterations)) for _ in range(2))
    icp = ICP(c)
    ours, theirs, cv_errors = [], [], []
    for s in starts:
        a, b = dataset[int(s)], dataset[int(s) + gap]
        reference = invert(b.gt_pose) @ a.gt_pose
        for pyramid, depth in ((src, a.depth), (tgt, b.depth)):
            pyramid.compute(depth, K)
        ours.append(pose_error(icp.align(src, tgt).pose, reference))
        o3d = open3d_runner(a.depth, b.depth, K, list(c.iterations), cfg.dataset.depth_max, args.open3d_python)
        if o3d is not None:
            theirs.append(pose_error(np.asarray(o3d.run()[2]), reference))
            o3d.close()
        cv = opencv_pair(a.depth, b.depth, K, cfg.dataset.depth_max, args.opencv_odometry, a.color, b.color)
        if cv is not None:
            cv_errors.append(pose_error(np.asarray(cv.run()[2]), reference))
    out = {"pairs": len(starts), "gap": gap, "ours": np.asarray(ours).tolist()}
    if theirs:
        out["open3d"] = np.asarray(theirs).tolist()
    if cv_errors:
        out["opencv"] = np.asarray(cv_errors).tolist()
    return out


def print_accuracy(acc: dict) -> None:
    import numpy as np

    print(f"\npose error vs reference over {acc['pairs']} pairs {acc['gap']} frames apart, 640x480, from the identity")
    print(f"{'':>9} | {'median':>16} {'mean':>16} {'max':>16}")
    for name in ("ours", "open3d", "opencv"):
        if name not in acc:
            continue
        e = np.asarray(acc[name])
        cells = [f"{f(e[:, 0]):.2f}° {1e3 * f(e[:, 1]):5.1f} mm" for f in (np.median, np.mean, np.max)]
        print(f"{name:>9} | " + " ".join(f"{c:>16}" for c in cells))
    for peer in ("open3d", "opencv"):
        if peer in acc:
            o, t = np.asarray(acc["ours"]), np.asarray(acc[peer])
            print(f"ours is nearer the reference than {peer} on {(o[:, 1] < t[:, 1]).sum()} of {len(o)} pairs in "
                  f"translation, {(o[:, 0] < t[:, 0]).sum()} in rotation")


def photometric_cost(cfg, args) -> dict:
    """ms per frame of the photometric term (see the module docstring): medians of alternated runs."""
    import dataclasses

    import numpy as np

    from ti_fusion.config import SynthConfig
    from ti_fusion.geometry import invert, make_pose, so3_exp
    from ti_fusion.kernels.pyramid import FramePyramid, grey_image
    from ti_fusion.synthetic.scene import SyntheticSequence
    from ti_fusion.tracking.icp import ICP

    seq = SyntheticSequence(SynthConfig())
    pose, G = seq.poses[40], make_pose(so3_exp(np.radians([1.0, -0.5, 0.5])), [0.01, -0.01, 0.01])
    (ds, cs), (dt, ct) = seq.render(pose, seed=1), seq.render(pose @ invert(G), seed=2)
    K, levels = seq.intrinsics, len(cfg.icp.iterations)
    src, tgt = (FramePyramid(cfg.pyramid, K.height, K.width, levels, input_level=1) for _ in range(2))
    src.compute(ds, K)
    tgt.compute(dt, K)
    depth_only = ICP(dataclasses.replace(cfg.icp, color_weight=0.0))
    joint = ICP(dataclasses.replace(cfg.icp, color_weight=cfg.icp.color_weight or 0.01))

    def intensity():
        src.compute_intensity(grey_image(cs))  # (stands in for the model's gather, a cheaper kernel)
        tgt.compute_intensity(grey_image(ct))

    runs = {"intensity": intensity, "icp_depth_only": lambda: depth_only.align(src, tgt),
            "icp_joint": lambda: joint.align(src, tgt, terms=("photometric",))}
    times: dict = {k: [] for k in runs}
    for _ in range(3):  # compile and warm up
        for fn in runs.values():
            fn()
    for _ in range(max(3, args.repeats)):
        for key, fn in runs.items():
            times[key].append(timed(fn)[0])
    out = {k: float(np.median(v)) for k, v in times.items()}
    out["term_per_frame"] = out["intensity"] + out["icp_joint"] - out["icp_depth_only"]
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="?", default="", help="7-Scenes folder (default: ../shared/data/redkitchen-7scenes)")
    parser.add_argument("--pair", nargs=2, type=int, default=[100, 110], metavar=("S", "T"))
    parser.add_argument("--repeats", type=int, default=20, help="timed runs per measurement (median)")
    parser.add_argument("--open3d-python", default=None, metavar="PY",
                        help="an interpreter with open3d installed, when this one has none")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    parser.add_argument("--accuracy-pairs", type=int, default=25,
                        help="frame pairs for the accuracy table (0: skip); real data only")
    parser.add_argument("--accuracy-gap", type=int, default=10, help="frames between the two of a pair")
    parser.add_argument("--photometric", type=int, default=1, help="0: skip the photometric term's cost")
    parser.add_argument("--opencv-odometry", default="depth", choices=OpenCVOdometry.KINDS,
                        help="which of OpenCV's odometries (depth: point-to-plane ICP)")
    parser.add_argument("--open3d-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    kept = keep_freed_memory()  # NumPy (and Open3D) at their best: see keep_freed_memory
    if args.open3d_worker:
        _worker(args.open3d_worker)
        return 0

    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
    from ti_fusion.backend import init_backend
    from ti_fusion.config import load_config

    cfg = load_config(None, args.set)
    backend = init_backend("cpu")
    depth_s, depth_t, K, reference, what = load_pair(args, cfg)
    print(f"ICP benchmark: {what}; backend {backend.arch}, {os.cpu_count()} CPUs; iterations {cfg.icp.iterations} "
          f"(coarse → fine), depth smoothing r = {cfg.pyramid.smooth_radius(K.width)} at {K.width} px (half at half); medians of {args.repeats}+ runs; "
          f"{numpy_conditions(kept)}")
    rows = []
    for f in (1, 2):
        Kf = K.downsampled(f)
        rows.append(bench_resolution(depth_s[::f, ::f].copy(), depth_t[::f, ::f].copy(), Kf, reference, cfg, args))

    def err(e):
        return f"{e[0]:.2f}° {1e3 * e[1]:.1f} mm" if e is not None else "-"

    for title, it_key, fr_key in (("wall-clock", "iteration_ms", "frame_ms"),
                                  ("CPU time of each process (all its threads)", "iteration_cpu_ms", "frame_cpu_ms")):
        print(f"\n{title}")
        print(f"{'':>9} | {'one ICP iteration, finest level (ms)':^36} | {'one frame pair: pyramid + ICP (ms)':^57} | "
              f"{'error vs reference':^44}")
        print(f"{'':>9} | {'Taichi':>10} {'NumPy':>10} {'NumPy/Ti':>12} | {'Taichi':>10} {'Open3D':>10} "
              f"{'O3D/Ti':>11} {'OpenCV':>10} {'CV/Ti':>11} | {'Taichi':>14} {'Open3D':>14} {'OpenCV':>14}")
        for r in rows:
            it, fr = r[it_key], r[fr_key]
            o3d_ms = f"{fr['open3d']:10.1f}" if "open3d" in fr else f"{'skipped':>10}"
            o3d_ratio = f"{fr['ratio']:10.2f}×" if "ratio" in fr else f"{'-':>11}"
            cv_ms = f"{fr['opencv']:10.1f}" if "opencv" in fr else f"{'skipped':>10}"
            cv_ratio = f"{fr['opencv_ratio']:10.2f}×" if "opencv_ratio" in fr else f"{'-':>11}"
            print(f"{r['resolution']:>9} | {it['taichi']:10.2f} {it['numpy']:10.1f} {it['ratio']:11.1f}× | "
                  f"{fr['taichi']:10.1f} {o3d_ms} {o3d_ratio} {cv_ms} {cv_ratio} | {err(r['taichi_error']):>14} "
                  f"{err(r.get('open3d_error')) if 'open3d' in fr else '-':>14} "
                  f"{err(r.get('opencv_error')) if 'opencv' in fr else '-':>14}")
    if "open3d" not in rows[0]["frame_ms"]:
        print("Open3D: not installed here (pip install open3d-cpu, or --open3d-python PY): skipped")
    else:
        print(f"Open3D {rows[0]['open3d_version']}: rgbd_odometry_multi_scale, Method.PointToPlane, its default loss "
              "parameters (depth_outlier_trunc 0.07, depth_huber_delta 0.05)")
    if "opencv" in rows[0]["frame_ms"]:
        print(f"{rows[0]['opencv_version']} through {rows[0]['opencv_api']}: its own settings (4 levels, 7, 7, 7, 10 "
              "iterations from the finest), prepareFrame of both frames + compute")
    else:
        print("OpenCV: this cv2 has no RGB-D odometry (OpenCV 5's cv2.Odometry or OpenCV 4 contrib's cv2.rgbd): skipped")
    accuracy = accuracy_over_pairs(cfg, args)
    if accuracy is not None:
        print_accuracy(accuracy)
    photometric = photometric_cost(cfg, args) if args.photometric else None
    if photometric is not None:
        p = photometric
        print(f"\nphotometric term, synthetic room tracked at 320x240 (ms per frame, wall-clock): intensity pyramids "
              f"{p['intensity']:.2f}, ICP depth only {p['icp_depth_only']:.2f}, joint {p['icp_joint']:.2f}; "
              f"the term costs {p['term_per_frame']:.2f} ms per frame")
    if args.json:
        Path(args.json).write_text(json.dumps({"data": what, "rows": rows, "accuracy": accuracy,
                                               "photometric": photometric}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
