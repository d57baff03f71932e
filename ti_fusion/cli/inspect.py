"""``ti-fusion inspect LOG.mcap|MAP``: what a run log holds, and how the run went; what a saved map holds.

Prints the channels (topic, schema, encoding, message count), the time range, the metadata records
and a summary of the per-frame stats: median and max milliseconds per stage (the ``ms`` dict of each
stats message; a plain number is the frame's total, as ``vo`` logs it), tracking failures (a ``status``
that is not a success: ``failed``) and, when ground truth was logged, the ATE of /camera/pose against
/gt/pose. ``--plot`` draws the stats over the frames to a PNG. A saved map (its folder or map.json), or a run
folder holding one (``map/``), adds what is in it: camera, surfels, keyframes, loops, extent, every checksum
verified (docs/MAPS.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.evaluation.metrics import associate_trajectories, ate_errors
from ti_fusion.io.mcap_log import LogContents, read_log
from ti_fusion.io.outputs import atomic_path, describe_run, run_in_progress

HELP = ("summarise an MCAP run log (channels, time range, ms per stage, failures, ATE; --plot for a PNG) or a "
        "saved map")
USES_DATASET = False
USES_TAICHI = False


def add_arguments(parser) -> None:
    parser.add_argument("log", metavar="LOG|MAP", help="an MCAP log written by slam or vo (log.mcap), a saved map "
                                                       "(its folder or map.json), or a run folder holding either")
    parser.add_argument("--plot", metavar="PNG", nargs="?", const="stats.png", default=None,
                        help="plot the stats over the frames to this PNG (default name stats.png; "
                             "a relative path goes into the --out folder)")


def writes_files(args) -> bool:
    """inspect only reads, unless asked for a plot or a summary.json (--out): no folder otherwise."""
    return bool(args.out or args.plot)


def run(ctx) -> dict:
    from ti_fusion.io.map_files import find_map_folder

    given = Path(ctx.args.log)
    has_map = find_map_folder(given) is not None
    if has_map and not (given.is_dir() and (given / "log.mcap").is_file()):  # a saved map, or a run with no log
        if ctx.args.plot:
            from ti_fusion.errors import InputError

            raise InputError(given, "--plot draws a log's stats: this holds a saved map and no log.mcap")
        summary = {"saved_map": summarise_map(given)}
        print(format_map(summary["saved_map"]), flush=True)
        return summary
    log = read_log(ctx.args.log)
    summary = summarise(log)
    summary["writer"] = run_in_progress(log.path.parent) if not log.complete else None
    print(format_report(log, summary), flush=True)
    if has_map:  # a run folder: its saved map too
        summary["saved_map"] = summarise_map(given)
        print(format_map(summary["saved_map"]), flush=True)
    if ctx.args.plot:
        plot = Path(ctx.args.plot)
        plot = plot if plot.is_absolute() else ctx.out.file(str(plot))
        plot_stats(log, plot)
        summary["plot"] = str(plot)
        print(f"plot: {plot}", flush=True)
    return summary


# --------------------------------------------------------------------------------------------------


def summarise_map(path: Path) -> dict:
    """What a saved map holds (``ti_fusion/io/map_files.py``), every array's checksum verified on the way."""
    from dataclasses import asdict

    from ti_fusion.io.map_files import map_folder
    from ti_fusion.slam.saved_map import load_map

    folder = map_folder(path)
    saved = load_map(folder)  # a damaged header is one InputError line there, as for a session
    position, weight = saved.surfels["position"], saved.surfels["weight"]
    confirmed = saved.make_config().fusion.unstable_weight
    camera = asdict(saved.intrinsics)
    return {"folder": str(folder), "version": saved.version,
            "bytes": sum(p.stat().st_size for p in folder.iterdir() if p.is_file()),
            "camera": {k: camera[k] for k in ("fx", "fy", "cx", "cy", "width", "height")},
            "map_level": saved.map_level, "surfels": saved.count,
            "confirmed_surfels": int(np.count_nonzero(weight >= confirmed)), "confirmed_weight": confirmed,
            "keyframes": len(saved.keyframes), "frames_fused": saved.frames_fused,
            "last_frame": saved.last_frame, "loops_applied": len(saved.loops.get("applied", [])),
            "trajectory_frames": len(saved.trajectory), "sessions": saved.trajectory.sessions,
            "extent_m": None if not len(position) else
            [[round(float(v), 3) for v in position.min(axis=0)], [round(float(v), 3) for v in position.max(axis=0)]],
            "checksums": "verified"}


