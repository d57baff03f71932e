"""A second session against a saved map, against one continuous run over the same frames (docs/MAPS.md).

For each case, three (four) runs of ``ti-fusion slam`` in this process, as a user runs them:

1. the first session: frames [0, split), which saves its map (``map/`` in its run folder);
2. the second session: frames [split, end) with ``--map`` the first run (extending the map);
3. one continuous run over [0, end);
4. with ``--localize``: the second session again with ``--localize``, the saved map's bytes compared before
   and after, its processing rate against the extending session's.

and prints one table: the frame the second session found itself at (counted from its first frame) beside the
first frame that sees mapped space (the first of the session whose ground-truth view covers at least
``--seen`` of a 16×12 grid of its image with the saved map's surfels, which are in the ground truth's frame:
the first run starts at its first ground-truth pose); the ATE of the second session's frames in the map's
trajectory that the second session writes (``map_trajectory.tum``: both sessions' frames, the first's as the
second session's loops corrected them), aligned to the ground truth once over all of it, and that of the same
frames in the continuous run (aligned once over all of its frames); their ratio (the target: at most 1.2); the
same measure with the two sessions' trajectories as each wrote it (``trajectory.tum``: the first session's
keeps its own drift, which only a later loop can correct); the ATE over every frame, of the map's trajectory
and of the continuous run; and the ATE a perfect second session (the ground truth's poses for its frames)
would get aligned together with the first session's trajectory as it wrote it: that session's drift alone,
the floor of the as-written measure.

    .venv/bin/python scripts/bench_sessions.py                                 # redkitchen 0-249 | 250-499, the loop
    .venv/bin/python scripts/bench_sessions.py --cases loop --loop-second 300  # the loop's second lap cut short

Cases: ``redkitchen`` (``--data``, 7-Scenes, frames 0-249 saved, then 250-499) and ``loop`` (the synthetic loop
at ``--loop-downsample``: its first lap saved (``--loop-first``), then ``--loop-second`` frames of the second lap).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"
GRID = (16, 12)  # cells across and down the image that "sees mapped space" counts


def _slam(argv: list[str], out: Path) -> tuple[int, dict]:
    from ti_fusion.cli.main import main as cli

    code = cli(["slam", *argv, "--quiet", "--out", str(out)])
    summary = out / "summary.json"
    return code, json.loads(summary.read_text()) if summary.exists() else {}


def _trajectory(run: Path, name: str = "trajectory.tum") -> tuple[np.ndarray, np.ndarray]:
    from ti_fusion.io.trajectory import read_tum

    path = run / name
    if not path.exists():
        return np.zeros(0), np.zeros((0, 4, 4))
    stamps, poses = read_tum(path)
    return np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64)


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for name in sorted(p.name for p in folder.iterdir()):
        h.update(name.encode() + (folder / name).read_bytes())
    return h.hexdigest()


def _ground_truth(data_args: list[str]) -> tuple[np.ndarray, np.ndarray, object]:
    """(timestamps, poses, intrinsics) of every frame of the data the runs read (the dataset's own ground truth)."""
    from ti_fusion.cli.main import _apply_dataset_args, build_parser
    from ti_fusion.config import load_config
    from ti_fusion.io.datasets import open_dataset

    parser, _ = build_parser()
    args = parser.parse_args(["slam", *data_args])
    cfg = load_config(None, args.set)
    _apply_dataset_args(args, cfg)
    dataset = open_dataset(cfg.dataset, cfg.synth)
    if hasattr(dataset, "ground_truth"):
        stamps, poses = dataset.ground_truth()
    else:  # the synthetic sequence: its rendered path
        seq = dataset.sequence
        stamps, poses = np.asarray(seq.timestamps), np.asarray(seq.poses)
    return np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64), dataset.intrinsics


