#!/usr/bin/env python3
"""Where a frame's kernel time goes, task by task: Taichi's kernel profiler over a dataset's frames, and the
fastest of repeated runs of each stage on the map the frames built.

    python scripts/bench_kernel_tasks.py [DATA] [--frames N] [--repeat R] [--top K]

DATA: a dataset folder (default: redkitchen at ../shared/data/redkitchen-7scenes). ``DenseSLAM.register_frame``
runs on frames 0 .. N-1 with ``ti.init(kernel_profiler=True)``; the profiler's records (one per parallel or
serial loop of a launch) are summed by task (``render_kernel_9_range_for``: the render's 10th loop) over the
frames after the first two (kernel compilation), and printed per frame, largest first, with launches per
frame. Those times move with the machine's load (a loop waits for both worker threads). Then, on the map as
the last frame left it, each stage of a frame runs ``--repeat`` times in a frame's order (the frame's maps,
the model prediction, ICP from the motion model's guess as tracking starts it, the fusion step's association
at the pose it found) and every task's
fastest run is printed: on a shared machine the fastest run is the one that had the cores, the number to
compare between two versions of a kernel. ICP's iterations are split by pyramid level (the profiler's
records of ``iterate`` in launch order).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"
WARMUP = 2
INSTANCE = re.compile(r"_c\d+_\d+")  # iterate_c94_0_kernel_2_range_for -> iterate_kernel_2_range_for


def _records():
    from taichi.lang import impl

    return [(INSTANCE.sub("", r.name), r.kernel_time) for r in impl.get_runtime().prog.get_kernel_profiler_records()]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA), help="a dataset folder")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=30, help="runs of each stage on the final map (0: none)")
    parser.add_argument("--top", type=int, default=30, help="tasks printed from the frames' profile")
    args = parser.parse_args(argv)
    if args.frames < WARMUP + 1:
        print(f"bench_kernel_tasks.py: --frames {args.frames}: give at least {WARMUP + 1}", file=sys.stderr)
        return 2
    if args.repeat < 0:
        print(f"bench_kernel_tasks.py: --repeat {args.repeat}: give at least 0", file=sys.stderr)
        return 2
    if not Path(args.data).is_dir():
        print(f"bench_kernel_tasks.py: {args.data}: not a folder (give a dataset folder)", file=sys.stderr)
        return 2

    import taichi as ti

    from ti_fusion.backend import init_backend
    from ti_fusion.config import load_config
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.kernels import icp as icp_kernels

    init_backend("cpu", kernel_profiler=True)
    cfg = load_config(None, [])
    cfg.dataset.path, cfg.dataset.stop, cfg.log.progress = args.data, args.frames, False
    dataset = open_dataset(cfg.dataset, cfg.synth)
    from ti_fusion.slam.dense import DenseSLAM

    slam = DenseSLAM(cfg, dataset.intrinsics)
    by_task, launches, timed, frame = {}, {}, 0, None
    for i in range(len(dataset) - 1):  # the last frame is the stages' frame below
        frame = dataset[i]
        ti.profiler.clear_kernel_profiler_info()
        slam.register_frame(frame)
        ti.sync()
        if i >= WARMUP:
            timed += 1
            for name, ms in _records():
                by_task[name] = by_task.get(name, 0.0) + ms
                launches[name] = launches.get(name, 0) + 1
    print(f"bench_kernel_tasks.py {Path(args.data).name} --frames {args.frames}: frames {WARMUP}-{len(dataset) - 2}, "
          f"{slam.mapper.count} surfels at the end; kernel ms per frame {sum(by_task.values()) / timed:.3f}")
    print("| ms per frame | launches per frame | task |\n|---|---|---|")
    for name, ms in sorted(by_task.items(), key=lambda kv: -kv[1])[:args.top]:
        print(f"| {ms / timed:.3f} | {launches[name] / timed:.2f} | {name} |")
    if args.repeat == 0:
        return 0

    frame = dataset[len(dataset) - 1]
    level = slam.mapper.frame_level(slam.frame_pyramid)
    pyramid, mapper, K = slam.frame_pyramid, slam.mapper, slam.model_intrinsics
    from ti_fusion.geometry import invert, renormalize

    last, guess = slam._held_pose(), slam._predicted_pose(frame.timestamp)
    init = invert(guess) @ last  # as DenseSLAM's tracking: the prediction's camera (at ``last``) into the frame's
    pyramid.compute(frame.depth, frame.intrinsics, None, frame.color, level)
    slam._reference(False)
    aligned = slam.icp.align(slam.model_pyramid, pyramid, init=init)
    pose = guess if aligned.failure else renormalize(last @ invert(aligned.pose))  # the frame's, for the association
    levels = []  # ICP level of each ``iterate`` launch, in order
    iterate = icp_kernels.PointToPlane.iterate

    def logged(self, iteration, lv=None):
        levels.append(self._level if lv is None else lv)
        return iterate(self, iteration, lv)

    icp_kernels.PointToPlane.iterate = logged
    stages = [("maps", lambda: pyramid.compute(frame.depth, frame.intrinsics, None, frame.color, level)),
              ("render", lambda: slam._reference(False)),
              ("icp", lambda: slam.icp.align(slam.model_pyramid, pyramid, init=init)),
              ("associate", lambda: mapper.map.associate_compatible(
                  pose, K, pyramid.vertex[level], pyramid.normal[level], mapper.config.dist_threshold,
                  mapper.config.normal_threshold_deg))]
    fastest = {}
    for _ in range(args.repeat):
        for stage, run in stages:
            levels.clear()
            ti.profiler.clear_kernel_profiler_info()
            t0 = time.perf_counter()
            run()
            ti.sync()
            wall = (time.perf_counter() - t0) * 1e3
            runs: dict[str, float] = {}
            its = iter(levels)
            for name, ms in _records():
                if stage == "icp" and name.startswith("iterate") and "_kernel_1_" in name:
                    name = f"{name} (level {next(its)}, per iteration)"
                runs[name] = min(runs.get(name, ms), ms) if "per iteration" in name else runs.get(name, 0.0) + ms
            runs["(the stage's wall ms)"] = wall
            for name, ms in runs.items():
                key = (stage, name)
                fastest[key] = min(fastest.get(key, ms), ms)
    icp_kernels.PointToPlane.iterate = iterate
    print(f"\nthe fastest of {args.repeat} runs of each stage on that map (frame {len(dataset) - 1}; ICP from the motion "
          f"model's guess: {len(aligned.iterations)} iterations, {aligned.failure or 'no failure'}):")
    print("| stage | task | fastest ms |\n|---|---|---|")
    for (stage, name), ms in fastest.items():
        if ms >= 0.01:
            print(f"| {stage} | {name} | {ms:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
