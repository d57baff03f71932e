"""Feature-based RGB-D odometry (ORB + PnP RANSAC), voxel downsampling, the ``vo`` command, ICP init.

The tracker tests run on a short stretch of the embedded synthetic sequence at 320×240 with sensor
noise on (texture-rich colour), rendered once per module on the CPU backend.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import SynthConfig, VOConfig
from ti_fusion.frame import Frame
from ti_fusion.tracking.features import (FEW_INLIERS, FEW_MATCHES, LARGE_MOTION, NO_COLOR, NO_DEPTH, FeatureOdometry,
                                estimate_relative_pose, motion_norm, relocalise)
from ti_fusion.geometry import invert, make_pose, pose_error, se3_exp, so3_exp
from ti_fusion.mapping.pointcloud import VoxelCloud, backproject, transform, voxel_downsample

N_FRAMES = 30
ELSEWHERE = 39  # a frame 1.3 s later: same scene, ≈ 12° and 28 cm from frame 9 (motion norm ≈ 0.45)
W, H, FX = 320, 240, 262.5


def _start_cpu():
    from ti_fusion import backend

    if backend._current is None or backend._current.arch != "cpu":
        backend.init_backend("cpu")


@pytest.fixture(scope="module")
def synth():
    _start_cpu()
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig(frames=ELSEWHERE + 1, width=W, height=H, fx=FX, noise=True))

    def frame(i: int) -> Frame:
        depth, color = seq.frame(i)
        return Frame(i, float(seq.timestamps[i]), depth, seq.intrinsics, color, seq.poses[i].copy())

    frames = [frame(i) for i in range(N_FRAMES)]
    return seq, frames, frame(ELSEWHERE)


def _path_length(poses) -> float:
    return float(np.linalg.norm(np.diff(np.asarray(poses)[:, :3, 3], axis=0), axis=1).sum())


# --------------------------------------------------------------------------------------------------
# The tracker
# --------------------------------------------------------------------------------------------------
def test_trajectory_on_synthetic_sequence(synth):
    from ti_fusion.evaluation.metrics import trajectory_metrics

    _, frames, _ = synth
    vo = FeatureOdometry()
    results = [vo.register_frame(f) for f in frames]
    assert all(r.accepted for r in results), [r.status for r in results if not r.accepted]
    # Anchored at the first frame's ground truth.
    np.testing.assert_allclose(results[0].pose, frames[0].gt_pose, atol=1e-9)
    est = np.array([r.pose for r in results])
    gt = np.array([f.gt_pose for f in frames])
    metrics = trajectory_metrics(est, gt)
    # Bound: 2 cm and 8 % of the path (≈ 0.27 m); measured ≈ 0.9 cm. PnP from 0.5-px ORB keypoints
    # leaves a few mm per frame (rotation/translation ambiguity of a narrow field of view), which adds up.
    assert metrics["ate_rmse_m"] < 0.02
    assert metrics["ate_rmse_m"] < 0.08 * _path_length(gt)
    assert metrics["rpe_rot_deg"] < 0.3
    r = results[5]
    assert r.keypoints > 500 and r.matches >= r.good >= r.inliers >= 100 and r.ms > 0
    assert r.relative.shape == (4, 4) and r.keyframe_index == 4
    stats = r.stats()
    assert stats["status"] == "accepted" and stats["reason"] == "" and stats["inliers"] == r.inliers


def test_relative_pose_convention_and_accuracy(synth):
    _, frames, _ = synth
    a, b = frames[3], frames[8]
    est = estimate_relative_pose(a, b)
    assert est.ok, est.reason
    T_gt = invert(b.gt_pose) @ a.gt_pose  # p_b = T p_a
    rot_deg, trans_m = pose_error(est.T, T_gt)
    moved_deg, moved_m = pose_error(np.eye(4), T_gt)
    assert rot_deg < 0.3 and trans_m < 0.01, (rot_deg, trans_m, moved_deg, moved_m)
    assert est.good >= est.inliers >= VOConfig().min_inliers_init
    assert est.pose is est.T
    np.testing.assert_allclose(est.motion_norm, motion_norm(est.T))
    # Re-localisation: b's camera-to-world pose from a's.
    pose_b = relocalise(a, a.gt_pose, b)
    rot_deg, trans_m = pose_error(pose_b, b.gt_pose)
    assert rot_deg < 0.3 and trans_m < 0.01


def test_ratio_matching_also_tracks(synth):
    _, frames, _ = synth
    est = estimate_relative_pose(frames[0], frames[2], VOConfig(match="ratio"))
    assert est.ok and est.good < est.matches
    rot_deg, trans_m = pose_error(est.T, invert(frames[2].gt_pose) @ frames[0].gt_pose)
    assert rot_deg < 0.3 and trans_m < 0.01


def test_motion_norm():
    T = make_pose(so3_exp([0.0, 0.2, 0.0]), [0.03, 0.0, 0.04])
    assert motion_norm(T) == pytest.approx(0.05 + 0.2)
    # Rotations are measured the short way round: ‖r‖ and 2π − ‖r‖ name the same rotation.
    assert motion_norm(make_pose(so3_exp([0.0, 0.0, np.pi - 0.1]), np.zeros(3))) == pytest.approx(np.pi - 0.1)


# --------------------------------------------------------------------------------------------------
# Rejection rules
# --------------------------------------------------------------------------------------------------
def test_blank_color_frame_is_rejected_and_skipped(synth):
    _, frames, _ = synth
    blank = replace(frames[3], color=np.full_like(frames[3].color, 128))
    vo = FeatureOdometry()
    r = [vo.register_frame(f) for f in (frames[0], frames[1], frames[2], blank, frames[4])]
    assert [x.accepted for x in r] == [True, True, True, False, True]
    assert r[3].reason == FEW_MATCHES and r[3].pose is None and r[3].good < VOConfig().min_good_match
    assert r[3].stats()["reason"] == FEW_MATCHES
    # The frame after the rejected one is matched against the keyframe, the last accepted frame.
    assert r[4].keyframe_index == 2
    rot_deg, trans_m = pose_error(r[4].pose, frames[4].gt_pose)
    assert rot_deg < 0.5 and trans_m < 0.02


def test_frame_from_elsewhere_is_rejected_as_too_large_a_motion(synth):
    _, frames, elsewhere = synth
    vo = FeatureOdometry()
    for f in frames[:10]:
        assert vo.register_frame(f).accepted
    r = vo.register_frame(elsewhere)
    assert not r.accepted and r.reason == LARGE_MOTION
    assert r.motion_norm > VOConfig().max_norm and r.inliers >= VOConfig().min_inliers
    nxt = vo.register_frame(frames[10])
    assert nxt.accepted and nxt.keyframe_index == 9
    # The same pair is fine for the initialiser, which does not judge the motion's size.
    est = estimate_relative_pose(frames[9], elsewhere)
    assert est.ok
    rot_deg, trans_m = pose_error(est.T, invert(elsewhere.gt_pose) @ frames[9].gt_pose)
    assert rot_deg < 2.0 and trans_m < 0.06


def test_min_inliers_rule(synth):
    _, frames, _ = synth
    vo = FeatureOdometry(VOConfig(min_inliers=100_000))
    assert vo.register_frame(frames[0]).accepted
    r = vo.register_frame(frames[1])
    assert not r.accepted and r.reason == FEW_INLIERS and 0 < r.inliers < 100_000


def test_no_depth_and_no_color(synth):
    _, frames, _ = synth
    no_depth = replace(frames[0], depth=np.zeros_like(frames[0].depth))
    failed = estimate_relative_pose(no_depth, frames[1])
    assert failed.reason == NO_DEPTH and not failed.ok and failed.pose is None
    assert estimate_relative_pose(replace(frames[0], color=None), frames[1]).reason == NO_COLOR
    r = FeatureOdometry().register_frame(replace(frames[0], color=None))
    assert not r.accepted and r.reason == NO_COLOR


def test_first_pose_is_identity_without_ground_truth(synth):
    _, frames, _ = synth
    vo = FeatureOdometry()
    r0 = vo.register_frame(replace(frames[0], gt_pose=None))
    r1 = vo.register_frame(replace(frames[1], gt_pose=None))
    np.testing.assert_allclose(r0.pose, np.eye(4))
    T_gt = invert(frames[1].gt_pose) @ frames[0].gt_pose
    rot_deg, trans_m = pose_error(r1.pose, invert(T_gt))
    assert rot_deg < 0.3 and trans_m < 0.01


# --------------------------------------------------------------------------------------------------
# Point clouds
# --------------------------------------------------------------------------------------------------
def _voxel_reference(xyz, rgb, size):
    """Brute force: a dict from voxel cell to the list of its points."""
    cells: dict[tuple, list[int]] = {}
    for i, p in enumerate(xyz):
        key = tuple(int(np.floor(c / size)) for c in p)
        cells.setdefault(key, []).append(i)
    out = {}
    for key, idx in cells.items():
        out[key] = (xyz[idx].mean(axis=0), None if rgb is None else np.rint(rgb[idx].astype(float).mean(axis=0)))
    return out


def _as_dict(xyz, rgb, size):
    keys = [tuple(int(np.floor(c / size)) for c in p) for p in xyz]
    return {k: (xyz[i], None if rgb is None else rgb[i]) for i, k in enumerate(keys)}


@pytest.mark.parametrize("size", [0.05, 0.013])
def test_voxel_downsample_matches_brute_force(rng, size):
    # Clustered points on both sides of zero (negative cells round down) with colours.
    xyz = rng.normal(0.0, 0.15, (3000, 3)) + rng.choice([-0.3, 0.0, 0.2], size=(3000, 1))
    rgb = rng.integers(0, 256, (3000, 3), dtype=np.uint8)
    ref = _voxel_reference(xyz, rgb, size)
    got_xyz, got_rgb = voxel_downsample(xyz, rgb, size)
    assert len(got_xyz) == len(ref)
    got = _as_dict(got_xyz, got_rgb, size)  # centroids stay in their voxel
    assert got.keys() == ref.keys()
    for key, (p, c) in ref.items():
        np.testing.assert_allclose(got[key][0], p, atol=1e-12)
        np.testing.assert_allclose(got[key][1], c, atol=0)
    xyz_only, none = voxel_downsample(xyz, None, size)
    assert none is None and len(xyz_only) == len(ref)


def test_joining_clouds_equals_downsampling_all_at_once(rng):
    size = 0.04
    parts = [rng.uniform(-1, 1, (n, 3)) for n in (500, 2000, 50, 1500)]
    colors = [rng.integers(0, 256, (len(p), 3), dtype=np.uint8) for p in parts]
    poses = [se3_exp(rng.normal(0, 0.3, 6)) for _ in parts]
    cloud = VoxelCloud(size)
    cloud.add(parts[0], colors[0], poses[0])
    cloud.add(parts[1], colors[1], poses[1])
    assert len(cloud) > 0  # merges what is pending; the next adds merge into it
    for p, c, T in zip(parts[2:], colors[2:], poses[2:]):
        cloud.add(p, c, T)
    xyz, rgb = cloud.points()
    world = np.concatenate([transform(T, p) for p, T in zip(parts, poses)])
    ref_xyz, ref_rgb = voxel_downsample(world, np.concatenate(colors), size)
    np.testing.assert_allclose(xyz, ref_xyz, atol=1e-12)
    np.testing.assert_array_equal(rgb, ref_rgb)
    with pytest.raises(ValueError):
        cloud.add(parts[0])  # colours on every cloud or on none


def test_a_stop_during_a_merge_leaves_the_cloud_whole(rng, monkeypatch):
    """A stop (SIGTERM, Ctrl-C) that lands while pending clouds merge is raised once the sums are whole: the
    run's last map snapshot, on its way out, reads the cloud (it read sums of two sizes, a traceback, when
    SIGTERM landed between them in ``ti-fusion vo``)."""
    from ti_fusion.interrupts import interrupt
    from ti_fusion.mapping import pointcloud

    parts = [rng.uniform(-1, 1, (n, 3)) for n in (800, 600)]
    colors = [rng.integers(0, 256, (len(p), 3), dtype=np.uint8) for p in parts]
    cloud = VoxelCloud(0.05)
    cloud.add(parts[0], colors[0])
    assert len(cloud) > 0
    cloud.add(parts[1], colors[1])
    sum_by = pointcloud._sum_by

    def stopped_during(inverse, values, n):  # the signal handler's call, between the sums
        interrupt(KeyboardInterrupt())
        return sum_by(inverse, values, n)

    monkeypatch.setattr(pointcloud, "_sum_by", stopped_during)
    with pytest.raises(KeyboardInterrupt):
        cloud.points()
    monkeypatch.setattr(pointcloud, "_sum_by", sum_by)
    xyz, rgb = cloud.points()
    ref_xyz, ref_rgb = voxel_downsample(np.concatenate(parts), np.concatenate(colors), 0.05)
    np.testing.assert_allclose(xyz, ref_xyz, atol=1e-12)
    np.testing.assert_array_equal(rgb, ref_rgb)


def test_backproject():
    K = Intrinsics(100.0, 110.0, 4.5, 3.0, 10, 8)
    depth = np.zeros((8, 10), np.float32)
    depth[2, 7] = 2.0
    depth[6, 1] = 0.5
    color = np.zeros((8, 10, 3), np.uint8)
    color[2, 7] = (1, 2, 3)
    xyz, rgb = backproject(depth, K, color)
    assert len(xyz) == 2
    np.testing.assert_allclose(xyz[0], [(7 - 4.5) * 2.0 / 100.0, (2 - 3.0) * 2.0 / 110.0, 2.0])
    np.testing.assert_array_equal(rgb[0], (1, 2, 3))
    xyz2, _ = backproject(depth, K, stride=2)  # pixel (7, 2) is not on the even grid; (1, 6) is not either
    assert len(xyz2) == 0


# --------------------------------------------------------------------------------------------------
# The vo command
# --------------------------------------------------------------------------------------------------
def _write_sevenscenes(root, frames, blank: int | None = None):
    """The synthetic frames as a 7-Scenes folder (16-bit millimetre depth, PNG colour, 4×4 pose files)."""
    import cv2

    root.mkdir()
    K = frames[0].intrinsics
    np.savetxt(root / "camera-intrinsics.txt", K.K)
    for f in frames:
        stem = root / f"frame-{f.index:06d}"
        color = np.full_like(f.color, 90) if f.index == blank else f.color
        assert cv2.imwrite(f"{stem}.depth.png", np.rint(f.depth * 1000.0).astype(np.uint16))
        assert cv2.imwrite(f"{stem}.color.png", np.ascontiguousarray(color[..., ::-1]))
        np.savetxt(f"{stem}.pose.txt", f.gt_pose)
    return root


def test_vo_command_writes_all_outputs(synth, tmp_path):
    from ti_fusion.cli.main import main
    from ti_fusion.io.mcap_log import read_log
    from ti_fusion.io.ply import read_ply
    from ti_fusion.io.trajectory import read_tum

    _, frames, _ = synth
    data = _write_sevenscenes(tmp_path / "seq", frames[:12], blank=5)
    out = tmp_path / "out"
    assert main(["vo", str(data), "--out", str(out), "--quiet", "--pair", "0", "3",
                 "--set", "log.map_every=5"]) == 0
    for name in ("trajectory.tum", "cloud.ply", "matches.png", "log.mcap", "trajectory.png", "summary.json"):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 12 and s["accepted"] == 11 and s["rejected"] == {"few_matches": 1}
    assert s["rejected_frames"] == [[5, "few_matches"]] and s["first_pose"] == "ground truth"
    assert s["ate_rmse_m"] < 0.02 and s["rpe_trans_m"] < 0.01 and s["fps"] > 0
    assert s["pair"]["frames"] == [0, 3] and s["pair"]["inliers"] >= 20
    stamps, poses = read_tum(out / "trajectory.tum")
    assert len(stamps) == 11 and 5.0 not in stamps
    cloud = read_ply(out / "cloud.ply")
    assert len(cloud) == s["cloud_points"] > 1000
    import cv2

    assert cv2.imread(str(out / "matches.png")).shape[:2] == (3 * H, 2 * W)
    log = read_log(out / "log.mcap")
    assert log.complete and log.stats_topic == "/vo/stats"
    assert log.channels["/vo/stats"].count == 12
    assert log.channels["/camera/pose"].count == 11 and log.channels["/gt/pose"].count == 11
    assert log.channels["/map/points"].count >= 2
    assert [m["reason"] for m in log.stats][5] == "few_matches"
    assert {"keypoints", "matches", "good", "inliers", "status", "ms"} <= set(log.stats[1])
    np.testing.assert_allclose(log.est_poses, poses, atol=1e-6)


def test_vo_command_keeps_the_trajectory_and_log_when_interrupted(synth, tmp_path, monkeypatch):
    from ti_fusion.cli.main import main
    from ti_fusion.io.mcap_log import read_log
    from ti_fusion.io.trajectory import read_tum

    _, frames, _ = synth
    data = _write_sevenscenes(tmp_path / "seq", frames[:8])
    original = FeatureOdometry.register_frame

    def interrupted(self, frame):
        if frame.index == 4:
            raise KeyboardInterrupt
        return original(self, frame)

    monkeypatch.setattr(FeatureOdometry, "register_frame", interrupted)
    out = tmp_path / "out"
    assert main(["vo", str(data), "--out", str(out), "--quiet"]) == 130
    stamps, _ = read_tum(out / "trajectory.tum")
    assert list(stamps) == [0.0, 1.0, 2.0, 3.0]
    log = read_log(out / "log.mcap")
    assert log.complete and log.channels["/vo/stats"].count == 4


# --------------------------------------------------------------------------------------------------
# As the ICP initialiser
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_feature_initialised_icp_recovers_a_large_motion(synth):
    """≈ 20° and 30 cm between two noise-free frames: ICP from the identity fails, from ORB + PnP it converges."""
    from ti_fusion.config import ICPConfig, PyramidConfig
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.pyramid import FramePyramid

    seq, _, _ = synth
    pose_a = seq.poses[10]
    # Pan and slide in the same direction (a pan with an opposite slide partly cancels on screen, and
    # ICP from the identity then still converges).
    pose_b = pose_a @ make_pose(so3_exp(np.radians([3.0, 20.0, 0.0])), [0.3, 0.03, 0.05])
    frames = []
    for i, pose in enumerate((pose_a, pose_b)):
        depth, color = seq.render(pose, noise=False)
        frames.append(Frame(i, float(i), depth, seq.intrinsics, color, pose))
    T_gt = invert(pose_b) @ pose_a  # source a → target b
    moved_deg, moved_m = pose_error(np.eye(4), T_gt)
    assert moved_deg > 19.0 and moved_m > 0.29

    cfg = ICPConfig()
    pyramid = []
    for f in frames:
        m = FramePyramid(PyramidConfig(depth_smooth_radius=0), H, W, levels=len(cfg.iterations))
        m.compute(f.depth, f.intrinsics)
        pyramid.append(m)
    icp = ICP(cfg)
    from_identity = icp.align(pyramid[0], pyramid[1], None)
    rot_deg, trans_m = pose_error(from_identity.pose, T_gt)
    assert from_identity.failure is not None or rot_deg > 1.0 or trans_m > 0.05

    est = estimate_relative_pose(frames[0], frames[1])
    assert est.ok, est.reason
    result = icp.align(pyramid[0], pyramid[1], est.T)
    rot_deg, trans_m = pose_error(result.pose, T_gt)
    assert result.failure is None
    assert rot_deg < 0.1 and trans_m < 0.001, (rot_deg, trans_m)


def test_vo_command_on_the_synthetic_default(synth, tmp_path):
    from ti_fusion.cli.main import main

    out = tmp_path / "out"
    assert main(["vo", "--frames", "6", "--downsample", "2", "--out", str(out), "--quiet"]) == 0
    for name in ("trajectory.tum", "cloud.ply", "matches.png", "log.mcap", "trajectory.png", "summary.json"):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 6 and s["accepted"] == 6 and s["ate_rmse_m"] < 0.01


@pytest.mark.slow
def test_icp_command_with_feature_initialisation(synth, tmp_path):
    from ti_fusion.cli.main import main

    out = tmp_path / "out"
    assert main(["icp", "--downsample", "2", "--source", "0", "--target", "30", "--init", "features",
                 "--out", str(out), "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["init"] == "features"
    assert s["init_trans_err_m"] < 0.02 and s["init_rot_err_deg"] < 0.5  # from 11.5° and 28 cm apart
    assert s["failure"] is None and s["trans_err_m"] < 0.002 and s["rot_err_deg"] < 0.1
