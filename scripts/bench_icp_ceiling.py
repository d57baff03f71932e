#!/usr/bin/env python
"""How far can one ICP iteration go on this machine? The Taichi kernel, the lean NumPy baseline and the
same pass in plain C, on the same frames, in one run.

    .venv/bin/python scripts/bench_icp_ceiling.py [DATA] [--pair S T] [--repeats N] [--cc gcc] [--set icp.KEY=VALUE]

For the frame pair of ``scripts/bench_icp.py`` (converged pose, finest level, 640×480 and 320×240) it
times one iteration of
- Taichi: ``PointToPlane.iterate`` as ``ICP.align`` runs it, on the machine's cores;
- NumPy: ``icp_numpy.LevelIteration`` and the 6×6 solve (the baseline of ``bench_icp.py``);
- C: ``scripts/icp_pass.c``, the same float64 pass (association and the 30 sums, no solve) on one
  thread, compiled with ``-O3`` and the floating-point freedoms Taichi's kernels have by default
  (``fast_math``: reassociation, no signed zeros; ``C_FLAGS``), for ``-march=x86-64`` (SSE2, no FMA: a
  point of comparison, not Taichi's code; Taichi 1.7.4 here emits AVX/AVX-512 encodings, but no FMA and
  mostly scalar or 2-wide double, see docs/PERFORMANCE.md) and ``-march=native``.
Each is timed at its best: the fastest single iteration of ``--repeats`` (each after an untimed one, so
threads are awake as within ICP). This machine is noisy (one NumPy iteration at 640×480 took 32 to 57
ms within one run) and the minimum is what each code can do; ``bench_icp.py`` reports medians instead,
so compare ratios within one script. The script stops if C's sums are not NumPy's. "C native ÷ 2" is the
time a perfect two-thread split of the native pass would take (no thread start-up, no solve): a bound on
how far NumPy's ratio could go with the code this compiler makes of this (scalar, interleaved-array) C
source, e.g. against a 20× target.

Needs a C compiler (``--cc``, default ``cc``); without one the C columns are skipped.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# The sibling scripts (bench_icp, benchlib) are imported in the functions that use them: the tests load this
# file alone, for how it builds the C programs (build_command, c_command)

C_SOURCE = Path(__file__).resolve().parent / "icp_pass.c"
MARCH = ("x86-64", "native")
# Taichi's default fast_math lets LLVM reassociate and ignore signed zeros (its IR: reassoc nsz); the C
# gets the same, so neither side is held to stricter rounding than the other
C_FLAGS = ("-O3", "-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math")
ROBUST_C = {"none": 0, "huber": 1, "tukey": 2}


def build_command(cc: str, march: str, source: Path, exe: Path, defines: tuple[str, ...] = ()) -> list[str]:
    """The compiler command for one C program of the ceiling benchmarks at one -march."""
    from ti_fusion.sensor import c_defines  # the depth noise model's constants, which icp_pass.c reads

    return [cc, *C_FLAGS, *c_defines(), f"-march={march}", *defines, "-o", str(exe), str(source), "-lm"]


def c_command(cc: str, march: str, robust: str, exe: Path) -> list[str]:
    """The compiler command of the ICP pass for one -march and robust mode (e.g. "huber+depth")."""
    name, _, depth = robust.partition("+")
    return build_command(cc, march, C_SOURCE, exe,
                         (f"-DROBUST={ROBUST_C[name]}", f"-DDEPTH_WEIGHTED={int(depth == 'depth')}"))


def compile_each_march(command, name: str, workdir: Path, script: str) -> dict[str, Path]:
    """{march: executable} for each -march that compiles; ``command(march, exe)`` gives the command."""
    out = {}
    for march in MARCH:
        exe = workdir / f"{name}_{march}"
        cmd = command(march, exe)
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode == 0:
            out[march] = exe
        else:
            last = run.stderr.strip().splitlines()[-1] if run.stderr.strip() else f"exit code {run.returncode}"
            print(f"{script}: {cmd[0]} -march={march} failed: {last}")
    return out


def compile_c(cc: str, robust: str, workdir: Path) -> dict[str, Path]:
    """{march: executable} of the ICP pass for each -march that compiles."""
    return compile_each_march(lambda march, exe: c_command(cc, march, robust, exe), "icp_pass", workdir,
                              "bench_icp_ceiling")


def c_executables(cc: str, compile_all, script: str, what: str) -> dict[str, Path]:
    """``compile_all()`` ({march: executable}) where the compiler ``cc`` exists; else, or if nothing
    compiled, {} after saying that the C columns are skipped."""
    if not shutil.which(cc):
        print(f"{script}: no C compiler ({cc}): C columns skipped")
        return {}
    executables = compile_all()
    if not executables:
        print(f"{script}: the C {what} did not compile: C columns skipped")
    return executables


def print_table(rows: list[dict], executables: dict, lead: tuple[str, ...] = ()) -> None:
    """The ceiling table: per row its size, the ``lead`` columns (e.g. "surfels"), then the best ms of
    NumPy, Taichi and C at each -march (``row["numpy"]``, ``row["taichi"]``, ``row["c_<march>"]``), with
    NumPy ÷ each, and C native ÷ 2, the perfect two-thread split."""
    head = f"{'':>8} |" + "".join(f" {name:>9} |" for name in lead) + f" {'NumPy':>7} | {'Taichi, all cores':>17}"
    for march in executables:
        head += f" | {'C ' + march + ', 1 thread':>24}"
    if "native" in executables:
        head += f" | {'C native ÷ 2 (ideal)':>20}"
    print(head)
    for r in rows:
        line = (f"{r['size']:>8} |" + "".join(f" {r[name]:>9,} |" for name in lead)
                + f" {r['numpy']:7.2f} | {r['taichi']:6.2f} ({r['numpy'] / r['taichi']:5.1f}×)   ")
        for march in executables:
            ms = r[f"c_{march}"]
            line += f" | {ms:12.2f} ({r['numpy'] / ms:5.1f}×)    "
        if "native" in executables:
            half = r["c_native"] / 2
            line += f" | {half:9.2f} ({r['numpy'] / half:5.1f}×)"
        print(line)


def best_ms(fn, repeats: int, before=None, after=None) -> float:
    """The fastest of ``repeats`` single timed calls, each after an untimed one (see the docstring)."""
    times = []
    for _ in range(repeats):
        if before:
            before()
        fn()  # untimed: threads awake, as within ICP
        if before:
            before()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if after:
            after()
    return 1e3 * min(times)


def bench_size(depth_s, depth_t, K, cfg, executables, repeats: int, workdir: Path) -> dict:
    from bench_icp import FinestIteration, compute_maps
    from benchlib import BLAS_SETTLE_S

    from ti_fusion.geometry import flatten_pose
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.pyramid import FramePyramid

    c = cfg.icp
    src, tgt = (FramePyramid(cfg.pyramid, K.height, K.width, len(c.iterations)) for _ in range(2))
    compute_maps(src, tgt, depth_s, depth_t, K, c)
    icp = ICP(c)
    pose = icp.align(src, tgt).pose
    one = FinestIteration(icp, src, tgt, pose)
    ref = one.numpy_level.sums(pose)
    row = {"size": f"{K.width}x{K.height}",
           "numpy": best_ms(one.numpy, repeats, after=lambda: time.sleep(BLAS_SETTLE_S)),
           "taichi": best_ms(one.taichi, repeats, before=one.start)}
    # the C program's inputs (see scripts/icp_pass.c)
    dist, angle, _, scale = one.thresholds
    params = np.concatenate([flatten_pose(pose), one.K, [dist ** 2, np.cos(np.radians(angle)), scale]])
    params.astype(np.float64).tofile(workdir / "params.bin")
    for fname, f in zip(("sv", "sn", "tv", "tn"), one.fields):
        f.to_numpy().astype(np.float32).tofile(workdir / f"{fname}.bin")
    for march, exe in executables.items():
        out = subprocess.run([str(exe), str(workdir), str(K.height), str(K.width), str(repeats)],
                             capture_output=True, text=True, check=True).stdout.split()
        ms, sums = float(out[0]), np.array([float(x) for x in out[1:]])
        scale = max(float(np.max(np.abs(ref))), 1e-300)
        if not np.array_equal(sums[-2:], ref[-2:]) or np.max(np.abs(sums - ref)) > 1e-9 * scale:
            raise SystemExit(f"bench_icp_ceiling: the C pass (-march={march}) does not give NumPy's sums: "
                             f"it would be timing a different computation")
        row[f"c_{march}"] = ms
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="?", default="", help="7-Scenes folder (default: ../shared/data/redkitchen-7scenes)")
    parser.add_argument("--pair", nargs=2, type=int, default=[100, 110], metavar=("S", "T"))
    parser.add_argument("--repeats", type=int, default=30, help="timed iterations of each (the fastest counts)")
    parser.add_argument("--cc", default="cc", help="C compiler (default cc)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    from bench_icp import load_pair
    from benchlib import keep_freed_memory, numpy_conditions

    kept = keep_freed_memory()
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
    from ti_fusion.backend import init_backend
    from ti_fusion.config import load_config
    from ti_fusion.tracking.icp import ICP

    cfg = load_config(None, args.set)
    backend = init_backend("cpu")
    depth_s, depth_t, K, _, what = load_pair(args, cfg)
    with tempfile.TemporaryDirectory(prefix="icp_ceiling_") as tmp:
        workdir = Path(tmp)
        robust = ICP(cfg.icp).terms[0].robust  # the geometric term's
        executables = c_executables(args.cc, lambda: compile_c(args.cc, robust, workdir), "bench_icp_ceiling", "pass")
        rows = [bench_size(depth_s[::f, ::f].copy(), depth_t[::f, ::f].copy(), K.downsampled(f), cfg, executables,
                           args.repeats, workdir) for f in (1, 2)]
    print(f"one ICP iteration at the finest level, {what}; {backend.arch} backend, {os.cpu_count()} CPUs; "
          f"robust {robust}; best ms of each (NumPy ÷ each); {numpy_conditions(kept)}")
    print_table(rows, executables)
    return 0


if __name__ == "__main__":
    sys.exit(main())
