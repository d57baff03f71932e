"""``ti-fusion icp DATA --source 10 --target 50``: align two frames with coarse-to-fine point-to-plane ICP.

The classic assignment's ICP experiment. Prints the per-iteration table (pyramid level, iteration, loss =
mean squared point-to-plane residual, inliers), the final pose (source camera → target camera,
p_target = T p_source) and, when the set has ground truth, its error against the reference relative pose
inv(T_wc_target) · T_wc_source. Writes ``icp.png``: the two clouds in the target camera frame before
(initial pose) and after ICP, from a fixed viewpoint, source orange and target blue.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ti_fusion.io.datasets import Frame, open_dataset
from ti_fusion.errors import InputError
from ti_fusion.geometry import invert, pose_error
from ti_fusion.io.outputs import atomic_path
from ti_fusion.tracking.icp import ICP, ICPResult
from ti_fusion.kernels.pyramid import FramePyramid
from ti_fusion.slam.dense import coarse_level_warning
from ti_fusion.timing import Stopwatch

log = logging.getLogger(__name__)

HELP = "align two frames with coarse-to-fine point-to-plane ICP: iterations, pose, error vs ground truth, PNG"
USES_DATASET = True
USES_TAICHI = True


def _identity(source: Frame, target: Frame, ctx) -> np.ndarray:
    return np.eye(4)


def _features(source: Frame, target: Frame, ctx) -> np.ndarray:
    """ORB + PnP RANSAC (ti_fusion.tracking.features): for motions too large for ICP from the identity."""
    from ti_fusion.tracking.features import estimate_relative_pose

    est = estimate_relative_pose(source, target, ctx.config.vo)
    if est.pose is None:
        print(f"features: no initial pose ({est.reason}: {est.good} good matches, {est.inliers} inliers); "
              "starting from the identity", flush=True)
        return np.eye(4)
    print(f"features: {est.good} good matches, {est.inliers} RANSAC inliers", flush=True)
    return est.pose


# --init choices: name → function(source frame, target frame, ctx) returning the initial 4×4 pose
# (source camera → target camera). Add an entry to offer another initialiser.
INITIALISERS: dict[str, Callable[[Frame, Frame, object], np.ndarray]] = {"identity": _identity,
                                                                          "features": _features}


def add_arguments(parser) -> None:
    parser.add_argument("--source", type=int, default=10, help="dataset frame number of the source (default 10)")
    parser.add_argument("--target", type=int, default=50, help="dataset frame number of the target (default 50)")
    parser.add_argument("--init", choices=tuple(INITIALISERS), default="identity",
                        help="initial pose of the source in the target camera (default identity)")


def _frame(dataset, option: str, index: int) -> Frame:
    try:
        return dataset.frame_by_raw_index(index)
    except (IndexError, KeyError):
        n = dataset._num_raw_frames()
        frames = f"frames 0 to {n - 1}" if n > 1 else "only frame 0"
        if dataset.format == "synthetic":  # no folder to name
            raise InputError(None, f"{option} {index}: the synthetic sequence has {frames}") from None
        raise InputError(dataset.root, f"{option} {index}: no such frame (the sequence has {frames})") from None


def _maps(frame: Frame, cfg) -> FramePyramid:
    K = frame.intrinsics
    pyramid = FramePyramid(cfg.pyramid, K.height, K.width, len(cfg.icp.iterations))
    pyramid.compute(frame.depth, K)
    return pyramid


def _print_result(result: ICPResult) -> None:
    print(f"{'level':>5} {'iter':>4} {'loss (m²)':>11} {'rms (mm)':>9} {'inliers':>8} {'|δξ|':>9}")
    for r in result.iterations:
        print(f"{r.level:>5} {r.iteration:>4} {r.loss:>11.4e} {1e3 * np.sqrt(r.loss):>9.3f} {r.inliers:>8} "
              f"{r.update_norm:>9.2e}")
    status = "converged" if result.converged else f"not converged{': ' + result.failure if result.failure else ''}"
    print(f"{status}; inliers {result.inliers} ({100 * result.inlier_ratio:.1f}% of valid source pixels), "
          f"cond(AᵀA) {result.condition:.3g}")
    print("pose (source camera → target camera):")
    for row in result.pose:
        print("  [" + "  ".join(f"{x: .6f}" for x in row) + "]")


def _cloud(frame: Frame, step: int) -> np.ndarray:
    K = frame.intrinsics
    z = frame.depth[::step, ::step].astype(np.float64)
    v, u = np.mgrid[0:frame.depth.shape[0]:step, 0:frame.depth.shape[1]:step]
    pts = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=-1).reshape(-1, 3)
    return pts[pts[:, 2] > 0]


def _viewer(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed virtual camera (rotation with columns right, down, forward; and its centre) behind, above
    and to the right of the target camera, looking at the middle of the target cloud."""
    center = np.median(points, axis=0)
    eye = center + np.array([0.9, -1.3, -2.4]) * max(center[2], 0.5) / 2.0
    forward = (center - eye) / np.linalg.norm(center - eye)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward], axis=1), eye


