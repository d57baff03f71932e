"""The modules one frame's path passes through, the module pairs that call each other both ways, and the calls
per frame across the pipeline, its step, the sinks and loop closure.

    python scripts/frame_path.py [--from 10] [ti-fusion slam options, e.g. --frames 40]

Runs ``ti-fusion slam`` (the synthetic sequence unless told otherwise) with a profiler on the loop's thread.
A frame is everything between two frames handed out by the loop (reading, ``register_frame``, the sinks);
frames from ``--from`` (after the warm-up) to the one before the last are counted. A module counts when a
Python function of one of its files (``ti_fusion/``, ``kernels/``) is entered; Taichi's kernels run compiled
and count through their Python callers. A call's caller is the nearest frame of the stack in the package.
"""

from __future__ import annotations

import argparse
import collections
import functools
import os
import sys
import tempfile
from pathlib import Path

import ti_fusion
import ti_fusion.slam.pipeline as pipeline_module
from ti_fusion.cli.main import main

REPO = Path(ti_fusion.__file__).resolve().parents[1]
# the boundaries whose calls are listed by function
LISTED = (("slam/pipeline", "slam/"), ("slam/pipeline", "sinks/"), ("sinks/", "slam/"), ("loop/", "slam/"),
          ("slam/", "loop/"))


@functools.cache
def module_of(filename: str) -> str | None:
    path = Path(filename)
    if not path.is_absolute():
        return None
    try:
        rel = path.resolve().relative_to(REPO)
    except ValueError:
        return None
    if rel.parts[0] not in ("ti_fusion", "kernels"):
        return None
    return "kernels/" + "/".join(rel.parts[2:]) if rel.parts[:2] == ("ti_fusion", "kernels") else str(rel)


class Trace:
    def __init__(self):
        self.frame = -1
        self.modules = collections.defaultdict(set)  # frame → modules entered
        self.calls = collections.defaultdict(int)  # (frame, caller module, callee module, callee function) → calls

    def __call__(self, fr, event, arg):
        if event != "call":
            return
        callee = module_of(fr.f_code.co_filename)
        if callee is None:
            return
        self.modules[self.frame].add(callee)
        back = fr.f_back
        while back is not None and module_of(back.f_code.co_filename) is None:
            back = back.f_back
        caller = module_of(back.f_code.co_filename) if back is not None else None
        if caller is not None and caller != callee:
            self.calls[(self.frame, caller, callee, fr.f_code.co_qualname)] += 1

    def counting(self, progress):
        def counted(*args, **kw):
            for item in progress(*args, **kw):
                self.frame += 1
                yield item
        return counted


def report(trace: Trace, first: int) -> None:
    frames = sorted(f for f in trace.modules if f >= first)[:-1]  # the last one holds the end of the run
    if not frames:
        sys.exit("no frame after --from: run more frames")
    every = set().union(*(trace.modules[f] for f in frames))
    sizes = sorted(len(trace.modules[f]) for f in frames)
    print(f"frames {frames[0]}..{frames[-1]}: {sizes[len(sizes) // 2]} modules in a median frame ({sizes[0]} to "
          f"{sizes[-1]}); {len(every)} modules in {len({os.path.dirname(m) for m in every})} folders in all:")
    for m in sorted(every):
        print("   ", m)
    steady, n = set(frames), len(frames)
    pairs = collections.defaultdict(int)
    named = collections.defaultdict(int)
    for (f, a, b, q), c in trace.calls.items():
        if f in steady:
            pairs[(a, b)] += c
            named[(a, b, q)] += c
    both = sorted({tuple(sorted(p)) for p in pairs if (p[1], p[0]) in pairs})
    print(f"module pairs that call each other both ways: {len(both)}")
    for a, b in both:
        print(f"    {a} <-> {b} ({pairs[(a, b)] / n:.2f} / {pairs[(b, a)] / n:.2f} calls a frame)")
    print("calls a frame (mean) across the pipeline, its step, the sinks and loop closure:")
    for (a, b, q), c in sorted(named.items()):
        if any(a.startswith("ti_fusion/" + x) and b.startswith("ti_fusion/" + y) for x, y in LISTED):
            print(f"    {a} -> {b} {q}: {c / n:.2f}")


def run() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--from", dest="first", type=int, default=10, help="the first frame counted (default 10)")
    args, slam_args = parser.parse_known_args()
    trace = Trace()
    pipeline_module.progress = trace.counting(pipeline_module.progress)
    out = tempfile.mkdtemp(prefix="frame-path-")
    sys.setprofile(trace)
    try:
        rc = main(["slam", "--quiet", "--out", out, "--overwrite", *slam_args])
    finally:
        sys.setprofile(None)
    report(trace, args.first)
    return rc


if __name__ == "__main__":
    sys.exit(run())
