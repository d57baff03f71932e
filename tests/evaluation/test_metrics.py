"""Trajectory I/O, association, ATE/RPE (checked against evo) and the trajectory plot. No Taichi needed."""

from __future__ import annotations

import copy

import cv2
import numpy as np
import pytest

from ti_fusion.errors import InputError
from ti_fusion.evaluation.metrics import (align_rigid, ate_errors, evaluate, evaluate_files, rotation_angles_deg,
                                  rpe_errors, rpe_pairs, trajectory_metrics)
from ti_fusion.geometry import invert, make_pose, rigidity_error, se3_exp, so3_exp
from ti_fusion.evaluation.plots import plot_trajectory
from ti_fusion.io.trajectory import associate, read_tum, write_tum

evo_core = pytest.importorskip("evo.core")
from evo.core import metrics as evo_metrics  # noqa: E402
from evo.core import sync as evo_sync  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402
from evo.tools import file_interface  # noqa: E402


def random_walk(rng, n: int, step_m: float = 0.02, step_rad: float = 0.03) -> np.ndarray:
    """A hand-held-like camera path: n camera-to-world poses with random increments."""
    poses = [se3_exp(rng.normal(0, 1, 6))]
    for _ in range(n - 1):
        xi = np.concatenate([rng.normal(0, step_rad, 3), rng.normal(0, step_m, 3) + [0.0, 0.0, step_m]])
        poses.append(poses[-1] @ se3_exp(xi))
    return np.array(poses)


def perturbed(rng, gt: np.ndarray, sigma: float = 0.005) -> np.ndarray:
    """Estimate-like poses: drift accumulating along the path, in an arbitrary world frame."""
    world = se3_exp(rng.normal(0, 1.0, 6))
    drift = np.eye(4)
    est = []
    for T in gt:
        drift = drift @ se3_exp(rng.normal(0, sigma, 6))
        est.append(world @ drift @ T @ se3_exp(rng.normal(0, sigma, 6)))
    return np.array(est)


# --------------------------------------------------------------------------------------------------
# TUM trajectory files
# --------------------------------------------------------------------------------------------------
def test_tum_round_trip(tmp_path, rng):
    poses = random_walk(rng, 50)
    stamps = 1305031102.175304 + np.arange(50) / 30.0
    path = write_tum(tmp_path / "sub" / "trajectory.tum", stamps, poses)
    stamps2, poses2 = read_tum(path)
    np.testing.assert_allclose(stamps2, stamps, atol=1e-6)
    np.testing.assert_allclose(poses2, poses, atol=1e-8)
    # A second round trip changes nothing beyond the printed precision.
    stamps3, poses3 = read_tum(write_tum(tmp_path / "again.tum", stamps2, poses2))
    np.testing.assert_array_equal(stamps3, stamps2)
    np.testing.assert_allclose(poses3, poses2, atol=1e-8)


def test_tum_file_read_by_evo(tmp_path, rng):
    poses = random_walk(rng, 20)
    stamps = np.arange(20, dtype=float)
    path = write_tum(tmp_path / "t.tum", stamps, poses)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.timestamps, stamps)
    np.testing.assert_allclose(np.array(traj.poses_se3), poses, atol=1e-8)