def format_map(m: dict) -> str:
    c = m["camera"]
    lines = [f"saved map: {m['folder']} (format version {m['version']}, {m['bytes'] / 1e6:.1f} MB, every checksum "
             "verified)",
             f"  camera    fx={c['fx']:g} fy={c['fy']:g} cx={c['cx']:g} cy={c['cy']:g} at {c['width']}x{c['height']}, "
             f"the map at pyramid level {m['map_level']}",
             f"  surfels   {m['surfels']:,} ({m['confirmed_surfels']:,} confirmed: confidence >= "
             f"{m['confirmed_weight']:g})",
             f"  keyframes {m['keyframes']}, {m['frames_fused']} frames fused (the last frame {m['last_frame']}), "
             f"{m['loops_applied']} loops applied",
             f"  trajectory {m['trajectory_frames']} posed frames of {m['sessions']} session(s)"
             + (" (a version 1 map keeps none)" if m["version"] == 1 else "")]
    if m["extent_m"] is not None:
        lo, hi = m["extent_m"]
        lines.append("  extent    " + ", ".join(f"{a} {lo[i]:.2f} to {hi[i]:.2f} m" for i, a in enumerate("xyz")))
    return "\n".join(lines)


# Statuses of a frame that was tracked: slam's "ok" (and "relocalised", a frame recovered by feature
# matching, which its summary.json does not count as a failure either), vo's "accepted".
SUCCESS_STATUSES = ("ok", "init", "relocalised", "accepted")


def failed(stats: dict) -> bool:
    """Whether a stats message reports a tracking failure (slam's "lost: ...", vo's "rejected: ..."; not slam's
    "skipped: ...", a frame before the map started, which its summary.json counts apart)."""
    status = stats.get("status")
    return status is not None and status not in SUCCESS_STATUSES and not status.startswith("skipped")


def summarise(log: LogContents) -> dict:
    """The figures inspect prints, as summary.json fields."""
    ms = stage_ms(log.stats)
    failures = [(s.get("frame", i), s.get("status")) for i, s in enumerate(log.stats) if failed(s)]
    ate_rmse, ate_poses = _ate_rmse(log)
    return {
        "frames": len(log.stats),
        "log": str(log.path),
        "complete": log.complete,
        "channels": {t: {"schema": c.schema_name, "encoding": c.message_encoding, "count": c.count}
                     for t, c in log.channels.items()},
        "messages": log.message_count,
        "time_range_s": None if log.start_s is None else [log.start_s, log.end_s],
        "duration_s": None if log.start_s is None else round(log.end_s - log.start_s, 6),
        "metadata": sorted(log.metadata),
        "stats_topic": log.stats_topic,
        "ms_per_stage": {k: {"median": round(float(np.median(v)), 3), "max": round(float(np.max(v)), 3)}
                         for k, v in ms.items()},
        "tracking_failures": len(failures),
        "failed_frames": [{"frame": f, "status": s} for f, s in failures],
        "ate_rmse_m": None if ate_rmse is None else round(ate_rmse, 6),
        "ate_poses": ate_poses,
    }


def format_report(log: LogContents, summary: dict) -> str:
    writer = summary.get("writer")
    if log.complete:
        state = ""
    elif writer is not None:
        state = f"  (still being written by a run: {describe_run(writer)}; read up to its last whole chunk)"
    else:
        state = "  (NOT finalised: the run was killed; read up to the last whole chunk)"
    lines = [f"log: {log.path}{state}"]
    width = max([len(t) for t in log.channels] + [5])
    swidth = max([len(c.schema_name) for c in log.channels.values()] + [6])
    lines.append(f"  {'topic':<{width}}  {'schema':<{swidth}}  {'encoding':<9} {'count':>7}")
    for c in log.channels.values():
        lines.append(f"  {c.topic:<{width}}  {c.schema_name:<{swidth}}  {c.message_encoding:<9} {c.count:>7}")
    if log.start_s is None:
        lines.append("time range: no messages")
    else:
        lines.append(f"time range: {log.start_s:.6f} .. {log.end_s:.6f} s ({log.end_s - log.start_s:.3f} s)")
    if log.metadata:
        lines.append("metadata: " + ", ".join(sorted(log.metadata)))
    if log.stats_topic:
        lines.append(f"stats ({log.stats_topic}, {len(log.stats)} frames):")
        if summary["ms_per_stage"]:
            lines.append(f"  {'stage':<12} {'median ms':>10} {'max ms':>10}")
            for stage, v in summary["ms_per_stage"].items():
                lines.append(f"  {stage:<12} {v['median']:>10.2f} {v['max']:>10.2f}")
        failed = summary["failed_frames"]
        shown = ", ".join(f"{f['frame']} ({f['status']})" for f in failed[:10])
        more = f", ... {len(failed) - 10} more" if len(failed) > 10 else ""
        lines.append(f"tracking failures: {len(failed)}" + (f": {shown}{more}" if failed else ""))
    else:
        lines.append("stats: none logged")
    if summary["ate_rmse_m"] is not None:
        lines.append(f"ATE RMSE: {summary['ate_rmse_m']:.4f} m over {summary['ate_poses']} poses "
                     "(rigidly aligned to ground truth)")
    elif summary["ate_poses"]:
        lines.append(f"ATE: not computed from {summary['ate_poses']} pose pair(s) with the ground truth: a rigid "
                     f"alignment of fewer than {MIN_ATE_POSES} fits them exactly")
    elif len(log.gt_times):
        lines.append("ATE: no estimated pose shares a time with the ground truth")
    return "\n".join(lines)


