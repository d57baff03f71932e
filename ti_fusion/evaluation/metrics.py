"""Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE).

Definitions (the TUM RGB-D benchmark's, computed as evo computes them; tests compare with evo):

- Association: estimated and ground-truth poses are paired by timestamp, one-to-one, greedily by
  smallest difference within ``max_difference`` seconds (TUM's associate.py; ``trajectory.associate``).
- ATE: the estimated positions are rigidly aligned to the ground truth (Umeyama / Horn, rotation and
  translation, NO scale: an RGB-D camera measures metric depth), then
  e_i = ‖t(S·P_i) − t(Q_i)‖ for estimated poses P_i, ground truth Q_i and the alignment S.
  ``ate_rmse_m`` = sqrt(mean e_i²); also mean, median and max.
- RPE over ``delta`` frames (pairs of associated poses, counted in that list): for each pair (i, j),
  E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j); translational error ‖t(E_ij)‖ in metres, rotational error the
  angle of R(E_ij) in degrees. ``rpe_trans_m`` and ``rpe_rot_deg`` are RMSEs over the pairs.
  Pairs are (0, δ), (δ, 2δ), ... as evo's default; ``all_pairs=True`` takes every (i, i + δ) as
  TUM's evaluate_rpe.py does. With δ = 1 both are all consecutive pairs. RPE needs no alignment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.io.trajectory import associate, read_tum


def align_rigid(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4×4 rigid S minimising Σ‖R·source_i + t − target_i‖² over points N×3 (Umeyama 1991, no scale)."""
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0  # a proper rotation, never a reflection
    S = np.eye(4)
    S[:3, :3] = U @ D @ Vt
    S[:3, 3] = mu_t - S[:3, :3] @ mu_s
    return S


