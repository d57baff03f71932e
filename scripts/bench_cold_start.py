#!/usr/bin/env python3
"""A short ``ti-fusion slam`` run with an empty Taichi kernel cache: this checkout against a git ref, one run.

    python scripts/bench_cold_start.py [--baseline REF] [--rounds N] [--frames 3] [--warm] [DATA]
                                       [--set SECTION.KEY=VALUE ...]

The code under test is this checkout's working tree (as the installed ``ti-fusion`` runs it); the
baseline is ``REF`` (default ``main``) extracted with ``git archive`` into a temporary folder and run by
the same interpreter, with that folder first on ``PYTHONPATH`` (each child checks that it imported
``ti_fusion`` from where it should). Each round runs the baseline, then the code under test (alternated
order on odd rounds), each ``python -m ti_fusion slam [DATA] --frames N`` in a child process with a
fresh ``TI_OFFLINE_CACHE_FILE_PATH`` (so every kernel compiles); ``--warm`` adds a second run of each
on the cache its cold run filled. Columns per run: the child's wall-clock life (``process s``), its CPU
time (user + system, from ``wait4``: on a loaded machine the less noisy of the two), its age at the first
frame done (``1st frame s``), and from its summary.json the kernel instances first launched, how many
compiled (a first launch over 1 s) and their seconds, and the five that took longest. The last lines
are the medians' ratios, under test / baseline, for wall-clock and CPU time, and the machine's load
(``os.getloadavg``) before and after: the box is shared, so compare the ratio, not the seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Run in each child instead of ``-m ti_fusion``: the same entry point, after checking where the package
# came from (an editable install of another checkout must not win over PYTHONPATH unnoticed).
CHILD = """
import sys
import ti_fusion, ti_fusion.kernels
from pathlib import Path
want = Path(sys.argv.pop(1)).resolve()
for module in (ti_fusion, ti_fusion.kernels):
    if want not in Path(module.__file__).resolve().parents:
        sys.exit(f"bench_cold_start.py: {module.__name__} imported from {module.__file__}, not from {want}")
from ti_fusion.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def extract(ref: str, into: Path) -> Path:
    """``ref`` of this repository as files under ``into`` (``git archive``), laid out as the installed
    package is (``kernels/`` is ``ti_fusion.kernels``); the folder to put on ``PYTHONPATH``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", ref], capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"bench_cold_start.py: --baseline {ref}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    link = into / "ti_fusion" / "kernels"
    if not link.exists():
        link.symlink_to(into / "kernels", target_is_directory=True)
    return into


def run_once(label: str, code_root: Path, args, cache: str, workdir: Path) -> dict:
    """One ``ti-fusion slam`` child with the kernel cache ``cache``: its times and kernel counts."""
    out = workdir / f"out-{label}-{time.monotonic_ns()}"
    argv = [sys.executable, "-c", CHILD, str(code_root), "slam", *([args.data] if args.data else []),
            "--frames", str(args.frames), "--arch", "cpu", "--quiet", "--out", str(out),
            *[f"--set={text}" for text in args.set]]
    env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": cache,
           "PYTHONPATH": os.pathsep.join(filter(None, [str(code_root), os.environ.get("PYTHONPATH")]))}
    started = time.perf_counter()
    child = subprocess.Popen(argv, cwd=workdir, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - started
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        tail = output.decode(errors="replace").strip().splitlines()[-3:]
        raise SystemExit(f"bench_cold_start.py: the {label} run exited with {child.returncode}: " + " | ".join(tail))
    s = json.loads((out / "summary.json").read_text())
    by_kernel = s.get("kernels_compiled_s") or {}
    top = sorted(by_kernel.items(), key=lambda kv: -kv[1])[:5]
    return {"label": label, "wall": wall, "cpu": usage.ru_utime + usage.ru_stime,
            "first_frame": s.get("first_frame_s"), "instances": s.get("kernel_instances"),
            "compiled": s.get("kernels_compiled"), "compile_s": s.get("kernel_compile_s"),
            "top": ", ".join(f"{name} {sec:.1f}" for name, sec in top)}


def fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="?", help="dataset (default: the embedded synthetic sequence)")
    parser.add_argument("--baseline", default="main", help="git ref to compare with (default: main)")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of (baseline, under test) (default: 1)")
    parser.add_argument("--frames", type=int, default=3, help="frames per run (default: 3)")
    parser.add_argument("--warm", action="store_true", help="also a run of each on the cache its cold run filled")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="passed on to ti-fusion slam (repeatable)")
    args = parser.parse_args()
    for name in ("rounds", "frames"):
        if getattr(args, name) < 1:
            parser.exit(2, f"bench_cold_start.py: --{name} {getattr(args, name)}: give at least 1\n")
    known = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", f"{args.baseline}^{{commit}}"],
                           capture_output=True)
    if known.returncode != 0:
        parser.exit(2, f"bench_cold_start.py: --baseline {args.baseline}: not a commit of {ROOT}\n")
    if args.data:
        args.data = str(Path(args.data).resolve())
        if not Path(args.data).exists():
            parser.exit(2, f"bench_cold_start.py: {args.data}: no such file or folder\n")
    load_before = os.getloadavg()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench-cold-") as tmp:
        tmp = Path(tmp)
        (tmp / "baseline").mkdir()
        arms = {"baseline": extract(args.baseline, tmp / "baseline"), "under test": ROOT}
        for r in range(args.rounds):
            order = ["baseline", "under test"] if r % 2 == 0 else ["under test", "baseline"]
            for label in order:
                cache = tempfile.mkdtemp(prefix="cache-", dir=tmp)
                row = run_once(label, arms[label], args, cache, tmp)
                rows.append({**row, "cache": "empty"})
                print(f"round {r + 1} {label}, empty cache: {row['wall']:.1f} s", file=sys.stderr, flush=True)
                if args.warm:
                    rows.append({**run_once(label, arms[label], args, cache, tmp), "cache": "warm"})
    load_after = os.getloadavg()

    print(f"ti-fusion slam {args.data or '(synthetic)'} --frames {args.frames}, baseline {args.baseline}, "
          f"{args.rounds} round(s)")
    print("| code | cache | process s | CPU s | 1st frame s | instances | compiled | compile s | longest |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['label']} | {row['cache']} | {row['wall']:.2f} | {row['cpu']:.2f} | {fmt(row['first_frame'])} | "
              f"{fmt(row['instances'], 'd')} | {fmt(row['compiled'], 'd')} | {fmt(row['compile_s'], '.1f')} | "
              f"{row['top']} |")
    for cache in ("empty", "warm"):
        mine = [r for r in rows if r["cache"] == cache]
        if not mine:
            continue
        for what in ("wall", "cpu"):
            base = statistics.median(r[what] for r in mine if r["label"] == "baseline")
            test = statistics.median(r[what] for r in mine if r["label"] == "under test")
            print(f"{cache} cache, {'process' if what == 'wall' else 'CPU'} time, median: under test {test:.2f} s / "
                  f"baseline {base:.2f} s = {test / base:.2f}x")
    print("load average (1, 5, 15 min): before " + ", ".join(f"{x:.1f}" for x in load_before)
          + "; after " + ", ".join(f"{x:.1f}" for x in load_after))
    return 0


if __name__ == "__main__":
    sys.exit(main())
