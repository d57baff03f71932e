"""Trajectory plots as PNG (matplotlib's Agg renderer through ``Figure``: no display, no pyplot state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from ti_fusion.errors import displayable
from ti_fusion.evaluation.metrics import align_rigid, trajectory_metrics
from ti_fusion.io.outputs import atomic_path

_AXES = "xyz"


def _top_view_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two world axes along which the camera moved most (x–z for a camera carried level)."""
    extent = positions.max(axis=0) - positions.min(axis=0)
    a, b = sorted(np.argsort(extent)[-2:])
    return int(a), int(b)


def metrics_line(metrics: dict) -> str:
    parts = [f"ATE RMSE {metrics['ate_rmse_m']:.4f} m"]
    if metrics.get("rpe_trans_m") is not None:
        delta = metrics.get("rpe_delta", 1)
        per = "frame" if delta == 1 else f"{delta} frames"
        parts.append(f"RPE {metrics['rpe_trans_m']:.4f} m, {metrics['rpe_rot_deg']:.3f}° per {per}")
    return "  ·  ".join(parts)


def _edge_points(loop_edges, est_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(from (m, 3), to (m, 3), applied (m,)) of loop edges given as (i, j, applied), i and j rows of
    ``est_poses``, or as (p_from, p_to, applied), two positions in the estimate's world frame."""
    p_from, p_to, applied = [], [], []
    for edge in loop_edges:
        if len(edge) != 3:
            raise ValueError(f"a loop edge is (from, to, applied), not {edge!r}")
        a, b, ok = edge
        ends = []
        for end in (a, b):
            if np.ndim(end) == 0:
                if not (float(end).is_integer() and 0 <= int(end) < len(est_xyz)):
                    raise ValueError(f"loop edge end {end!r} is not a row of the {len(est_xyz)} poses")
                ends.append(("row", int(end)))
            else:
                point = np.asarray(end, dtype=np.float64)
                if point.shape != (3,):
                    raise ValueError(f"loop edge end {end!r} is neither a row of the poses nor an x, y, z position")
                ends.append(("point", point))
        p_from.append(ends[0])
        p_to.append(ends[1])
        applied.append(bool(ok))
    return p_from, p_to, np.asarray(applied, bool)


def plot_trajectory(path_png: str | Path, est_poses, gt_poses=None, timestamps=None,
                    title: str = "Camera trajectory", metrics: dict | None = None, loop_edges=None) -> Path:
    """Write a PNG: top view (the plane of most motion) and x, y, z over time.

    ``est_poses`` and ``gt_poses`` are camera-to-world N×4×4, already paired (same length, same
    timestamps). With ground truth, the estimate is drawn after rigid alignment to it (as ATE measures
    it) and ATE/RPE go in the title (computed here unless ``metrics`` is given).

    ``loop_edges``: loop closures drawn in the top view as lines between two camera positions, applied
    ones green and solid with a ring at each end, the other candidates faint, red and dashed; each is
    (i, j, applied) with i, j rows of ``est_poses``, or (p_from, p_to, applied) with two positions in the
    estimate's world frame (aligned with it).
    """
    est = np.asarray(est_poses, dtype=np.float64).reshape(-1, 4, 4)
    gt = None if gt_poses is None else np.asarray(gt_poses, dtype=np.float64).reshape(-1, 4, 4)
    if gt is not None and len(gt) != len(est):
        raise ValueError(f"{len(est)} estimated poses for {len(gt)} ground-truth poses: associate them first")
    est_xyz = est[:, :3, 3]
    est_label = "estimate"
    edges = _edge_points(loop_edges or (), est_xyz)
    S = np.eye(4)
    if gt is not None and len(gt) > 0:
        metrics = metrics or trajectory_metrics(est, gt)
        S = align_rigid(est_xyz, gt[:, :3, 3])
        est_xyz = est_xyz @ S[:3, :3].T + S[:3, 3]
        est_label = "estimate (rigidly aligned)"
        title = f"{title}\n{metrics_line(metrics)}"
    elif metrics:
        title = f"{title}\n{metrics_line(metrics)}"

    if timestamps is None:
        t, t_label = np.arange(len(est), dtype=np.float64), "frame"
    else:
        t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if np.all(t == np.round(t)) and (len(t) < 2 or np.median(np.diff(t)) >= 1):
            t_label = "frame number (timestamp)"  # 7-Scenes, ICL-NUIM: frame numbers, not seconds
        else:
            t, t_label = t - t[0], "time [s] (from the first frame)"

    fig = Figure(figsize=(13, 6.5), dpi=100, layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=[1.1, 1.0])
    top = fig.add_subplot(grid[:, 0])
    series = [(est_xyz, est_label, "tab:blue", "-")]
    if gt is not None:
        series.insert(0, (gt[:, :3, 3], "ground truth", "0.2", "--"))
    a, b = _top_view_axes(series[0][0] if len(series[0][0]) else est_xyz)
    for xyz, label, color, style in series:
        top.plot(xyz[:, a], xyz[:, b], style, color=color, lw=1.5, label=label)
        if len(xyz):
            top.plot(xyz[0, a], xyz[0, b], "o", color=color, ms=6)
    _draw_loop_edges(top, edges, est_xyz, S, a, b)
    top.plot([], [], "o", color="0.5", label="start")
    top.set_xlabel(f"{_AXES[a]} [m]")
    top.set_ylabel(f"{_AXES[b]} [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.set_title(f"top view ({_AXES[a]}–{_AXES[b]} plane)")
    top.grid(True, alpha=0.3)
    top.legend(loc="best")

    for k in range(3):
        ax = fig.add_subplot(grid[k, 1])
        for xyz, label, color, style in series:
            ax.plot(t, xyz[:, k], style, color=color, lw=1.2, label=label)
        ax.set_ylabel(f"{_AXES[k]} [m]")
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.set_title("position per axis")
            ax.legend(loc="best", fontsize="small")
        if k == 2:
            ax.set_xlabel(t_label)
        else:
            ax.tick_params(labelbottom=False)
    fig.suptitle(displayable(title))
    path_png = Path(path_png)
    path_png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path_png) as tmp:  # whole or not at all; OutputError naming the file when it cannot be
        fig.savefig(tmp)
    return path_png


def _draw_loop_edges(ax, edges, est_xyz: np.ndarray, S: np.ndarray, a: int, b: int) -> None:
    """Loop edges on the top view (axes a, b): candidates not applied (rejected by verification or refused
    by the pose graph) thin, faint red and dashed under the trajectory (there can be hundreds, between
    look-alike places), applied loops green on top of it with a ring at each end (after the correction both
    ends are at the same place, so the line alone may vanish); the legend counts each. The ends given as
    positions take the estimate's alignment ``S``, those given as rows are read from ``est_xyz``."""
    p_from, p_to, applied = edges

    def where(end):
        kind, value = end
        return est_xyz[value] if kind == "row" else S[:3, :3] @ value + S[:3, 3]

    for ok in (False, True):
        pick = [k for k in range(len(applied)) if applied[k] == ok]
        if not pick:
            continue
        ends = np.array([[where(p_from[k])[[a, b]], where(p_to[k])[[a, b]]] for k in pick])
        if ok:
            ax.add_collection(LineCollection(ends, colors="tab:green", linewidths=2.0, zorder=4))
            ax.plot(ends[:, :, 0].ravel(), ends[:, :, 1].ravel(), "o", color="tab:green", mfc="none", ms=5,
                    zorder=4, label=f"loop closure (applied: {len(pick)})")
        else:
            ax.add_collection(LineCollection(ends, colors="tab:red", linewidths=0.8, linestyles="--", alpha=0.3,
                                             zorder=1, label=f"loop candidate (not applied: {len(pick)})"))
