#!/usr/bin/env python3
"""Where a frame's time goes between the host and the device: per frame, Taichi kernel launches, device→host
reads, kernel time and host overhead, on any backend.

    python scripts/bench_host.py [DATA ...] [--frames N] [--downsample F] [--arch cpu|cuda|vulkan]
                                 [--repeat N] [--json OUT] [--top K] [--set SECTION.KEY=VALUE ...]

DATA: dataset folders, and ``synthetic`` for the synthetic sequence (default: redkitchen at
../shared/data/redkitchen-7scenes when present, and the synthetic sequence). The frames are read into memory
first; then ``DenseSLAM.register_frame`` runs on each (maps, tracking, fusion: what ``fps processing``
counts), with ``ti.sync()`` after it so that a GPU's queued work is inside the frame's time. The first two
frames (kernel compilation) are left out of every column. ``--set`` overrides the default config as
ti-fusion's ``--set`` does (e.g. ``icp.color_weight=0`` for the synthetic sequence without colour).

Each data set runs twice (``--repeat N``: 2N times, alternating, reported by the median run of each kind),
each in a child process of its own:
- counting (no profiler): ``launches`` = calls of Taichi's ``Kernel.__call__`` (this project's kernels
  and Taichi's own, e.g. the copy kernels behind ``to_numpy``/``from_numpy``/``fill``); ``reads`` =
  device→host reads, counted by wrappers around Taichi's Python API, not by hand: ``to_numpy`` of a field
  or ndarray, a field element read from Python (``field[i]``), a kernel that returns a value, and, off the
  CPU, a launch that is given a NumPy array (Taichi copies it to the device and back, waiting for the
  kernel). On the CPU a NumPy argument is passed by address, so it is no read. ``processing ms`` = wall
  time of ``register_frame`` + sync;
- profiling (``kernel_profiler=True``): ``kernel ms`` = Taichi's kernel profiler's total per frame (cpu
  and cuda; Taichi has no kernel profiler on vulkan: n/a, and that run is skipped there), ``profiled ms``
  the processing time of that run (the profiler synchronises after every kernel, which adds to it).
``host ms`` = processing ms (the counting run) − kernel ms (the profiling run), the host overhead: what
the frame spends outside Taichi's kernels in an ordinary run (Python, launch paths, waiting for reads; on
the CPU, where the profiler times each parallel loop from its dispatch to its barrier, the thread pool's
dispatch counts as kernel time). ``host ms (profiled)`` = profiled ms − kernel ms, both from the profiling
run: it also holds the profiler's own cost (on a GPU its synchronisation after every kernel, which
serialises the host's launches with the device's work), but no load that changes between the two runs
does. Between two processes on a shared machine ``host ms`` drifts by milliseconds (it can even come out
below zero): ``--repeat 3`` or more on a quiet machine. ``busy`` = kernel ms / processing ms, the
device's share of an ordinary frame ("GPU busy"), and ``busy (profiled)`` the same of the
profiling run.
``--top K`` also prints the K kernels launched most per frame and, from the profiling run, the K that took
the most kernel time per frame (the profiler's records summed by kernel, every instance and parallel loop
of a kernel together).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"
WARMUP = 2  # frames left out: kernel compilation
# A profiler record's name is the kernel's, then its instance and task: iterate_c94_0_kernel_2_range_for
KERNEL_INSTANCE = re.compile(r"_c\d+_\d+.*$")


class Counter:
    """Counts Taichi kernel launches (by kernel name) and device→host reads through wrappers around
    Taichi's Python API (module docstring)."""

    def __init__(self, arch: str):
        self.arch = arch
        self.launches: dict[str, int] = {}
        self.reads: dict[str, int] = {}
        self._depth = 0  # inside a wrapped read: its internal launches and reads are not reads of their own
        self.active = False
        self._originals: list = []  # (class, name, method) to put back (``uninstall``)

    def _read(self, what: str) -> None:
        if self.active and self._depth == 0:
            self.reads[what] = self.reads.get(what, 0) + 1

    def install(self) -> None:
        import numpy as np
        import importlib

        _ndarray, field, kernel_impl, matrix = (importlib.import_module(f"taichi.lang.{m}")
                                                for m in ("_ndarray", "field", "kernel_impl", "matrix"))

        from taichi.types.ndarray_type import NdarrayType  # a NumPy array for a vector argument is copied by value

        counter = self
        # a launch is a call: ti_fusion.frontend's shorter path launches an instance again without
        # ``Kernel.launch_kernel``
        call = kernel_impl.Kernel.__call__

        def counted_call(kernel, *args, **kwargs):
            if counter.active:
                name = kernel.func.__name__
                counter.launches[name] = counter.launches.get(name, 0) + 1
                if kernel.return_type:
                    counter._read(f"return of {name}")
                elif counter.arch != "cpu" and any(isinstance(a, np.ndarray) and isinstance(p.annotation, NdarrayType)
                                                   for a, p in zip(args, kernel.arguments)):
                    counter._read(f"NumPy argument of {name}")
            return call(kernel, *args, **kwargs)

        self._originals.append((kernel_impl.Kernel, "__call__", call))
        kernel_impl.Kernel.__call__ = counted_call

        def reading(cls, method: str, what: str):
            original = cls.__dict__.get(method, getattr(cls, method))
            self._originals.append((cls, method, original))

            def wrapper(self, *args, **kwargs):
                counter._read(what)
                counter._depth += 1
                try:
                    return original(self, *args, **kwargs)
                finally:
                    counter._depth -= 1

            setattr(cls, method, wrapper)

        for cls in (field.ScalarField, matrix.MatrixField, _ndarray.ScalarNdarray, matrix.MatrixNdarray,
                    matrix.VectorNdarray):
            reading(cls, "to_numpy", f"{cls.__name__}.to_numpy")
        for cls in (field.ScalarField, matrix.MatrixField, _ndarray.ScalarNdarray, matrix.MatrixNdarray,
                    matrix.VectorNdarray):
            reading(cls, "__getitem__", f"{cls.__name__}[...]")

    def uninstall(self) -> None:
        """Put Taichi's methods back (tests)."""
        for cls, name, method in reversed(self._originals):
            setattr(cls, name, method)
        self._originals.clear()

    def total_reads(self) -> int:
        return sum(self.reads.values())

    def reset(self) -> None:
        self.launches.clear()
        self.reads.clear()


