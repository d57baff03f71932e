#!/usr/bin/env python
"""How far can one fusion step go on this machine? The Taichi kernels, the NumPy step of
``bench_fusion.py`` and the same step in plain C, on the same map and frame, in one run.

    .venv/bin/python scripts/bench_fusion_ceiling.py [--surfels 1000000] [--repeats 10] [--sizes 320x240,640x480] [--cc cc]

For each size it builds a map of about ``--surfels`` surfels along the synthetic sequence (as
``bench_fusion.py``), then times one step (the next frame, ground-truth pose, the default FusionConfig)
``--repeats`` times, each on a fresh copy of the map, for
- Taichi: ``SurfelMapper.integrate`` on the machine's cores;
- NumPy: ``ti_fusion.reference.fusion.NumpyFusion.integrate``, the baseline of ``bench_fusion.py``;
- C: ``scripts/fusion_step.c``, the same step on one thread, built as ``bench_icp_ceiling.py`` builds
  its C (``-O3`` and the floating-point freedoms of Taichi's kernels), for ``-march=x86-64`` (SSE2, no
  FMA: a point of comparison, not Taichi's code; Taichi 1.7.4 here emits AVX/AVX-512 encodings, but no
  FMA and little wide vectorisation, see docs/PERFORMANCE.md) and ``-march=native``.
Each is timed at its best (the fastest of the repeats). "C native ÷ 2" is the time a perfect two-thread
split of the native step would take, with no thread start-up: a bound on how far NumPy's ratio could go
with the code this compiler makes of this (scalar, interleaved-array) C source, e.g. against a 20×
target. The script stops if C's step does not merge, add, cover and remove as many surfels
as the kernels' (it would be timing a different computation) and reports how many of the resulting
surfels match the kernels' to 1e-4.

Needs a C compiler (``--cc``, default ``cc``); without one the C columns are skipped.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# The sibling scripts (bench_icp_ceiling, benchlib) are imported in the functions that use them: the tests
# load this file alone, for the C program's inputs and outputs

C_SOURCE = Path(__file__).resolve().parent / "fusion_step.c"


def check_config(cfg) -> None:
    """fusion_step.c implements the default step only."""
    if (cfg.confidence_weighting, cfg.depth_weighting, cfg.skip_covered, cfg.remove_unstable,
            cfg.remove_free_space) != (True, False, True, True, False):
        raise SystemExit("bench_fusion_ceiling: the C step implements the default fusion settings only")


def write_inputs(workdir: Path, data: dict, pyramid, rgb, pose, K, frame: int, cfg, radial) -> None:
    """The C program's inputs (see scripts/fusion_step.c)."""
    from ti_fusion.kernels.common import camera_to_world, world_to_camera
    from ti_fusion.kernels.surfels import ATTRIBUTES

    H, W = rgb.shape[:2]
    ints = np.array([W, H, len(data["position"]), frame, cfg.unstable_age], np.int32)
    params = np.concatenate([world_to_camera(pose), camera_to_world(pose), K.as_tuple(),
                             [cfg.dist_threshold, math.cos(math.radians(cfg.normal_threshold_deg)),
                              cfg.unstable_weight]]).astype(np.float32)
    ints.tofile(workdir / "ints.bin")
    params.tofile(workdir / "params.bin")
    pyramid.vertex[0].to_numpy().astype(np.float32).tofile(workdir / "vertex.bin")
    pyramid.normal[0].to_numpy().astype(np.float32).tofile(workdir / "normal_map.bin")
    radial.astype(np.float32).tofile(workdir / "radial.bin")
    np.ascontiguousarray(rgb, dtype=np.uint8).tofile(workdir / "rgb.bin")
    for name in ATTRIBUTES:
        data[name].tofile(workdir / f"{name}.bin")


def read_outputs(workdir: Path, n: int) -> dict:
    from ti_fusion.kernels.surfels import ATTRIBUTES

    out = {}
    for name in ATTRIBUTES:
        dtype = np.int32 if name.startswith("t_") else np.float32
        a = np.fromfile(workdir / f"out_{name}.bin", dtype)
        out[name] = a.reshape(n, 3) if a.size == 3 * n else a
    return out


def run_c(exe: Path, workdir: Path, repeats: int) -> tuple[float, tuple[int, ...]]:
    """(best ms, (merged, added, covered, removed, surfels kept)) of the C step on ``workdir``'s inputs;
    the map after it is left in ``workdir`` (``read_outputs``)."""
    out = subprocess.run([str(exe), str(workdir), str(repeats)], capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[0]), tuple(int(x) for x in out[1:])