def test_read_tum_skips_comments_and_blank_lines(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text("# ground truth\n\n1.5 1 2 3 0 0 0 1\n  # indented comment\n2.5 0 0 0 0 0 1 0\n")
    stamps, poses = read_tum(path)
    assert stamps.tolist() == [1.5, 2.5]
    np.testing.assert_allclose(poses[0], make_pose(np.eye(3), [1, 2, 3]))
    np.testing.assert_allclose(poses[1][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_write_tum_projects_nearly_orthonormal_rotations(tmp_path, rng):
    T = se3_exp(rng.normal(0, 1, 6))
    T[:3, :3] *= 1.0003
    _, poses = read_tum(write_tum(tmp_path / "t.tum", [0.0], [T]))
    assert rigidity_error(poses[0]) is None
    np.testing.assert_allclose(poses[0][:3, :3].T @ poses[0][:3, :3], np.eye(3), atol=1e-8)


@pytest.mark.parametrize("text, problem", [
    ("1 2 3\n", "line 1: expected 8 values"),
    ("0 0 0 0 0 0 0 1\n1 0 nan 0 0 0 0 1\n", "line 2: contains NaN"),
    ("# c\n0 0 0 0 0 0 0 1\n1 0 0 0 0.5 0.5 0.5 0.9\n", "line 3: quaternion has norm"),
    ("0 0 0 0 0 0 0 0\n", "line 1: quaternion has norm 0"),
    ("0 0 x 0 0 0 0 1\n", "line 1: expected numbers"),
    ("# only a comment\n", "no poses"),
])
def test_read_tum_bad_input(tmp_path, text, problem):
    path = tmp_path / "bad_traj.txt"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert "bad_traj.txt" in str(info.value) and problem in str(info.value), str(info.value)


def test_read_tum_missing_file(tmp_path):
    with pytest.raises(InputError, match="nothere.txt.*not found"):
        read_tum(tmp_path / "nothere.txt")


def test_write_tum_refuses_bad_poses(tmp_path, rng):
    poses = random_walk(rng, 3)
    bad = poses.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"out.tum: pose 1 \(line 3.*NaN"):
        write_tum(tmp_path / "out.tum", [0, 1, 2], bad)
    scaled = poses.copy()
    scaled[2, :3, :3] *= 1.2
    with pytest.raises(InputError, match="out.tum: pose 2.*orthonormal"):
        write_tum(tmp_path / "out.tum", [0, 1, 2], scaled)
    with pytest.raises(InputError, match="out.tum: 2 timestamps for 3 poses"):
        write_tum(tmp_path / "out.tum", [0, 1], poses)
    with pytest.raises(InputError, match="out.tum: poses must be"):
        write_tum(tmp_path / "out.tum", [0], np.eye(3)[None])


# --------------------------------------------------------------------------------------------------
# Association
# --------------------------------------------------------------------------------------------------
def associate_py_reference(first: list[float], second: list[float], max_difference: float):
    """TUM's associate.py (offset 0), on lists of stamps."""
    potential = sorted((abs(a - b), a, b) for a in first for b in second if abs(a - b) < max_difference)
    first, second = list(first), list(second)
    matches = []
    for _, a, b in potential:
        if a in first and b in second:
            first.remove(a)
            second.remove(b)
            matches.append((a, b))
    return sorted(matches)


def test_associate_matches_tum_associate_py(rng):
    for _ in range(20):
        a = np.sort(rng.uniform(0, 3, rng.integers(5, 60)))
        b = np.sort(rng.uniform(0, 3, rng.integers(5, 60)))
        ia, ib = associate(a, b, 0.02)
        ref = associate_py_reference(a.tolist(), b.tolist(), 0.02)
        assert list(zip(a[ia].tolist(), b[ib].tolist())) == ref
        assert len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib)


def test_associate_unsorted_and_empty():
    ia, ib = associate([3.0, 1.0, 2.0], [1.001, 2.999, 10.0])
    assert ia.tolist() == [0, 1] and ib.tolist() == [1, 0]
    ia, ib = associate([0.0], [1.0])
    assert ia.size == ib.size == 0


# --------------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------------
def test_align_rigid_recovers_a_transform(rng):
    pts = rng.normal(0, 1, (30, 3))
    S = se3_exp(rng.normal(0, 2, 6))
    moved = pts @ S[:3, :3].T + S[:3, 3]
    np.testing.assert_allclose(align_rigid(pts, moved), S, atol=1e-10)
    # Mirror-image targets: still a proper rotation.
    R = align_rigid(pts, pts * [1, 1, -1])[:3, :3]
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_ate_is_zero_for_a_rigidly_moved_trajectory(rng):
    gt = random_walk(rng, 40)
    S = se3_exp(rng.normal(0, 2, 6))
    errors, S_found = ate_errors(np.array([S @ T for T in gt]), gt)
    assert errors.max() < 1e-10
    np.testing.assert_allclose(S_found, invert(S), atol=1e-9)
    m = trajectory_metrics(np.array([S @ T for T in gt]), gt)
    assert m["ate_rmse_m"] < 1e-10 and m["rpe_trans_m"] < 1e-10 and m["rpe_rot_deg"] < 1e-6


def test_rpe_of_a_constant_step_error():
    # The estimate moves 1 cm further per frame and turns 1° more about z than the ground truth.
    step_gt = make_pose(np.eye(3), [0.0, 0.0, 0.1])
    err = make_pose(so3_exp([0.0, 0.0, np.radians(1.0)]), [0.0, 0.0, 0.01])
    gt, est = [np.eye(4)], [np.eye(4)]
    for _ in range(10):
        gt.append(gt[-1] @ step_gt)
        est.append(est[-1] @ step_gt @ err)
    trans, rot = rpe_errors(np.array(est), np.array(gt))
    np.testing.assert_allclose(trans, 0.01, atol=1e-12)
    np.testing.assert_allclose(rot, 1.0, atol=1e-9)


def test_rpe_pairs_and_small_angles():
    assert rpe_pairs(7, 1).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [5, 6]]
    assert rpe_pairs(7, 3).tolist() == [[0, 3], [3, 6]]
    assert rpe_pairs(7, 3, all_pairs=True).tolist() == [[0, 3], [1, 4], [2, 5], [3, 6]]
    assert rpe_pairs(3, 5).shape == (0, 2)
    angle = 1e-7
    assert rotation_angles_deg(so3_exp([angle, 0.0, 0.0])) == pytest.approx(np.degrees(angle), rel=1e-8)
    assert rotation_angles_deg(so3_exp([0.0, np.pi, 0.0])) == pytest.approx(180.0)


