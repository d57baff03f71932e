"""Measure a candidate default on every synthetic scene (and a real sequence) against another setting.

Runs ``ti-fusion slam`` once per scene × seed × variant (a variant is a name and ``--set`` overrides; the
first is the column compared against) and prints a Markdown table of the ATE over all frames, the lost
frames and the frames on which a second ICP start was tried, read from each run's ``summary.json``. A run
whose summary is already in the output folder is read, not run again, so an interrupted table resumes.

    python scripts/bench_defaults.py --variant depth:icp.color_weight=0 --variant colour:icp.color_weight=0.01 \
        --scenes room,wall,corridor,jerky,cabinet --seeds 0,11,23 \
        --real ../shared/data/redkitchen-7scenes:0:200 --out /tmp/bench_defaults

Accuracy and counts only: the machine this runs on is usually shared, so no frame rates are printed.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from ti_fusion.cli import main; sys.argv[0] = 'ti-fusion'; sys.exit(main())"]


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``name:section.key=value,section.key=value`` (``name:`` alone = the defaults)."""
    name, _, sets = text.partition(":")
    if not name:
        raise SystemExit(f"--variant {text!r}: give it a name before ':'")
    return name, [s for s in sets.split(",") if s]


def run_one(out: Path, source: list[str], sets: list[str], extra: list[str]) -> dict | None:
    """The run's summary, running it first unless ``out`` already holds one."""
    summary = out / "summary.json"
    if not summary.exists():
        cmd = [*CLI, "slam", *source, "--quiet", "--overwrite", "--out", str(out), *extra]
        for s in sets:
            cmd += ["--set", s]
        print("$ ti-fusion", " ".join(cmd[3:]), file=sys.stderr, flush=True)
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if done.returncode != 0 or not summary.exists():
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            print(f"  failed (exit {done.returncode}): {tail[0]}", file=sys.stderr, flush=True)
            return None
    return json.loads(summary.read_text())


def cell(s: dict | None) -> str:
    if s is None:
        return "failed"
    ate = s.get("ate_rmse_m")
    if ate is None:
        return "no ATE"
    lost = s.get("untracked_frames", s.get("tracking_failures", 0))
    text = f"{ate * 100:.2f} cm ({s.get('ate_percent_of_path', float('nan')):.2f} %), {lost} lost"
    if lost:
        text += f" (tracked alone {s['ate_tracked_only_rmse_m'] * 100:.2f} cm)"
    if s.get("keyframes"):  # loop closure ran: its loops, none included
        text += f", {s.get('loops_applied', 0)} loops"
        if s.get("loops_refused"):
            text += f" ({len(s['loops_refused'])} refused)"
    return text + f", 2nd start on {s.get('frames_with_second_start', 0)}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variant", action="append", required=True,
                   help="NAME:SECTION.KEY=VALUE[,...] (repeat; NAME: alone = the defaults)")
    p.add_argument("--scenes", default="room,wall,corridor,jerky,cabinet",
                   help="synthetic scenes, comma-separated; NAME@ARGS adds CLI arguments, e.g. room@--stride=20")
    p.add_argument("--seeds", default="0", help="synth.seed values, comma-separated")
    p.add_argument("--frames", type=int, default=0, help="frames per synthetic run; 0 = the scene's own length")
    p.add_argument("--downsample", type=int, default=2)
    p.add_argument("--real", action="append", default=[],
                   help="PATH[:START:STOP] of a real sequence (run once, without --downsample)")
    p.add_argument("--set", action="append", default=[], help="SECTION.KEY=VALUE for every run")
    p.add_argument("--out", type=Path, default=Path("/tmp/bench_defaults"))
    a = p.parse_args()
    variants = [parse_variant(v) for v in a.variant]

    rows: list[tuple[str, list[dict | None]]] = []
    for spec in [s for s in a.scenes.split(",") if s]:
        scene, _, args = spec.partition("@")
        extra = [x.replace("=", " ", 1) for x in args.split("@") if x]
        extra = [w for x in extra for w in x.split(" ")]
        for seed in [int(x) for x in a.seeds.split(",")]:
            source = ["--scene", scene, "--downsample", str(a.downsample)]
            if a.frames:
                source += ["--frames", str(a.frames)]
            label = f"{scene}{' ' + ' '.join(extra) if extra else ''}, seed {seed}"
            tag = f"{scene}{''.join(extra).replace('-', '_').replace('/', '_')}-s{seed}"
            cells = [run_one(a.out / f"{tag}-{name}", source, [*a.set, f"synth.seed={seed}", *sets], extra)
                     for name, sets in variants]
            rows.append((label, cells))
    for real in a.real:
        path, *span = real.split(":")
        source = [path] + (["--start", span[0], "--stop", span[1]] if len(span) == 2 else [])
        tag = Path(path).name + ("-" + "-".join(span) if span else "")
        cells = [run_one(a.out / f"{tag}-{name}", source, [*a.set, *sets], []) for name, sets in variants]
        rows.append((f"{Path(path).name} {'–'.join(span) if span else 'all'}", cells))

    print("| scene / split | " + " | ".join(f"{n} ({', '.join(s) or 'defaults'})" for n, s in variants) + " |")
    print("| --- " * (len(variants) + 1) + "|")
    for label, cells in rows:
        print(f"| {label} | " + " | ".join(cell(c) for c in cells) + " |")


if __name__ == "__main__":
    main()