def _frames(data: str, frames: int, downsample: int, overrides: list[str] | None = None):
    """(config, dataset, frames in memory): the synthetic sequence's are made by Taichi kernels, so they are
    made here, before anything is counted. ``overrides``: ``--set`` texts (``SECTION.KEY=VALUE``)."""
    from ti_fusion.config import load_config
    from ti_fusion.io.datasets import open_dataset

    cfg = load_config(None, overrides)
    cfg.dataset.path = None if data == "synthetic" else data
    cfg.dataset.downsample = downsample
    cfg.dataset.stop = frames
    cfg.log.progress = False
    dataset = open_dataset(cfg.dataset, cfg.synth)
    return cfg, dataset, [dataset[i] for i in range(len(dataset))]


def child(args) -> dict:
    """One run on one data set (counting, or with the kernel profiler): a JSON object on stdout."""
    import taichi as ti
    from taichi.lang import impl

    from ti_fusion.backend import init_backend

    kwargs = {"kernel_profiler": True} if args.profile else {}
    backend = init_backend(args.arch, **kwargs)
    counter = Counter(backend.arch)
    counter.install()
    cfg, dataset, frames = _frames(args.data[0], args.frames, args.downsample, args.set)
    from ti_fusion.slam.dense import DenseSLAM

    slam = DenseSLAM(cfg, dataset.intrinsics)
    wall, kernel_ms, tracked, poses, kernel_ms_by = [], [], 0, [], {}
    for i, frame in enumerate(frames):
        steady = i >= WARMUP
        if steady:
            counter.active = True
            if args.profile:
                ti.profiler.clear_kernel_profiler_info()
        t0 = time.perf_counter()
        result = slam.register_frame(frame)
        ti.sync()
        t1 = time.perf_counter()
        counter.active = False
        if steady:
            wall.append((t1 - t0) * 1e3)
            if args.profile:
                kernel_ms.append(ti.profiler.get_kernel_profiler_total_time() * 1e3)
                for record in impl.get_runtime().prog.get_kernel_profiler_records():
                    name = KERNEL_INSTANCE.sub("", record.name)
                    kernel_ms_by[name] = kernel_ms_by.get(name, 0.0) + record.kernel_time
        tracked += int(result.tracked)
        poses.append(None if result.pose is None else [float(x) for x in result.pose.ravel()])
    n = max(1, len(wall))
    return {"data": args.data[0], "arch": backend.arch, "frames": len(frames), "timed_frames": len(wall),
            "tracked": tracked, "processing_ms": sum(wall) / n,
            "launches": sum(counter.launches.values()) / n, "reads": sum(counter.reads.values()) / n,
            "by_kernel": {k: v / n for k, v in sorted(counter.launches.items(), key=lambda kv: -kv[1])},
            "by_read": {k: v / n for k, v in sorted(counter.reads.items(), key=lambda kv: -kv[1])},
            "kernel_ms": sum(kernel_ms) / n if kernel_ms else None,
            "kernel_ms_by_kernel": {k: v / n for k, v in sorted(kernel_ms_by.items(), key=lambda kv: -kv[1])},
            "poses": poses}


