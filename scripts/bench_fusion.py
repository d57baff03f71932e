#!/usr/bin/env python
"""Milliseconds per fusion step with a ~1 M-surfel map: Taichi kernels against vectorised NumPy.

    .venv/bin/python scripts/bench_fusion.py [--arch cpu] [--surfels 1000000] [--steps 10] [--sizes 320x240,640x480]

For each resolution: fuse frames of the synthetic sequence (noise on) with the Taichi mapper until the
map holds ``--surfels`` surfels, copy that map into a NumPy implementation of the same step
(``ti_fusion.reference.fusion.NumpyFusion``: project with filter passes 1 and 2 in Keller's order,
the nearest-depth index map, merge, add with the covered-pixel test,
remove, with the same thresholds), then run the next ``--steps`` frames through both, each on its own
copy, and print the median milliseconds per stage and the ratio, measured in the same run. The first
Taichi step of each size (kernel compilation) is not timed, and each Taichi step starts 0.2 s after the
NumPy one, once OpenBLAS's threads have stopped spinning. Freed memory is kept for reuse
(``benchlib.keep_freed_memory``) so that NumPy's large temporaries do not page-fault afresh at every step.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchlib import BLAS_SETTLE_S, keep_freed_memory, numpy_conditions

STAGES = ("project", "merge", "add", "remove")


def bench_size(width: int, height: int, target: int, steps: int) -> dict:
    from ti_fusion.config import FusionConfig
    from ti_fusion.reference.fusion import NumpyFusion, build_map
    from ti_fusion.timing import StageTimer

    cfg = FusionConfig(level=0)  # the step at this resolution (the SLAM default fuses 640×480 input at 320×240)
    mapper, pyramid, seq, frame = build_map(width, height, target, cfg)
    print(f"  {width}×{height}: map of {mapper.count:,} surfels after {frame} frames", flush=True)
    K = seq.intrinsics
    ref = NumpyFusion(mapper.to_numpy(), cfg, capacity=mapper.map.capacity)
    timer = StageTimer()
    numpy_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    counts = []
    for k in range(steps + 1):
        i = frame + k
        depth, color = seq.frame(i)
        pyramid.compute(depth, K)
        stats = mapper.integrate(pyramid, color, seq.poses[i], frame + k, timer)
        ms = ref.integrate(pyramid.vertex[0].to_numpy(), pyramid.normal[0].to_numpy(), depth, color, seq.poses[i], K,
                           frame + k)
        time.sleep(BLAS_SETTLE_S)  # OpenBLAS's threads asleep before the next Taichi step
        if k > 0:  # the first Taichi step compiles the kernels
            for s in STAGES:
                numpy_ms[s].append(ms[s])
        counts.append((stats.surfels, ref.n))
    taichi = timer.summary(skip_first=1)
    row = {"size": f"{width}×{height}", "surfels": counts[0][0],
           "taichi": {s: taichi[s]["median"] for s in STAGES},
           "numpy": {s: float(np.median(numpy_ms[s])) for s in STAGES},
           "final_counts": counts[-1]}
    row["taichi"]["step"] = sum(row["taichi"][s] for s in STAGES)
    row["numpy"]["step"] = sum(row["numpy"][s] for s in STAGES)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    parser.add_argument("--arch", default="cpu", help="Taichi backend: cpu | vulkan | cuda | auto")
    parser.add_argument("--surfels", type=int, default=1_000_000, help="map size before the timed steps")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per size (after one warm-up)")
    parser.add_argument("--sizes", default="320x240,640x480", help="comma-separated WxH")
    args = parser.parse_args()
    kept = keep_freed_memory()  # NumPy at its best: see keep_freed_memory

    from ti_fusion.backend import init_backend

    backend = init_backend(args.arch)
    print(f"backend: {backend.arch}; map ≈ {args.surfels:,} surfels; {args.steps} timed steps per size; "
          f"{numpy_conditions(kept)}", flush=True)
    rows = []
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.lower().split("x"))
        rows.append(bench_size(w, h, args.surfels, args.steps))

    cols = (*STAGES, "step")
    print()
    print(f"{'size':<9} {'surfels':>9}  {'impl':<7}" + "".join(f"{c:>9}" for c in cols))
    for r in rows:
        print(f"{r['size']:<9} {r['surfels']:>9,}  {'taichi':<7}" + "".join(f"{r['taichi'][c]:9.2f}" for c in cols))
        print(f"{'':<9} {'':>9}  {'numpy':<7}" + "".join(f"{r['numpy'][c]:9.2f}" for c in cols))
        print(f"{'':<9} {'':>9}  {'ratio':<7}" + "".join(
            f"{r['numpy'][c] / r['taichi'][c]:8.1f}×" if r["taichi"][c] >= 0.05 else f"{'-':>9}" for c in cols))
        t, n = r["final_counts"]
        print(f"{'':<9} surfels after the timed steps: taichi {t:,}, numpy {n:,}")
    print("\nms per stage: median over the timed steps (Taichi stages synchronised with ti.sync()).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