def _stage_dict(stats: dict) -> dict[str, float]:
    """A stats message's ``ms`` as {stage: ms}: a dict's numeric entries, or a plain number as the total."""
    ms = stats.get("ms")
    if _is_number(ms):
        return {"total": float(ms)}
    if isinstance(ms, dict):
        return {k: float(v) for k, v in ms.items() if _is_number(v)}
    return {}


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def stage_ms(stats: list[dict]) -> dict[str, np.ndarray]:
    """{stage: ms per frame} from the ``ms`` of each stats message, plus their ``total``."""
    stages: dict[str, list[float]] = {}
    per_frame = [_stage_dict(s) for s in stats]
    for ms in per_frame:
        for k, v in ms.items():
            stages.setdefault(k, []).append(v)
    out = {k: np.asarray(v) for k, v in stages.items()}
    if out and "total" not in out:
        out["total"] = np.asarray([sum(ms.values()) for ms in per_frame if ms])
    return out


# A rigid alignment fits one or two positions exactly: their "error" would be zero whatever the tracking did
MIN_ATE_POSES = 3


def _ate_rmse(log: LogContents) -> tuple[float | None, int]:
    """(ATE RMSE of /camera/pose against /gt/pose after the rigid alignment of ``evaluation``, or None
    with fewer than MIN_ATE_POSES pairs; the number of pose pairs), poses paired by log time."""
    if not len(log.gt_times) or not len(log.est_times):
        return None, 0
    # both are logged at the frame's time: pair equal times only
    _, est, gt = associate_trajectories(log.est_times, log.est_poses, log.gt_times, log.gt_poses,
                                        max_difference=1e-6)
    if len(est) < MIN_ATE_POSES:
        return None, len(est)
    errors, _ = ate_errors(est, gt)
    return float(np.sqrt(np.mean(errors**2))), len(est)


# --------------------------------------------------------------------------------------------------

# Panels after the ms one: (title, test on a flattened stats key). First match wins.
_PANELS = [
    ("inlier ratio", lambda k: "inlier" in k and "ratio" in k),
    ("inliers", lambda k: "inlier" in k),
    ("residual", lambda k: "residual" in k),
    ("surfels", lambda k: "surfel" in k),
    ("features", lambda k: "match" in k or "keypoint" in k),
]


def _flatten(d: dict, prefix: str = "") -> dict[str, float]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def plot_stats(log: LogContents, path: Path) -> Path:
    """ms per stage (stacked), then inliers, residual, surfel count... over the frames; failures in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stats = log.stats
    frames = np.array([s.get("frame", i) for i, s in enumerate(stats)], dtype=float)
    flat = [_flatten(s) for s in stats]
    series: dict[str, dict[str, np.ndarray]] = {}
    for key in sorted({k for f in flat for k in f}):
        if key == "frame" or key.startswith("ms."):
            continue
        for title, wanted in _PANELS:
            if wanted(key.lower()):
                series.setdefault(title, {})[key] = np.array([f.get(key, np.nan) for f in flat])
                break
    titles = [t for t, _ in _PANELS if t in series]
    fig, axes = plt.subplots(1 + len(titles), 1, figsize=(10, 2.6 * (1 + len(titles))), sharex=True,
                             squeeze=False)
    axes = axes[:, 0]

    all_ms = stage_ms(stats)
    ms = {k: v for k, v in all_ms.items() if k != "total"} or all_ms  # vo logs only a total
    ax = axes[0]
    if ms and all(len(v) == len(frames) for v in ms.values()):
        ax.stackplot(frames, *ms.values(), labels=list(ms), alpha=0.85)
        ax.legend(loc="upper right", fontsize=8, ncol=min(len(ms), 6))
    elif ms:
        for k, v in ms.items():
            ax.plot(np.arange(len(v)), v, label=k)
        ax.legend(loc="upper right", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no per-stage timings logged", ha="center", va="center", transform=ax.transAxes)
    total = all_ms.get("total")
    if total is not None and len(total) == len(frames) > 5:
        # The first frame's kernel compilation can dwarf the rest: clip it and say so.
        top = 1.25 * float(np.percentile(total, 98))
        if total.max() > 2 * top:
            ax.set_ylim(0, top)
            i = int(np.argmax(total))
            ax.annotate(f"frame {frames[i]:g}: {total[i]:.0f} ms (clipped)", xy=(frames[i], top),
                        xytext=(5, -12), textcoords="offset points", fontsize=8)
    ax.set_ylabel("ms per frame")
    ax.set_title(f"{log.path.name}: {len(stats)} frames" + ("" if log.complete else " (not finalised)"))

    for ax, title in zip(axes[1:], titles):
        for key, values in series[title].items():
            ax.plot(frames, values, marker=".", markersize=3, linewidth=1, label=key)
        ax.set_ylabel(title)
        ax.legend(loc="upper right", fontsize=8)

    failures = [frames[i] for i, s in enumerate(stats) if failed(s)]
    for ax in axes:
        ax.grid(True, alpha=0.3)
        for f in failures:
            ax.axvline(f, color="red", alpha=0.5, linewidth=1)
    axes[-1].set_xlabel("frame" + (" (red: tracking failure)" if failures else ""))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path