def _first_seeing(points: np.ndarray, poses: np.ndarray, K, seen: float) -> int | None:
    """The index of the first pose whose view covers at least ``seen`` of the image's grid cells with ``points``
    (world frame) between 0.3 and 4 m in front of it; None if none does."""
    pts = points[:: max(1, len(points) // 200_000)]
    for i, T in enumerate(poses):
        R, t = T[:3, :3], T[:3, 3]
        p = (pts - t) @ R  # world → camera
        z = p[:, 2]
        ok = (z > 0.3) & (z < 4.0)
        u = K.fx * p[ok, 0] / z[ok] + K.cx
        v = K.fy * p[ok, 1] / z[ok] + K.cy
        inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        cells = set(zip((u[inside] * GRID[0] / K.width).astype(int), (v[inside] * GRID[1] / K.height).astype(int)))
        if len(cells) >= seen * GRID[0] * GRID[1]:
            return i
    return None


def _ate_of(est_stamps, est, gt_stamps, gt, of_stamps) -> float | None:
    """RMSE of the ATE of the poses at ``of_stamps`` after one rigid alignment of all of ``est`` to the ground truth."""
    from ti_fusion.evaluation.metrics import associate_trajectories, ate_errors

    stamps, e, g = associate_trajectories(est_stamps, est, gt_stamps, gt)
    if len(e) < 3:
        return None
    errors, _ = ate_errors(e, g)
    keep = np.isin(np.round(stamps, 6), np.round(np.asarray(of_stamps), 6))
    return float(np.sqrt(np.mean(errors[keep] ** 2))) if keep.any() else None


def run_case(name: str, data: list[str], split: int, end: int, args) -> dict:
    from ti_fusion.evaluation.metrics import associate_trajectories
    from ti_fusion.slam.saved_map import load_map

    row = {"case": name, "first": f"0-{split - 1}", "second": f"{split}-{end - 1}"}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        gt_stamps, gt, K = _ground_truth(data + ["--frames", str(end)])
        watch = time.perf_counter()
        code, first = _slam(data + ["--frames", str(split)], tmp / "first")
        row["first_s"] = time.perf_counter() - watch
        if code != 0:
            return {**row, "error": f"first session exited with {code}"}
        digest = _digest(tmp / "first" / "map")
        second_args = data + ["--start", str(split), "--frames", str(end - split), "--map", str(tmp / "first")]
        code, second = _slam(second_args, tmp / "second")
        row["second_exit"] = code
        row["found_at"] = None if second.get("localised_at") is None else second["localised_at"] - split
        # the first frame of the second session that sees the saved map, by ground truth
        stamps_all = gt_stamps
        session = (stamps_all >= stamps_all[min(split, len(stamps_all) - 1)] - 1e-6)
        seeing = _first_seeing(load_map(tmp / "first").surfels["position"].astype(np.float64), gt[session], K,
                               args.seen)
        row["first_seeing"] = seeing
        a_stamps, a = _trajectory(tmp / "first")
        b_stamps, b = _trajectory(tmp / "second")
        joint_stamps, joint = np.concatenate([a_stamps, b_stamps]), np.concatenate([a, b])
        row["ate_sessions_m"] = _ate_of(joint_stamps, joint, gt_stamps, gt, b_stamps)
        # the same with the second session's poses the ground truth's: what the first session's own error costs
        # the second on this measure, whatever the second does (its trajectory is not the second session's to fix)
        perfect_stamps, _, perfect = associate_trajectories(b_stamps, b, gt_stamps, gt) if len(b_stamps) else (
            np.zeros(0), None, np.zeros((0, 4, 4)))
        row["ate_perfect_second_m"] = _ate_of(np.concatenate([a_stamps, perfect_stamps]),
                                              np.concatenate([a, perfect]), gt_stamps, gt, perfect_stamps)
        row["second_posed"] = len(b_stamps)
        # what the second session leaves of both: the map's trajectory, the first session's frames moved by its loops
        m_stamps, m = _trajectory(tmp / "second", "map_trajectory.tum")
        row["ate_map_m"] = _ate_of(m_stamps, m, gt_stamps, gt, b_stamps)
        row["ate_map_all_m"] = _ate_of(m_stamps, m, gt_stamps, gt, m_stamps)
        row["fps_extend"] = second.get("fps_processing")
        code, whole = _slam(data + ["--frames", str(end)], tmp / "whole")
        c_stamps, c = _trajectory(tmp / "whole")
        row["ate_continuous_m"] = _ate_of(c_stamps, c, gt_stamps, gt, c_stamps[c_stamps >= (b_stamps[0] if len(
            b_stamps) else np.inf) - 1e-6]) if len(c_stamps) else None
        row["ate_continuous_all_m"] = _ate_of(c_stamps, c, gt_stamps, gt, c_stamps) if len(c_stamps) else None
        if row["ate_map_m"] is not None and row["ate_continuous_m"]:
            row["ratio"] = row["ate_map_m"] / row["ate_continuous_m"]
        if row["ate_sessions_m"] is not None and row["ate_continuous_m"]:
            row["ratio_as_written"] = row["ate_sessions_m"] / row["ate_continuous_m"]
        if args.localize:
            code, localised = _slam(second_args + ["--localize"], tmp / "localised")
            row["localize_exit"] = code
            row["map_unchanged"] = _digest(tmp / "first" / "map") == digest
            row["fps_localize"] = localised.get("fps_processing")
            row["localize_unlocalised"] = localised.get("unlocalised_frames")
            row["localize_odometry"] = localised.get("odometry_frames")  # posed by odometry off the map
            d_stamps, d = _trajectory(tmp / "localised")
            row["ate_localize_m"] = _ate_of(np.concatenate([a_stamps, d_stamps]), np.concatenate([a, d]), gt_stamps,
                                            gt, d_stamps)
    return row


def _cell(value, spec: str = "") -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    return format(value, spec) if spec else str(value)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default="redkitchen,loop", help="comma-separated: redkitchen, loop")
    p.add_argument("--data", default=str(DEFAULT_DATA), help="the 7-Scenes folder of the redkitchen case")
    p.add_argument("--split", type=int, default=250, help="redkitchen: the second session's first frame")
    p.add_argument("--end", type=int, default=500, help="redkitchen: one past its last frame")
    p.add_argument("--downsample", type=int, default=1, help="redkitchen: --downsample")
    p.add_argument("--loop-downsample", type=int, default=2, help="the loop: --downsample")
    p.add_argument("--loop-first", type=int, default=0, help="the loop: frames of the first session (0 = one lap; "
                   "the scene's own length, once round and 3 m on, lets the first session close its loop)")
    p.add_argument("--loop-second", type=int, default=0, help="the loop: frames of the second session (0 = a lap)")
    p.add_argument("--seen", type=float, default=0.3, help="'sees mapped space': this fraction of the grid covered")
    p.add_argument("--no-localize", dest="localize", action="store_false", help="leave out the --localize run")
    p.add_argument("--arch", default="cpu")
    p.add_argument("--set", action="append", default=[], help="--set for every run")
    args = p.parse_args()
    unknown = [case for case in args.cases.split(",") if case not in ("redkitchen", "loop")]
    if unknown:
        p.error(f"--cases: no case {unknown[0]!r} (redkitchen, loop)")

    from ti_fusion.synthetic.scenes import LOOP_LENGTH, LOOP_SPEED
    from ti_fusion.synthetic.shapes import FPS

    common = ["--arch", args.arch, *[f"--set={s}" for s in args.set]]
    rows = []
    for case in args.cases.split(","):
        if case == "redkitchen":
            data = [args.data, "--downsample", str(args.downsample), *common]
            rows.append(run_case(case, data, args.split, args.end, args))
        else:  # the loop
            lap = int(round(LOOP_LENGTH / LOOP_SPEED * FPS))
            first, second = args.loop_first or lap, args.loop_second or lap
            data = ["--scene", "loop", "--downsample", str(args.loop_downsample), *common]
            rows.append(run_case(case, data, first, first + second, args))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)

    print("ATE of the second session's frames, each trajectory aligned to the ground truth once over all of it: "
          "map_trajectory.tum (both sessions, as the second's loops corrected them) against one continuous run; "
          "beside it, the two sessions' trajectory.tum as each wrote it, and the floor of that measure (a perfect "
          "second session with the first as written)")
    print("| case | first session | second session | found at (frame of the session) | first frame seeing the "
          "map | ATE, map_trajectory.tum | ATE, one continuous run, same frames | ratio (target <= 1.2) "
          "| ATE, every frame: map_trajectory.tum / continuous | ATE, the sessions as written (ratio) "
          "| a perfect second session with the first as written | --localize: map unchanged "
          "| fps processing: extend / --localize |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['case']} | {r['first']} | {r['second']} | {r['error']} | | | | | | | | | |")
            continue
        ate = lambda v: "—" if v is None else f"{v * 100:.2f} cm"
        print(f"| {r['case']} | {r['first']} | {r['second']} | {_cell(r['found_at'])} | {_cell(r['first_seeing'])} "
              f"| {ate(r['ate_map_m'])} | {ate(r['ate_continuous_m'])} | {_cell(r.get('ratio'), '.2f')} "
              f"| {ate(r['ate_map_all_m'])} / {ate(r['ate_continuous_all_m'])} "
              f"| {ate(r['ate_sessions_m'])} ({_cell(r.get('ratio_as_written'), '.2f')}) "
              f"| {ate(r.get('ate_perfect_second_m'))} | {_cell(r.get('map_unchanged'))} "
              f"| {_cell(r.get('fps_extend'))} / {_cell(r.get('fps_localize'))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
