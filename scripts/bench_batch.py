#!/usr/bin/env python3
"""``ti-fusion batch`` on local Ray against the same ``ti-fusion slam`` runs one after another, in one run.

    python scripts/bench_batch.py [--inputs room,wall,corridor,loop] [--frames 20] [--downsample 2]
                                  [--jobs 2] [--threads 1] [--taichi-threads N] [--manifest FILE] [--keep DIR]
                                  [--no-warmup]

The jobs are the manifest's (``--manifest``), or one per ``--inputs`` name: a synthetic scene (``room``,
``wall``, ...) or a folder of the shared data (``redkitchen``: ../shared/data/redkitchen-7scenes,
``tum-cabinet``: ../shared/data/tum-fr3-cabinet-keyframes), each with ``--frames`` and ``--downsample``.

1. the first job, untimed, as each arm runs it (Taichi's default threads, pinned; the batch's Taichi threads,
   unpinned), just before that arm, so that both find Taichi's kernel cache warm: the cache's keys depend on
   what a process compiled before and on its thread count, and pinning compiles a probe kernel first;
2. one by one: each job's ``python -m ti_fusion slam ARGS`` after the other, as a shell loop runs them
   (Taichi's default threads: one per core), timed from the first start to the last end;
3. the batch: ``python -m ti_fusion batch MANIFEST --jobs N --threads T`` (and ``--taichi-threads N`` where
   given), timed the same way (Ray's start included).

Prints each job's frames and ATE in both arms (from the one-by-one run's summary.json and the batch's
results.csv) and whether they are identical, the batch's timeline (its summary.json's: Ray's start, each
job's Ray worker, task, process and frame loop, Ray's shutdown), the two times and their ratio (batch / one
by one).
"""

from __future__ import annotations

import argparse
import importlib.util
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = {"redkitchen": ROOT.parent / "shared" / "data" / "redkitchen-7scenes",
          "tum-cabinet": ROOT.parent / "shared" / "data" / "tum-fr3-cabinet-keyframes"}


def manifest_text(inputs: list[str], frames: int, downsample: int) -> str:
    lines = ["[defaults]", f"frames = {frames}", f"downsample = {downsample}", ""]
    for name in inputs:
        lines.append("[[inputs]]")
        if name in SHARED:
            lines += [f'name = "{name}"', f'data = "{SHARED[name]}"']
        else:
            lines += [f'name = "{name}"', f'scene = "{name}"']
        lines.append("")
    return "\n".join(lines)


def timed(argv: list[str], log: Path, env: dict | None = None) -> tuple[float, int]:
    started = time.perf_counter()
    with open(log, "w") as f:
        code = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT,
                              env={**os.environ, **(env or {})}).returncode
    return time.perf_counter() - started, code