def bench_size(width: int, height: int, target: int, repeats: int, executables: dict, workdir: Path) -> dict:
    import taichi as ti

    from benchlib import BLAS_SETTLE_S
    from ti_fusion.config import FusionConfig
    from ti_fusion.reference.fusion import NumpyFusion, build_map, matching_rows

    cfg = FusionConfig(level=0)
    check_config(cfg)
    mapper, pyramid, seq, frame = build_map(width, height, target, cfg)
    print(f"  {width}×{height}: map of {mapper.count:,} surfels after {frame} frames", flush=True)
    K = seq.intrinsics
    depth, rgb = seq.frame(frame)
    pyramid.compute(depth, K)
    pose = seq.poses[frame]
    data = mapper.to_numpy()

    def taichi_step():
        mapper.map.from_numpy(data)  # untimed: a fresh copy of the map
        ti.sync()
        t0 = time.perf_counter()
        stats = mapper.integrate(pyramid, rgb, pose, frame)
        ti.sync()
        return time.perf_counter() - t0, stats

    taichi_step()  # compiles, fills the radial table
    taichi_times, stats = zip(*(taichi_step() for _ in range(repeats)))
    result = mapper.to_numpy()
    radial = mapper.map.fusion_images(height, width).radial.to_numpy()

    vertex, normal = pyramid.vertex[0].to_numpy(), pyramid.normal[0].to_numpy()
    numpy_times = []
    for _ in range(repeats):
        ref = NumpyFusion(data, cfg, capacity=len(data["position"]) + width * height)  # untimed copy
        ms = ref.integrate(vertex, normal, depth, rgb, pose, K, frame)
        numpy_times.append(sum(ms.values()))
        time.sleep(BLAS_SETTLE_S)
    row = {"size": f"{width}x{height}", "surfels": len(data["position"]), "numpy": min(numpy_times),
           "taichi": 1e3 * min(taichi_times), "numpy_count": ref.n}
    s = stats[-1]
    counts = (s.merged, s.added, s.covered, s.removed, s.surfels)
    if executables:
        write_inputs(workdir, data, pyramid, rgb, pose, K, frame, cfg, radial)
    for march, exe in executables.items():
        ms, c_counts = run_c(exe, workdir, repeats)
        # a handful of surfels may pass or fail a threshold test by a rounding (float32 in both, operations
        # ordered differently): allow 0.1% on each count, no more
        if any(abs(a - b) > max(3, 1e-3 * b) for a, b in zip(c_counts, counts)):
            raise SystemExit(f"bench_fusion_ceiling: the C step (-march={march}) merged/added/covered/removed/"
                             f"kept {c_counts}, the kernels {counts}: it would be timing a different computation")
        row[f"c_{march}"] = ms
        # surfels are compared index by index, which only means something while the counts agree (one
        # append more shifts every later one)
        row[f"match_{march}"] = (f"{100 * matching_rows(read_outputs(workdir, c_counts[-1]), result):.2f}%"
                                 if c_counts == counts else f"not compared, counts {c_counts}")
    row["counts"] = counts
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--surfels", type=int, default=1_000_000, help="map size before the timed step")
    parser.add_argument("--repeats", type=int, default=10, help="timed steps of each (the fastest counts)")
    parser.add_argument("--sizes", default="320x240,640x480", help="comma-separated WxH")
    parser.add_argument("--cc", default="cc", help="C compiler (default cc)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    from bench_icp_ceiling import build_command, c_executables, compile_each_march, print_table
    from benchlib import keep_freed_memory, numpy_conditions

    kept = keep_freed_memory()
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
    from ti_fusion.backend import init_backend

    backend = init_backend("cpu")
    with tempfile.TemporaryDirectory(prefix="fusion_ceiling_") as tmp:
        workdir = Path(tmp)
        executables = c_executables(
            args.cc, lambda: compile_each_march(lambda march, exe: build_command(args.cc, march, C_SOURCE, exe),
                                                "fusion_step", workdir, "bench_fusion_ceiling"),
            "bench_fusion_ceiling", "step")
        rows = []
        for size in args.sizes.split(","):
            w, h = (int(x) for x in size.lower().split("x"))
            rows.append(bench_size(w, h, args.surfels, args.repeats, executables, workdir))
    print(f"\none fusion step (synthetic sequence, default settings); {backend.arch} backend, {os.cpu_count()} CPUs; "
          f"best ms of {args.repeats} (NumPy ÷ each); {numpy_conditions(kept)}")
    print_table(rows, executables, lead=("surfels",))
    for r in rows:
        merged, added, covered, removed, kept_n = r["counts"]
        match = ", ".join(f"{march} {r[f'match_{march}']}" for march in executables)
        print(f"{r['size']}: the kernels merged {merged:,}, added {added:,}, skipped {covered:,} covered, removed "
              f"{removed:,}, kept {kept_n:,} (NumPy kept {r['numpy_count']:,})"
              + (f"; surfels equal to the kernels' (1e-4): {match}" if match else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