def _as_poses(poses, what: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{what} must be N×4×4, got shape {poses.shape}")
    return poses


def ate_errors(est_poses, gt_poses, align: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(per-pose position errors in metres after alignment, the 4×4 alignment S applied to the estimate)."""
    est, gt = _as_poses(est_poses, "est_poses"), _as_poses(gt_poses, "gt_poses")
    if len(est) != len(gt):
        raise ValueError(f"{len(est)} estimated poses for {len(gt)} ground-truth poses")
    S = align_rigid(est[:, :3, 3], gt[:, :3, 3]) if align else np.eye(4)
    aligned = est[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return np.linalg.norm(aligned - gt[:, :3, 3], axis=1), S


def _inverse(T: np.ndarray) -> np.ndarray:
    """Batched inverse of rigid transforms (…×4×4)."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles of rotation matrices (…×3×3) in degrees; atan2 form, accurate at small angles too."""
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.linalg.norm(vee, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


def rpe_pairs(n: int, delta: int = 1, all_pairs: bool = False) -> np.ndarray:
    """Index pairs (i, j) with j − i = delta: consecutive blocks (0, δ), (δ, 2δ), ... or every i."""
    if delta < 1:
        raise ValueError("delta must be a positive number of frames")
    starts = np.arange(0, n - delta) if all_pairs else np.arange(0, n - delta, delta)
    return np.stack([starts, starts + delta], axis=1).reshape(-1, 2)


def rpe_errors(est_poses, gt_poses, delta: int = 1, all_pairs: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(translational errors in metres, rotational errors in degrees) per pose pair (see module docstring)."""
    est, gt = _as_poses(est_poses, "est_poses"), _as_poses(gt_poses, "gt_poses")
    if len(est) != len(gt):
        raise ValueError(f"{len(est)} estimated poses for {len(gt)} ground-truth poses")
    pairs = rpe_pairs(len(est), delta, all_pairs)
    i, j = pairs[:, 0], pairs[:, 1]
    gt_rel = _inverse(gt[i]) @ gt[j]
    est_rel = _inverse(est[i]) @ est[j]
    E = _inverse(gt_rel) @ est_rel
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angles_deg(E[:, :3, :3])


def _rmse(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x**2))) if len(x) else None


def trajectory_metrics(est_poses, gt_poses, delta: int = 1, all_pairs: bool = False) -> dict:
    """ATE and RPE of already paired poses (est_poses[k] ↔ gt_poses[k]). RPE fields are None when
    there are fewer than delta + 1 poses."""
    ate, _ = ate_errors(est_poses, gt_poses)
    if len(ate) == 0:
        raise InputError(None, "no pose pairs to evaluate")
    trans, rot = rpe_errors(est_poses, gt_poses, delta, all_pairs)
    return {
        "ate_rmse_m": _rmse(ate),
        "ate_mean_m": float(np.mean(ate)),
        "ate_median_m": float(np.median(ate)),
        "ate_max_m": float(np.max(ate)),
        "rpe_trans_m": _rmse(trans),
        "rpe_rot_deg": _rmse(rot),
        "rpe_delta": int(delta),
        "rpe_pairs": int(len(trans)),
        "pairs": int(len(ate)),
    }


def held_trajectory(results, gts) -> tuple[list[float], list[np.ndarray], list, list[bool]]:
    """(timestamps, poses, ground truths, tracked) of every frame of a run from the first that got a pose:
    a frame the run rejected without a pose (``vo``) holds the last pose reported before it, a failed one
    (``slam``) the pose it reported. ``results`` have ``timestamp``, ``pose`` (None: none) and, where the
    run tells them apart, ``tracked``; ``gts`` are the frames' ground-truth poses (None: none)."""
    stamps, poses, truths, tracked, held = [], [], [], [], None
    for r, g in zip(results, gts):
        held = r.pose if r.pose is not None else held
        if held is None:
            continue  # before the first pose (slam's skipped frames): nothing reported to evaluate
        stamps.append(r.timestamp)
        poses.append(held)
        truths.append(g)
        tracked.append(bool(getattr(r, "tracked", r.pose is not None)) and r.pose is not None)
    return stamps, poses, truths, tracked


def tracked_ate(est_poses, gt_poses, tracked) -> dict:
    """The counts of a run's evaluated frames, tracked and not, and the ATE over the tracked frames alone
    (aligned on their own; None with fewer than 3), labelled so it is never read as the run's ATE."""
    est, gt = _as_poses(est_poses, "est_poses"), _as_poses(gt_poses, "gt_poses")
    tracked = np.asarray(tracked, dtype=bool)
    n = int(tracked.sum())
    out = {"ate_frames": int(len(est)), "tracked_frames": n, "untracked_frames": int(len(est) - n),
           "ate_tracked_only_rmse_m": None}
    if n >= 3:
        errors, _ = ate_errors(est[tracked], gt[tracked])
        out["ate_tracked_only_rmse_m"] = _rmse(errors)
    return out


def associate_trajectories(est_stamps, est_poses, gt_stamps, gt_poses, max_difference: float = 0.02):
    """(timestamps, est N×4×4, gt N×4×4) of the pose pairs matched by timestamp (estimate's stamps)."""
    est_stamps = np.asarray(est_stamps, dtype=np.float64)
    est, gt = _as_poses(est_poses, "est_poses"), _as_poses(gt_poses, "gt_poses")
    if len(est_stamps) != len(est) or len(gt_stamps) != len(gt):
        raise ValueError("every pose needs one timestamp")
    i_est, i_gt = associate(est_stamps, gt_stamps, max_difference)
    return est_stamps[i_est], est[i_est], gt[i_gt]


def evaluate(est_stamps, est_poses, gt_stamps, gt_poses, delta: int = 1, max_difference: float = 0.02,
             all_pairs: bool = False) -> dict:
    """ATE/RPE of an estimated trajectory against ground truth, paired by timestamp.

    Returns {"ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_max_m", "rpe_trans_m", "rpe_rot_deg",
    "rpe_delta", "rpe_pairs", "pairs", "est_poses", "unmatched"}: ``pairs`` poses matched out of
    ``est_poses``.
    """
    _, est, gt = associate_trajectories(est_stamps, est_poses, gt_stamps, gt_poses, max_difference)
    if len(est) == 0:
        raise InputError(None, f"no estimated pose has a ground-truth pose within {max_difference} s")
    result = trajectory_metrics(est, gt, delta, all_pairs)
    result["est_poses"] = int(len(est_poses))
    result["unmatched"] = int(len(est_poses) - len(est))
    return result


def evaluate_files(est_path: str | Path, gt_path: str | Path, delta: int = 1, max_difference: float = 0.02,
                   all_pairs: bool = False) -> dict:
    """``evaluate`` on two TUM trajectory files."""
    est_stamps, est = read_tum(est_path)
    gt_stamps, gt = read_tum(gt_path)
    try:
        return evaluate(est_stamps, est, gt_stamps, gt, delta, max_difference, all_pairs)
    except InputError as exc:
        raise InputError(est_path, f"{exc.problem} (ground truth {gt_path})") from None
