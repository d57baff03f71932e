#!/usr/bin/env python3
"""Milliseconds per stage on every available Taichi backend, one table, measured in one run.

    python scripts/bench_backends.py [--width 640 --height 480] [--repeats 20] [--data DIR]

Taichi runs one backend per process, so each backend is measured in a child process of this script on
the same frames (the synthetic sequence, or ``--data`` such as ../shared/data/redkitchen-7scenes), and the
parent prints the table with each backend's ratio to cpu. Stages: frame maps (pyramid, vertex and
normal maps), one ICP iteration (association + linearisation + reduction + 6×6 solve, at the finest
level), one fusion step (project, filter, merge, add, remove) into a map of ``--frames`` fused frames,
and rendering the model prediction for tracking. Compilation is excluded (warm-up runs first).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

STAGES = ("pyramid", "icp_iteration", "fusion_step", "render")


def _time(fn, repeats: int) -> float:
    import taichi as ti

    fn()
    ti.sync()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ti.sync()
        samples.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(samples))


def worker(args) -> dict:
    from ti_fusion.backend import init_backend
    from ti_fusion.config import Config, PyramidConfig
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.errors import BackendUnavailable
    from ti_fusion.mapping.mapper import SurfelMapper
    from ti_fusion.geometry import invert
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.pyramid import FramePyramid

    try:
        info = init_backend(args.worker)
    except BackendUnavailable as exc:
        return {"arch": args.worker, "error": str(exc)}
    cfg = Config()
    cfg.dataset.path = args.data or ""
    cfg.synth.width, cfg.synth.height, cfg.synth.fx = args.width, args.height, 525.0 * args.width / 640
    cfg.dataset.downsample = 1 if not args.data else 640 // args.width
    cfg.dataset.stop = args.frames + 1
    dataset = open_dataset(cfg.dataset, cfg.synth)
    K = dataset.intrinsics
    frames = [dataset[i] for i in range(len(dataset))]
    raw = PyramidConfig(depth_smooth_radius=0)
    source, target = FramePyramid(raw, K.height, K.width, 3), FramePyramid(raw, K.height, K.width, 3)
    source.compute(frames[0].depth, K)
    target.compute(frames[1].depth, K)

    ms = {"pyramid": _time(lambda: target.compute(frames[1].depth, K), args.repeats)}

    cfg.icp.iterations = [0, 0, 10]
    cfg.icp.stop_update = 0.0
    icp = ICP(cfg.icp)
    init = invert(frames[1].gt_pose) @ frames[0].gt_pose
    ms["icp_iteration"] = _time(lambda: icp.align(source, target, init), max(2, args.repeats // 4)) / 10

    cfg.fusion.level = 0  # the kernels at this resolution, whatever level the SLAM default fuses at
    mapper = SurfelMapper(cfg.fusion)
    pyramid = FramePyramid(raw, K.height, K.width, 1)
    for i, frame in enumerate(frames[:-1]):
        pyramid.compute(frame.depth, K)
        mapper.integrate(pyramid, frame.color, frame.gt_pose, i)
    last = frames[-1]
    pyramid.compute(last.depth, K)
    step = [len(frames)]

    def fuse():
        mapper.integrate(pyramid, last.color, last.gt_pose, step[0])
        step[0] += 1

    ms["fusion_step"] = _time(fuse, args.repeats)
    prediction = FramePyramid(raw, K.height, K.width, 3)
    ms["render"] = _time(lambda: mapper.render_pyramid(prediction, last.gt_pose, K), args.repeats)
    return {"arch": info.arch, "ms": ms, "surfels": mapper.count, "size": f"{K.width}x{K.height}"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--frames", type=int, default=10, help="frames fused before timing the fusion step")
    parser.add_argument("--data", default="", help="dataset folder (default: the synthetic sequence)")
    parser.add_argument("--archs", default="cpu,vulkan,cuda")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print("RESULT " + json.dumps(worker(args)), flush=True)
        return 0

    rows = []
    for arch in args.archs.split(","):
        cmd = [sys.executable, __file__, "--worker", arch, "--width", str(args.width), "--height",
               str(args.height), "--repeats", str(args.repeats), "--frames", str(args.frames), "--data", args.data]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        if not lines:
            rows.append({"arch": arch, "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]})
        else:
            rows.append(json.loads(lines[-1][len("RESULT "):]))
    cpu = next((r for r in rows if r.get("arch") == "cpu" and "ms" in r), None)
    print(f"ms per stage at {args.width}x{args.height} (median of {args.repeats}; ratio = cpu / backend)")
    print(f"{'backend':<8} " + " ".join(f"{s:>20}" for s in STAGES))
    for r in rows:
        if "ms" not in r:
            print(f"{r['arch']:<8} unavailable: {r['error']}")
            continue
        cells = []
        for s in STAGES:
            ratio = f" ({cpu['ms'][s] / r['ms'][s]:.2f}x)" if cpu else ""
            cells.append(f"{r['ms'][s]:.2f}{ratio}".rjust(20))
        print(f"{r['arch']:<8} " + " ".join(cells))
    if cpu:
        print(f"(fusion step into a map of {cpu['surfels']} surfels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