def _run_child(args, data: str, profile: bool) -> dict:
    cmd = [sys.executable, __file__, data, "--child", "--frames", str(args.frames), "--downsample",
           str(args.downsample), "--arch", args.arch] + (["--profile"] if profile else []) + \
        [f"--set={text}" for text in args.set]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        return {"data": data, "error": f"exit {out.returncode}: {tail}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _median_run(runs: list[dict], key: str) -> dict:
    """Of repeated runs, the one with the median ``key`` among those that ran (the first failed one when
    none did; for an even count, the faster of the middle two)."""
    timed = sorted((r for r in runs if "error" not in r and r.get(key) is not None), key=lambda r: r[key])
    if timed:
        return timed[(len(timed) - 1) // 2]
    return next((r for r in runs if "error" in r), runs[0])


def _cell(x: float | None, spec: str = ".2f") -> str:
    return "n/a" if x is None else format(x, spec)


def _cells(xs: list) -> str:
    return " / ".join(_cell(x) for x in xs)


def _percent(part: float | None, whole: float | None) -> str:
    return "n/a" if part is None or not whole else f"{100 * part / whole:.0f} %"


def _name(data: str) -> str:
    return "synthetic" if data == "synthetic" else Path(data).name


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="*", help="dataset folders, or 'synthetic'")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--arch", default="cpu", choices=("cpu", "cuda", "vulkan"))
    parser.add_argument("--json", help="write the rows (with per-kernel launches and poses) to this file")
    parser.add_argument("--top", type=int, default=0, help="also print the K kernels launched most per frame")
    parser.add_argument("--repeat", type=int, default=1,
                        help="run each data set N times, counting and profiling runs alternating, and report "
                             "the median run of each (host ms between two processes needs a steady machine)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a config override, as ti-fusion's --set (repeatable), e.g. icp.color_weight=0")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)))
        return 0
    if not args.data:
        args.data = ([str(DEFAULT_DATA)] if (DEFAULT_DATA / "frame-000000.depth.png").is_file() else []) + ["synthetic"]
    from ti_fusion.config import load_config
    from ti_fusion.errors import InputError

    try:
        load_config(None, args.set)
    except InputError as exc:
        print(f"bench_host.py: {exc}", file=sys.stderr)
        return 2
    for data in args.data:
        if data != "synthetic" and not Path(data).is_dir():
            print(f"bench_host.py: {data}: not a folder (give a dataset folder or 'synthetic')", file=sys.stderr)
            return 2
    rows = []
    sets = "".join(f" --set {text}" for text in args.set)
    if args.repeat < 1:
        print(f"bench_host.py: --repeat {args.repeat}: give at least 1", file=sys.stderr)
        return 2
    print(f"bench_host.py --arch {args.arch} --frames {args.frames} --downsample {args.downsample}{sets} "
          f"--repeat {args.repeat} ({os.cpu_count()} CPUs; first {WARMUP} frames left out; median runs)")
    print("| data | arch | frames | launches/frame | reads/frame | kernel ms | host ms | processing ms | "
          "fps processing | busy | profiled ms | host ms (profiled) | busy (profiled) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for data in args.data:
        counts, profs = [], []
        for _ in range(args.repeat):  # alternating, so that a drifting load reaches both kinds of run alike
            counts.append(_run_child(args, data, profile=False))
            # Taichi has no kernel profiler on vulkan, and asking for it there took > 3 min for 40 frames on
            # an H200 with NVIDIA's driver (docs/PERFORMANCE.md): the profiling run is left out on vulkan.
            profs.append(_run_child(args, data, profile=True) if args.arch != "vulkan" else {})
        count, prof = _median_run(counts, "processing_ms"), _median_run(profs, "kernel_ms")
        for run in counts + profs:  # a failed run is said, not only left out
            if "error" in run and run is not count:
                print(f"bench_host.py: {_name(data)}: a run failed: {run['error']}", file=sys.stderr)
        row = dict(count)
        row["runs"] = {"processing_ms": [c.get("processing_ms") for c in counts],
                       "kernel_ms": [q.get("kernel_ms") for q in profs],
                       "profiled_processing_ms": [q.get("processing_ms") for q in profs]}
        if "error" in count:
            print(f"| {_name(data)} | {args.arch} | {count['error']} |")
            rows.append(row)
            continue
        row["kernel_ms"] = prof.get("kernel_ms")
        row["kernel_ms_by_kernel"] = prof.get("kernel_ms_by_kernel", {})
        row["profiled_processing_ms"] = prof.get("processing_ms")
        k, p, q = row["kernel_ms"], row["processing_ms"], row["profiled_processing_ms"]
        row["host_ms"] = None if k is None else p - k
        row["profiled_host_ms"] = None if k is None or q is None else q - k
        row["busy"] = None if k is None else k / p  # device_check.sh's table reads these three
        print(f"| {_name(data)} | {count['arch']} | {count['frames']} ({count['tracked']} tracked) | "
              f"{count['launches']:.1f} | {count['reads']:.2f} | {_cell(k)} | {_cell(row['host_ms'])} | {p:.2f} | "
              f"{1e3 / p:.1f} | {_percent(row['busy'], 1)} | {_cell(q)} | {_cell(row['profiled_host_ms'])} | "
              f"{_percent(k, q)} |")
        rows.append(row)
    if args.repeat > 1:
        for row in rows:
            if "runs" in row:
                runs = row["runs"]
                print(f"{_name(row['data'])}, every run in order: processing ms {_cells(runs['processing_ms'])}; "
                      f"kernel ms {_cells(runs['kernel_ms'])}; profiled ms {_cells(runs['profiled_processing_ms'])}")
    if args.top:
        for row in rows:
            if "error" in row:
                continue
            print(f"\n{_name(row['data'])}: launches per frame by kernel (top {args.top}); reads per frame by kind")
            for name, n in list(row["by_kernel"].items())[:args.top]:
                print(f"  {n:7.2f}  {name}")
            for name, n in row["by_read"].items():
                print(f"  {n:7.2f}  read: {name}")
            if row.get("kernel_ms_by_kernel"):
                print(f"{_name(row['data'])}: kernel ms per frame by kernel (the profiler's, top {args.top})")
                for name, ms in list(row["kernel_ms_by_kernel"].items())[:args.top]:
                    print(f"  {ms:7.3f}  {name}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