def print_timeline(launched: float, ended: float, summary: dict, batch_dir: Path) -> None:
    """The batch's events in seconds since the bench launched its command; per job, its steps."""
    origin = summary.get("started_at")
    events = summary.get("timeline") or []
    if origin is None or not events:
        return
    shift = origin - launched
    print("batch timeline (s since the command was launched):")
    print(f"  {shift:6.2f}  driver process started")
    per_job: dict[str, dict] = {}
    for t, event, job in events:
        if job:
            per_job.setdefault(job, {})[event] = t + shift
        else:
            print(f"  {t + shift:6.2f}  {event}")
    print(f"  {ended - launched:6.2f}  driver process ended")
    print()
    print("| job | task submitted | its worker process started | task started | job process started | "
          "frame loop started | job process ended | result seen |")
    print("|---|---|---|---|---|---|---|---|")
    for job, at in per_job.items():
        loop = None
        try:
            run = json.loads((batch_dir / "runs" / job / "summary.json").read_text())
            if "job process end" in at and run.get("wall_s") is not None:
                loop = at["job process end"] - run["wall_s"]  # the run's wall_s is its frame loop's
        except (OSError, ValueError):
            pass
        cells = [at.get(k) for k in ("task submitted", "worker process", "task", "job process")] + [loop] + \
                [at.get(k) for k in ("job process end", "result")]
        print(f"| {job} | " + " | ".join("" if c is None else f"{c:.2f}" for c in cells) + " |")
    starts = [at["job process"] for at in per_job.values() if "job process" in at]
    ends = [at["job process end"] for at in per_job.values() if "job process end" in at]
    if starts and ends:
        print(f"the batch's own cost: {min(starts):.2f} s before the first job's process, "
              f"{ended - launched - max(ends):.2f} s after the last one ended")
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", default="room,wall,corridor,loop",
                    help="synthetic scenes or shared data names (redkitchen, tum-cabinet), comma-separated")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--downsample", type=int, default=2)
    ap.add_argument("--manifest", default=None, help="a manifest of one's own instead of --inputs")
    ap.add_argument("--jobs", type=int, default=2, help="the batch's jobs at once (default 2)")
    ap.add_argument("--threads", type=int, default=1, help="Taichi CPU threads per batch job (default 1)")
    ap.add_argument("--taichi-threads", type=int, default=None,
                    help="Taichi CPU threads per batch job (default: the batch's, twice --threads up to the cores)")
    ap.add_argument("--keep", default=None, metavar="DIR", help="write the runs here (default: a temporary folder)")
    ap.add_argument("--no-warmup", action="store_true", help="no untimed job first")
    args = ap.parse_args()

    sys.path.insert(0, str(ROOT))
    from ti_fusion.batch.manifest import read_manifest
    from ti_fusion.batch.runner import MISSING_RAY, job_env, local_cpus, taichi_threads
    from ti_fusion.errors import InputError

    if importlib.util.find_spec("ray") is None:  # else the batch arm fails in a second and the ratio means nothing
        print(f"bench_batch.py: {MISSING_RAY}", file=sys.stderr)
        return 2

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-batch-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.manifest:
        manifest = Path(args.manifest).resolve()
    else:
        missing = [n for n in args.inputs.split(",") if n in SHARED and not SHARED[n].is_dir()]
        if missing:
            print(f"bench_batch.py: {SHARED[missing[0]]}: not found (the shared data)", file=sys.stderr)
            return 2
        manifest = work / "bench.toml"
        manifest.write_text(manifest_text(args.inputs.split(","), args.frames, args.downsample))
    try:
        jobs = read_manifest(manifest).jobs
    except InputError as exc:
        print(f"bench_batch.py: {exc}", file=sys.stderr)
        return 2
    py = [sys.executable, "-m", "ti_fusion"]
    print(f"{len(jobs)} jobs from {manifest}; runs in {work}; {os.cpu_count()} CPUs "
          f"(load average now {os.getloadavg()[0]:.2f})", flush=True)

    def warm_up(arm: str, env: dict | None) -> None:
        if not args.no_warmup:
            seconds, code = timed(py + ["slam", *jobs[0].args, "--out", str(work / "warmup"), "--overwrite",
                                        "--quiet"], work / "warmup.log", env)
            print(f"warm-up as {arm} ({jobs[0].name}): {seconds:.1f} s, exit {code}", flush=True)

    # each arm's warm-up just before it: the kernel cache is an LRU that other runs on the machine evict from
    warm_up("one by one", None)
    one = {}
    started = time.perf_counter()
    for job in jobs:
        seconds, code = timed(py + ["slam", *job.args, "--out", str(work / "one" / job.name), "--overwrite", "--quiet"],
                              work / f"one-{job.name}.log")
        summary_path = work / "one" / job.name / "summary.json"
        one[job.name] = json.loads(summary_path.read_text()) if code == 0 and summary_path.is_file() else {}
        print(f"  one by one: {job.name}: {seconds:.1f} s, exit {code}", flush=True)
    sequential = time.perf_counter() - started

    taichi = args.taichi_threads or taichi_threads(args.threads, local_cpus())
    warm_up("batch", job_env(args.threads, taichi))
    batch_dir = work / "batch"
    launched = time.time()
    batched, code = timed(py + ["batch", str(manifest), "--out", str(batch_dir), "--overwrite", "--jobs",
                                str(args.jobs), "--threads", str(args.threads)] +
                           (["--taichi-threads", str(taichi)] if args.taichi_threads else []), work / "batch.log")
    print(f"  batch: {batched:.1f} s, exit {code}", flush=True)
    if code != 0:
        print(f"bench_batch.py: the batch failed (exit {code}); no ratio: see {work / 'batch.log'}", file=sys.stderr)
        return 1
    rows = {}
    if (batch_dir / "results.csv").is_file():
        with open(batch_dir / "results.csv") as f:
            rows = {r["run_dir"].removeprefix("runs/"): r for r in csv.DictReader(f)}

    print()
    print("| job | frames one / batch | ATE m one by one | ATE m batch | identical |")
    print("|---|---|---|---|---|")
    same_all = True
    for job in jobs:
        s, r = one.get(job.name, {}), rows.get(job.name, {})
        ate_one, ate_batch = s.get("ate_rmse_m"), (float(r["ate_m"]) if r.get("ate_m") else None)
        frames_batch = int(r["frames"]) if r.get("frames") else None
        same = s.get("frames") == frames_batch and ate_one == ate_batch and r.get("status") == "done"
        same_all &= same
        print(f"| {job.name} | {s.get('frames')} / {frames_batch} | {ate_one!r} | {ate_batch!r} | "
              f"{'yes' if same else 'NO'} |")
    compiled = {"one by one": sum(s.get("kernels_compiled") or 0 for s in one.values()), "batch": 0}
    for job in jobs:
        try:
            compiled["batch"] += json.loads((batch_dir / "runs" / job.name / "summary.json").read_text()).get(
                "kernels_compiled") or 0
        except (OSError, ValueError):
            pass
    print(f"kernels compiled: one by one {compiled['one by one']}, batch {compiled['batch']}"
          + (" (not a warm-cache measurement: the kernel cache lost them meanwhile)" if any(compiled.values()) else ""))
    print()
    try:
        batch_summary = json.loads((batch_dir / "summary.json").read_text())
    except (OSError, ValueError):
        batch_summary = {}
    print_timeline(launched, launched + batched, batch_summary, batch_dir)
    ray_s = batch_summary.get("ray_start_s")
    print(f"one by one (Taichi's default threads): {sequential:.1f} s")
    print(f"batch, {args.jobs} jobs at once x {args.threads} CPU(s) "
          f"({taichi} Taichi threads), Ray's start included: {batched:.1f} s"
          + (f" (Ray's start: {ray_s:.1f} s)" if ray_s is not None else ""))
    print(f"batch / one by one: {batched / sequential:.2f}x; rows identical: {'yes' if same_all else 'NO'}; "
          f"load average after: {os.getloadavg()[0]:.2f}")
    return 0 if same_all else 1


if __name__ == "__main__":
    sys.exit(main())