def _evo_numbers(gt_stamps, gt, est_stamps, est, delta, all_pairs):
    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=np.asarray(gt_stamps, dtype=float))
    traj = PoseTrajectory3D(poses_se3=list(est), timestamps=np.asarray(est_stamps, dtype=float))
    ref, traj = evo_sync.associate_trajectories(ref, traj, max_diff=0.02)
    aligned = copy.deepcopy(traj)
    aligned.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    out = {"ate_rmse_m": ape.get_statistic(evo_metrics.StatisticsType.rmse),
           "ate_mean_m": ape.get_statistic(evo_metrics.StatisticsType.mean),
           "ate_median_m": ape.get_statistic(evo_metrics.StatisticsType.median),
           "ate_max_m": ape.get_statistic(evo_metrics.StatisticsType.max),
           "pairs": ref.num_poses}
    for key, relation in (("rpe_trans_m", evo_metrics.PoseRelation.translation_part),
                          ("rpe_rot_deg", evo_metrics.PoseRelation.rotation_angle_deg)):
        rpe = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs)
        rpe.process_data((ref, aligned))
        out[key] = rpe.get_statistic(evo_metrics.StatisticsType.rmse)
        out["rpe_pairs"] = len(rpe.error)
    return out


@pytest.mark.parametrize("delta, all_pairs", [(1, False), (5, False), (5, True)])
def test_metrics_match_evo(rng, delta, all_pairs):
    for _ in range(3):
        n = int(rng.integers(60, 120))
        gt = random_walk(rng, n)
        gt_stamps = 1000.0 + np.arange(n) / 30.0
        est_all = perturbed(rng, gt, sigma=float(rng.uniform(0.001, 0.01)))
        # The estimate skips some frames and its clock jitters by a few ms.
        keep = np.sort(rng.choice(n, size=n - 7, replace=False))
        est, est_stamps = est_all[keep], gt_stamps[keep] + rng.uniform(-0.005, 0.005, len(keep))
        ours = evaluate(est_stamps, est, gt_stamps, gt, delta=delta, all_pairs=all_pairs)
        ref = _evo_numbers(gt_stamps, gt, est_stamps, est, delta, all_pairs)
        assert ours["pairs"] == ref["pairs"] == n - 7 and ours["rpe_pairs"] == ref["rpe_pairs"]
        assert ours["unmatched"] == 0 and ours["rpe_delta"] == delta
        for key in ("ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_max_m", "rpe_trans_m", "rpe_rot_deg"):
            assert ours[key] == pytest.approx(ref[key], rel=1e-6), key
        assert ours["ate_rmse_m"] > 1e-3  # a real error, not a trivially matched zero


def test_evaluate_files_and_unmatched(tmp_path, rng):
    gt = random_walk(rng, 30)
    stamps = np.arange(30, dtype=float)
    est = perturbed(rng, gt)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", np.r_[stamps, 100.0], np.concatenate([est, est[-1:]]))
    result = evaluate_files(tmp_path / "est.tum", tmp_path / "gt.tum")
    assert result["pairs"] == 30 and result["unmatched"] == 1 and result["est_poses"] == 31
    assert result == pytest.approx({**evaluate(stamps, est, stamps, gt), "unmatched": 1, "est_poses": 31})
    write_tum(tmp_path / "late.tum", stamps + 0.5, est)
    with pytest.raises(InputError, match="late.tum: no estimated pose has a ground-truth pose within 0.02 s"):
        evaluate_files(tmp_path / "late.tum", tmp_path / "gt.tum")


def test_rpe_none_when_too_short(rng):
    gt = random_walk(rng, 3)
    m = trajectory_metrics(gt, gt, delta=5)
    assert m["rpe_trans_m"] is None and m["rpe_pairs"] == 0 and m["ate_rmse_m"] < 1e-12


# --------------------------------------------------------------------------------------------------
# Plot
# --------------------------------------------------------------------------------------------------
def test_plot_trajectory_writes_png(tmp_path, rng):
    gt = random_walk(rng, 80)
    est = perturbed(rng, gt, sigma=0.003)
    stamps = 1305031102.0 + np.arange(80) / 30.0
    path = plot_trajectory(tmp_path / "plots" / "trajectory.png", est, gt, stamps, title="test sequence")
    image = cv2.imread(str(path))
    assert image is not None and image.shape == (650, 1300, 3)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50  # something was drawn
    # Without ground truth, and frame-number timestamps.
    path = plot_trajectory(tmp_path / "est_only.png", est, timestamps=np.arange(80.0))
    assert cv2.imread(str(path)) is not None
    with pytest.raises(ValueError, match="associate them first"):
        plot_trajectory(tmp_path / "x.png", est, gt[:10])


def test_keep_freed_memory_takes_effect_on_glibc():
    """The benchmarks' allocator setting (scripts/benchlib.py), in a child process (it would stay set for the
    rest of this one): True on glibc, and NumPy still works after it."""
    import platform
    import subprocess
    import sys
    from pathlib import Path

    benchlib = Path(__file__).resolve().parents[2] / "scripts" / "benchlib.py"
    code = ("import runpy, sys; import numpy as np; kept = runpy.run_path(sys.argv[1])['keep_freed_memory'](); "
            "a = np.ones(5_000_000); del a; assert float(np.ones(5_000_000).sum()) == 5e6; print(kept)")
    out = subprocess.run([sys.executable, "-c", code, str(benchlib)], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == ("True" if platform.libc_ver()[0] == "glibc" else out)
