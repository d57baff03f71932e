"""What a batch folder knows of its jobs, and the results it writes from that.

Each job has a record, ``jobs/<job>.json``: its arguments, status (``done``, ``failed``, ``interrupted``),
exit code, error line, wall time, and the figures of its run's own ``summary.json`` (read by the job, never
parsed from its output). The table and the plot are written from the records alone, so a batch resumed,
or stopped half-way, writes the same rows for the jobs it did not run again.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from ti_fusion.io.outputs import atomic_write, jsonable

DONE, FAILED, INTERRUPTED, NOT_RUN = "done", "failed", "interrupted", "not run"

# The table's columns: (name, what it holds). ATE and RPE only where the input has ground truth.
COLUMNS = (
    ("input", "the manifest's input"),
    ("variant", "the variant ('' without variants)"),
    ("status", "done, failed, interrupted (Ctrl-C: runs again on resume) or not run"),
    ("exit", "the job's exit code (negative: killed by that signal)"),
    ("frames", "frames processed (summary.json frames)"),
    ("failures", "tracking failures (summary.json tracking_failures)"),
    ("ate_m", "ATE RMSE over all frames, metres"),
    ("rpe_trans_m", "RPE translation, metres"),
    ("rpe_rot_deg", "RPE rotation, degrees"),
    ("fps_processing", "frames per second of tracking, fusion and logging after the warm-up"),
    ("fps_wall", "frames per second of the whole loop"),
    ("wall_s", "seconds from the job's process start to its end (start-up and compiling included)"),
    ("error", "why the job failed: its one-line error, or the signal that killed it"),
    ("run_dir", "the job's run folder, relative to the batch folder"),
)
# summary.json key of each figure column
_FROM_SUMMARY = {"frames": "frames", "failures": "tracking_failures", "ate_m": "ate_rmse_m",
                 "rpe_trans_m": "rpe_trans_m", "rpe_rot_deg": "rpe_rot_deg",
                 "fps_processing": "fps_processing", "fps_wall": "fps_wall"}
# the summary.json fields a record keeps
SUMMARY_FIELDS = tuple(_FROM_SUMMARY.values()) + ("wall_s", "ate_frames", "path_length_m", "surfels", "backend")


def record_path(batch: Path, job_name: str) -> Path:
    return batch / "jobs" / f"{job_name}.json"


def run_dir(batch: Path, job_name: str) -> Path:
    return batch / "runs" / job_name


def log_path(batch: Path, job_name: str) -> Path:
    return batch / "jobs" / f"{job_name}.log"


def read_record(batch: Path, job_name: str) -> dict | None:
    try:
        return json.loads(record_path(batch, job_name).read_text())
    except (OSError, ValueError):  # none yet, or one cut short by a crash: the job runs again
        return None


def write_record(batch: Path, record: dict) -> None:
    path = record_path(batch, record["job"])
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        f.write(json.dumps(jsonable(record), indent=2) + "\n")


def rows(batch: Path, jobs) -> list[dict]:
    """One row per job, in the manifest's order, from the records (``not run`` where there is none)."""
    out = []
    for job in jobs:
        rec = read_record(batch, job.name)
        if rec is not None and tuple(rec.get("args", ())) != job.args:
            rec = None  # a record of other options: not this job's result
        summary = (rec or {}).get("summary") or {}
        row = {"input": job.input, "variant": job.variant, "status": (rec or {}).get("status", NOT_RUN),
               "exit": (rec or {}).get("exit_code"), "wall_s": (rec or {}).get("wall_s"),
               "error": (rec or {}).get("error") or "", "run_dir": f"runs/{job.name}", "job": job.name}
        for column, key in _FROM_SUMMARY.items():
            row[column] = summary.get(key)
        out.append(row)
    return out


def write_tables(batch: Path, table: list[dict]) -> tuple[Path, Path]:
    """results.csv (full precision) and results.md (rounded, ATE in cm, RPE in mm)."""
    names = [c for c, _ in COLUMNS]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=names, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in table:
        writer.writerow({k: "" if row.get(k) is None else row[k] for k in names})
    csv_path, md_path = batch / "results.csv", batch / "results.md"
    with atomic_write(csv_path) as f:
        f.write(text.getvalue())
    with atomic_write(md_path) as f:
        f.write(markdown(table) + "\n")
    return csv_path, md_path


def markdown(table: list[dict]) -> str:
    head = ["input", "variant", "status", "exit", "frames", "failures", "ATE cm", "RPE mm", "RPE deg",
            "fps proc", "fps wall", "wall s", "error", "run folder"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table:
        cells = [r["input"], r["variant"], r["status"], _fmt(r["exit"], "d"), _fmt(r["frames"], "d"),
                 _fmt(r["failures"], "d"), _fmt(r["ate_m"], ".3f", 100), _fmt(r["rpe_trans_m"], ".2f", 1000),
                 _fmt(r["rpe_rot_deg"], ".3f"), _fmt(r["fps_processing"], ".1f"), _fmt(r["fps_wall"], ".1f"),
                 _fmt(r["wall_s"], ".1f"), str(r["error"]).replace("|", "\\|"), r["run_dir"]]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines)


def _fmt(value, spec: str, scale: float = 1) -> str:
    if value is None:
        return ""
    return format(int(value) if spec == "d" else value * scale, spec)


def plot_ate(batch: Path, table: list[dict], inputs, variants) -> Path:
    """ate.png: a bar per input per variant (ATE in cm; log scale when the ATEs span more than 100×);
    an input without ground truth, or a job that did not finish, is written where its bar would be."""
    from matplotlib.figure import Figure  # not pyplot: drawn on a thread while Ray stops, and its state is global

    variants = list(variants) or [""]
    by = {(r["input"], r["variant"]): r for r in table}
    width = 0.8 / len(variants)
    fig = Figure(figsize=(max(5.0, 1.2 * len(inputs) * max(1, len(variants)) ** 0.5 + 2), 4), dpi=110)
    ax = fig.add_subplot()
    values = [r["ate_m"] * 100 for r in table if r["ate_m"] is not None and r["ate_m"] > 0]
    log = bool(values) and max(values) > 100 * min(values)
    floor = min(values) if values else 1.0
    for k, variant in enumerate(variants):
        xs = [i - 0.4 + width * (k + 0.5) for i in range(len(inputs))]
        heights = []
        for x, name in zip(xs, inputs):
            row = by.get((name, variant))
            ate = None if row is None else row["ate_m"]
            if ate is None or not math.isfinite(ate):
                why = "no GT" if row is not None and row["status"] == DONE else (row["status"] if row else "")
                ax.text(x, floor if log else 0, why, rotation=90, ha="center", va="bottom", fontsize=7, color="0.4")
                heights.append(float("nan"))
            else:
                heights.append(ate * 100)
        ax.bar(xs, heights, width * 0.95, label=variant or None)
    ax.set_xticks(range(len(inputs)), inputs, rotation=20, ha="right", fontsize=8)
    ax.set_xlim(-0.5, len(inputs) - 0.5)  # the groups with no bar (failed, no ground truth) stay in view
    ax.set_ylabel("ATE RMSE (cm)")
    if log:
        ax.set_yscale("log")
    ax.set_title("ATE per input" + (" per variant" if variants != [""] else ""))
    if variants != [""]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = batch / "ate.png"
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png")
    return path
