"""A run's ATE over every frame (a rejected or failed frame holds the pose reported for it) and, labelled
apart, over the tracked frames alone (``held_trajectory``, ``tracked_ate``)."""

from dataclasses import dataclass

import numpy as np

from ti_fusion.evaluation.metrics import ate_errors, held_trajectory, tracked_ate


@dataclass
class R:
    timestamp: float
    pose: np.ndarray | None


@dataclass
class S(R):
    tracked: bool = True


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_a_rejected_frame_holds_the_last_pose_and_frames_before_the_first_are_left_out():
    results = [R(0.0, None), R(1.0, _pose(0)), R(2.0, None), R(3.0, None), R(4.0, _pose(3))]
    gts = [_pose(-1), _pose(0), _pose(1), _pose(2), _pose(3)]
    stamps, poses, truths, tracked = held_trajectory(results, gts)
    assert stamps == [1.0, 2.0, 3.0, 4.0] and tracked == [True, False, False, True]
    assert [p[0, 3] for p in poses] == [0, 0, 0, 3] and [g[0, 3] for g in truths] == [0, 1, 2, 3]


def test_a_failed_slam_frame_keeps_its_reported_pose_and_counts_as_not_tracked():
    results = [S(0.0, _pose(0)), S(1.0, _pose(0.5), tracked=False), S(2.0, _pose(2))]
    _, poses, _, tracked = held_trajectory(results, [_pose(0), _pose(1), _pose(2)])
    assert [p[0, 3] for p in poses] == [0, 0.5, 2] and tracked == [True, False, True]


def test_the_tracked_minority_is_labelled_apart_from_the_run():
    """Three accepted frames out of ten (the vo run of the issue): the tracked-only figure is exact, the
    run's is over all ten frames holding the last pose, and the counts say which is which."""
    rng = np.random.default_rng(3)
    gt = np.stack([_pose(0.1 * i) for i in range(10)])
    gt[:, 1, 3] = rng.normal(0, 0.05, 10)
    est = gt.copy()
    tracked = np.zeros(10, bool)
    tracked[:3] = True
    est[3:] = est[2]  # held
    out = tracked_ate(est, gt, tracked)
    assert out["ate_frames"] == 10 and out["tracked_frames"] == 3 and out["untracked_frames"] == 7
    assert out["ate_tracked_only_rmse_m"] < 1e-9
    all_frames = np.sqrt(np.mean(ate_errors(est, gt)[0] ** 2))
    assert all_frames > 0.1
    assert tracked_ate(est[:2], gt[:2], tracked[:2])["ate_tracked_only_rmse_m"] is None