def save_figure(path, source: Frame, target: Frame, before: np.ndarray, after: np.ndarray, title: str) -> None:
    """Two panels, before and after: both clouds in the target camera frame seen by one fixed virtual
    camera, drawn far to near so that nearer points hide farther ones."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    step = max(1, int(np.sqrt(source.depth.size / 40000)))  # about 40k points per cloud
    src, tgt = _cloud(source, step), _cloud(target, step)
    R, eye = _viewer(tgt)
    colors = np.array([[0.12, 0.40, 0.85], [0.98, 0.55, 0.05]])  # target blue, source orange
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.8), dpi=110)
    for ax, (name, T) in zip(axes, (("before (initial pose)", before), ("after ICP", after))):
        pts = np.concatenate([tgt, src @ T[:3, :3].T + T[:3, 3]])
        which = np.concatenate([np.zeros(len(tgt), int), np.ones(len(src), int)])
        cam = (pts - eye) @ R
        keep = cam[:, 2] > 0.1
        cam, which = cam[keep], which[keep]
        order = np.argsort(-cam[:, 2])
        cam, which = cam[order], which[order]
        ax.scatter(cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2], s=0.6, c=colors[which], linewidths=0)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_axis_off()
        ax.set_title(name)
    axes[0].legend(handles=[Patch(color=colors[1], label=f"source (frame {source.index})"),
                            Patch(color=colors[0], label=f"target (frame {target.index})")],
                   loc="lower left", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:  # whole or not at all; OutputError naming the file when it cannot be
            fig.savefig(tmp)
    finally:
        plt.close(fig)


def run(ctx) -> dict:
    cfg = ctx.config
    args = ctx.args
    dataset = open_dataset(cfg.dataset, cfg.synth)
    source, target = _frame(dataset, "--source", args.source), _frame(dataset, "--target", args.target)
    if source.depth.shape != target.depth.shape:
        raise InputError(dataset.root, f"frames {args.source} and {args.target} differ in size")
    init = np.asarray(INITIALISERS[args.init](source, target, ctx), dtype=np.float64)

    watch = Stopwatch()
    src_maps, tgt_maps = _maps(source, cfg), _maps(target, cfg)
    maps_ms = watch.lap()
    warning = coarse_level_warning(cfg.icp, src_maps.shapes[-1], src_maps.shapes[0])
    if warning:
        log.warning(warning)
    result = ICP(cfg.icp).align(src_maps, tgt_maps, init)
    icp_ms = watch.lap()
    _print_result(result)

    summary = {
        "frames": 2,
        "ms_per_stage": {"pyramid": round(maps_ms, 3), "icp": round(icp_ms, 3)},
        "dataset": dataset.describe(),
        "source": args.source,
        "target": args.target,
        "init": args.init,
        "pose": result.pose.tolist(),
        "rot_err_deg": None,
        "trans_err_m": None,
        "converged": result.converged,
        "failure": result.failure,
        "inliers": result.inliers,
        "inlier_ratio": result.inlier_ratio,
        "residual_rms_m": result.residual_rms,
        "condition": result.condition,
        "iterations": result.table(),
    }
    title = f"frames {args.source} → {args.target}, init {args.init}"
    if source.gt_pose is not None and target.gt_pose is not None:
        reference = invert(target.gt_pose) @ source.gt_pose
        rot0, trans0 = pose_error(init, reference)
        rot, trans = pose_error(result.pose, reference)
        print(f"error against ground truth: {rot:.3f}° {1e3 * trans:.2f} mm "
              f"(initial pose: {rot0:.3f}° {1e3 * trans0:.2f} mm)")
        summary.update(rot_err_deg=rot, trans_err_m=trans, init_rot_err_deg=rot0, init_trans_err_m=trans0,
                       reference_pose=reference.tolist())
        title += f" — error vs ground truth: before {rot0:.2f}° {1e3 * trans0:.1f} mm, after {rot:.2f}° {1e3 * trans:.1f} mm"
    if result.failure:
        title += f" — ICP failed: {result.failure}"
    png = ctx.out.file("icp.png")
    save_figure(png, source, target, init, result.pose, title)
    summary["figure"] = png.name
    print(f"maps {summary['ms_per_stage']['pyramid']:.1f} ms, ICP {summary['ms_per_stage']['icp']:.1f} ms "
          "(the first run includes compiling the kernels)")
    return summary
