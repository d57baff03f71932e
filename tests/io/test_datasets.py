"""Dataset loaders: small fake sequences of each format written in tmp_path, plus the real redkitchen set.

No Taichi needed. Images are tiny (40×30) so the whole file runs in a few seconds.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.io.datasets import Dataset, Frame, detect, detect_format, open_dataset
from ti_fusion.io.datasets.iclnuim import ICLNUIMDataset
from ti_fusion.io.datasets.sevenscenes import SevenScenesDataset
from ti_fusion.io.datasets.tum import TUMDataset, freiburg_camera, interpolate_pose
from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, rigidity_error, rot_to_quat, se3_exp, so3_exp
from ti_fusion.io.trajectory import read_tum

W, H = 40, 30


# --------------------------------------------------------------------------------------------------
# Writers of fake sequences
# --------------------------------------------------------------------------------------------------
def random_depth(rng, scale: float, invalid_value: int = 0) -> np.ndarray:
    """16-bit raw depth between 0.5 and 5 m with a few invalid pixels."""
    raw = (rng.uniform(0.5, 5.0, (H, W)) * scale).astype(np.uint16)
    raw[rng.random((H, W)) < 0.1] = invalid_value
    return raw


def write_depth(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), raw)


def write_color(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV writes BGR


def random_color(rng) -> np.ndarray:
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


def tum_line(t: float, T: np.ndarray) -> str:
    q = rot_to_quat(T[:3, :3])
    return f"{t:.6f} " + " ".join(f"{v:.12f}" for v in (*T[:3, 3], *q))


def gt_motion(t: float) -> np.ndarray:
    """Rotation at constant angular velocity, translation linear in time: what slerp + lerp reproduce exactly."""
    return make_pose(so3_exp(np.array([0.3, -0.2, 0.5]) * t), np.array([0.1, 0.2, -0.3]) * t + [1.0, 0.5, 2.0])


def make_tum(root: Path, rng, n: int = 5, name: str = "rgbd_dataset_freiburg1_fake") -> dict:
    """A TUM folder: depth at 30 Hz from t0, rgb 7 ms later; rgb of the last depth frame missing, so
    that frame has no partner and is dropped; ground truth at 100 Hz, offset by 3 ms."""
    root = root / name
    t0 = 1305031102.0
    depth_stamps = np.round(t0 + np.arange(n) / 30.0, 6)  # as printed: the files hold 6 decimals
    rgb_stamps = depth_stamps[:-1] + 0.007
    raws, colors = [], []
    for k, t in enumerate(depth_stamps):
        raw = random_depth(rng, 5000.0)
        raws.append(raw)
        write_depth(root / "depth" / f"{t:.6f}.png", raw)
    for t in rgb_stamps:
        c = random_color(rng)
        colors.append(c)
        write_color(root / "rgb" / f"{t:.6f}.png", c)
    (root / "depth.txt").write_text("# depth maps\n# timestamp filename\n"
                                    + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_stamps))
    (root / "rgb.txt").write_text("# color images\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_stamps))
    gt_stamps = np.round(t0 - 0.1 + 0.003 + np.arange(int((n / 30.0 + 0.2) * 100)) / 100.0, 6)
    (root / "groundtruth.txt").write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        + "".join(tum_line(t, gt_motion(t - t0)) + "\n" for t in gt_stamps))
    return {"root": root, "depth_stamps": depth_stamps, "raws": raws, "colors": colors, "t0": t0}


def make_icl(root: Path, rng, n: int = 4) -> dict:
    root = root / "living_room_traj0_frei_png"
    raws, colors, poses = [], [], {}
    for k in range(n):
        raw = random_depth(rng, 5000.0)
        raws.append(raw)
        write_depth(root / "depth" / f"{k}.png", raw)
        c = random_color(rng)
        colors.append(c)
        write_color(root / "rgb" / f"{k}.png", c)
    lines = []
    for k in range(1, n):  # as in the release, frame 0 has no ground-truth line
        poses[k] = se3_exp(rng.normal(0, 0.3, 6))
        q = rot_to_quat(poses[k][:3, :3])
        lines.append(f"{k} " + " ".join(f"{v:.12f}" for v in (*poses[k][:3, 3], *q)))
    (root / "livingRoom0.gt.freiburg").write_text("\n".join(lines) + "\n")
    return {"root": root, "raws": raws, "colors": colors, "poses": poses}


def make_7scenes(root: Path, rng, n: int = 6, color_ext: str = "png", intrinsics: bool = True) -> dict:
    root = root / "seq-01"
    root.mkdir(parents=True)
    raws, colors, poses = [], [], []
    for k in range(n):
        raw = random_depth(rng, 1000.0, invalid_value=65535)
        raw[0, 0], raw[0, 1] = 0, 65535
        raws.append(raw)
        write_depth(root / f"frame-{k:06d}.depth.png", raw)
        c = random_color(rng)
        colors.append(c)
        if color_ext == "png":
            write_color(root / f"frame-{k:06d}.color.png", c)
        else:
            write_color(root / f"frame-{k:06d}.color.jpg", c)
        T = se3_exp(rng.normal(0, 0.3, 6))
        poses.append(T.copy())
        T[:3, :3] *= 0.9998  # the release's slightly non-orthonormal rotations
        np.savetxt(root / f"frame-{k:06d}.pose.txt", T)
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", np.array([[58.0, 0, 20.0], [0, 58.1, 15.0], [0, 0, 1]]))
    return {"root": root, "raws": raws, "colors": colors, "poses": poses}


# --------------------------------------------------------------------------------------------------
# TUM RGB-D
# --------------------------------------------------------------------------------------------------
def test_tum_depth_color_timestamps_and_association(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    ds = TUMDataset(fake["root"], DatasetConfig(depth_max=4.0))
    # The last depth frame has no rgb within 0.02 s: dropped, as associate.py drops it.
    assert len(ds) == 4 and ds.has_ground_truth
    for k in range(4):
        f = ds[k]
        raw = fake["raws"][k]
        assert f.depth.dtype == np.float32 and f.depth.shape == (H, W)
        expected = raw.astype(np.float32) / 5000.0
        expected[(raw == 0) | (expected > 4.0)] = 0.0
        np.testing.assert_array_equal(f.depth, expected)
        assert f.color.dtype == np.uint8 and f.color.shape == (H, W, 3)
        np.testing.assert_array_equal(f.color, fake["colors"][k])  # RGB, not BGR
        assert f.timestamp == pytest.approx(fake["depth_stamps"][k], abs=1e-6)  # the depth timestamp
    assert ds[0].depth[ds[0].depth > 0].max() <= 4.0


def test_tum_depth_max_zero_keeps_every_range(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    f = TUMDataset(fake["root"], DatasetConfig(depth_max=0.0))[0]
    raw = fake["raws"][0]
    np.testing.assert_allclose(f.depth, raw / 5000.0, rtol=1e-6)
    assert f.depth.max() > 4.0


def test_tum_association_is_greedy_and_one_to_one(tmp_path, rng):
    fake = make_tum(tmp_path, rng, n=3)
    root = fake["root"]
    d = fake["depth_stamps"]
    # One rgb image between depth 0 and 1, nearer to depth 1: depth 1 takes it, depth 0 gets nothing.
    t_rgb = d[0] + 0.019
    write_color(root / "rgb" / "x.png", random_color(rng))
    write_color(root / "rgb" / "y.png", random_color(rng))
    (root / "rgb.txt").write_text(f"{t_rgb:.6f} rgb/x.png\n{d[2] + 0.001:.6f} rgb/y.png\n")
    ds = TUMDataset(root)
    assert [round(f.timestamp - d[0], 4) for f in ds] == [round(d[1] - d[0], 4), round(d[2] - d[0], 4)]
    assert ds[0].meta["color_file"].endswith("x.png")


def test_tum_without_rgb_is_depth_only(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    (fake["root"] / "rgb.txt").unlink()
    ds = TUMDataset(fake["root"])
    assert len(ds) == 5 and ds[0].color is None


def test_tum_ground_truth_interpolated_with_slerp(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    ds = TUMDataset(fake["root"])
    for f in ds:
        # Depth stamps fall between 100 Hz samples; slerp + lerp reproduce the motion exactly.
        # (1e-6: float64 resolves a Unix time to ~2e-7 s)
        np.testing.assert_allclose(f.gt_pose, gt_motion(f.timestamp - fake["t0"]), atol=1e-6)
        assert rigidity_error(f.gt_pose) is None
    stamps, poses = ds.ground_truth()
    assert len(stamps) == len(poses) == 4


def test_interpolate_pose_nearest_and_none():
    stamps = np.array([0.0, 0.01, 0.5])
    poses = np.array([gt_motion(t) for t in stamps])
    np.testing.assert_allclose(interpolate_pose(stamps, poses, 0.005, 0.02), gt_motion(0.005), atol=1e-12)
    # Gap too wide to interpolate: the nearest sample within tolerance.
    np.testing.assert_allclose(interpolate_pose(stamps, poses, 0.02, 0.02), poses[1])
    np.testing.assert_allclose(interpolate_pose(stamps, poses, 0.49, 0.02), poses[2])
    assert interpolate_pose(stamps, poses, 0.2, 0.02) is None
    assert interpolate_pose(stamps, poses, -0.1, 0.02) is None
    np.testing.assert_array_equal(interpolate_pose(stamps, poses, 0.5, 0.02), poses[2])


def test_tum_frames_outside_ground_truth_have_none(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    gt = fake["root"] / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:2] + lines[-3:]) + "\n")  # only samples after the last frame
    ds = TUMDataset(fake["root"])
    assert not ds.has_ground_truth and ds[0].gt_pose is None


@pytest.mark.parametrize("name, expected", [
    ("rgbd_dataset_freiburg1_xyz", (517.3, 516.5, 318.6, 255.3)),
    ("rgbd_dataset_freiburg2_desk", (520.9, 521.0, 325.1, 249.7)),
    ("rgbd_dataset_freiburg3_long_office_household", (535.4, 539.2, 320.1, 247.6)),
    ("my_recording", (525.0, 525.0, 319.5, 239.5)),
])
def test_tum_intrinsics_from_folder_name(tmp_path, rng, name, expected):
    fake = make_tum(tmp_path, rng, n=2, name=name)
    K = TUMDataset(fake["root"]).intrinsics
    assert K.as_tuple() == pytest.approx(expected)
    assert (K.width, K.height) == (W, H)  # from the first depth image


def test_freiburg_camera_names():
    assert freiburg_camera("fr2_pioneer_360") == "freiburg2"
    assert freiburg_camera("rgbd_dataset_freiburg3_walking_xyz") == "freiburg3"
    assert freiburg_camera("surfr1") is None and freiburg_camera("fr12") is None


def test_tum_intrinsics_file_in_folder_and_config(tmp_path, rng):
    fake = make_tum(tmp_path, rng, n=2)
    (fake["root"] / "intrinsics.txt").write_text("50 51 20.5 14.5\n")  # focal lengths a 40x30 image can have
    assert TUMDataset(fake["root"]).intrinsics.as_tuple() == (50.0, 51.0, 20.5, 14.5)
    other = tmp_path / "cam.txt"
    other.write_text("# K\n60 0 21\n0 62 16\n0 0 1\n")
    K = TUMDataset(fake["root"], DatasetConfig(intrinsics_file=str(other))).intrinsics
    assert K.as_tuple() == (60.0, 62.0, 21.0, 16.0)


# --------------------------------------------------------------------------------------------------
# ICL-NUIM
# --------------------------------------------------------------------------------------------------
def test_iclnuim_frames_intrinsics_and_poses(tmp_path, rng):
    fake = make_icl(tmp_path, rng)
    ds = ICLNUIMDataset(fake["root"])
    assert len(ds) == 4 and ds.has_ground_truth
    assert ds.intrinsics.as_tuple() == (481.20, 480.0, 319.5, 239.5)
    for k, f in enumerate(ds):
        assert f.timestamp == k
        raw = fake["raws"][k]
        expected = raw.astype(np.float32) / 5000.0
        expected[(raw == 0) | (expected > 4.0)] = 0.0
        np.testing.assert_array_equal(f.depth, expected)
        np.testing.assert_array_equal(f.color, fake["colors"][k])
        if k == 0:
            assert f.gt_pose is None  # no ground-truth line for frame 0
        else:
            np.testing.assert_allclose(f.gt_pose, fake["poses"][k], atol=1e-9)
    stamps, poses = ds.ground_truth()
    assert stamps.tolist() == [1.0, 2.0, 3.0]


def test_iclnuim_numeric_order_not_lexical(tmp_path, rng):
    root = tmp_path / "icl"
    for k in (0, 1, 2, 10):
        write_depth(root / "depth" / f"{k}.png", random_depth(rng, 5000.0))
        write_color(root / "rgb" / f"{k}.png", random_color(rng))
    ds = ICLNUIMDataset(root)
    assert [f.timestamp for f in ds] == [0, 1, 2, 10] and not ds.has_ground_truth


# --------------------------------------------------------------------------------------------------
# 7-Scenes
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("color_ext", ["png", "jpg"])
def test_7scenes_depth_poses_intrinsics(tmp_path, rng, color_ext):
    fake = make_7scenes(tmp_path, rng, color_ext=color_ext)
    ds = SevenScenesDataset(fake["root"], DatasetConfig(depth_max=10.0))
    assert len(ds) == 6 and ds.has_ground_truth
    assert ds.intrinsics.as_tuple() == (58.0, 58.1, 20.0, 15.0)
    for k, f in enumerate(ds):
        raw = fake["raws"][k]
        expected = raw.astype(np.float32) / 1000.0
        expected[(raw == 0) | (raw == 65535)] = 0.0
        np.testing.assert_array_equal(f.depth, expected)
        assert f.depth[0, 0] == 0 and f.depth[0, 1] == 0
        if color_ext == "png":
            np.testing.assert_array_equal(f.color, fake["colors"][k])
        else:  # JPEG is lossy: the right image in the right channel order, approximately
            assert np.abs(f.color.astype(int) - fake["colors"][k]).mean() < 60
        assert f.timestamp == k
        # Re-orthonormalised: exactly a rotation, and the one before the 0.9998 scaling.
        R = f.gt_pose[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(f.gt_pose, fake["poses"][k], atol=1e-9)


def test_7scenes_default_intrinsics(tmp_path, rng):
    fake = make_7scenes(tmp_path, rng, n=2, intrinsics=False)
    K = SevenScenesDataset(fake["root"]).intrinsics
    assert K.as_tuple() == (585.0, 585.0, 320.0, 240.0) and (K.width, K.height) == (W, H)


# --------------------------------------------------------------------------------------------------
# Selection and downsampling (base.py), format detection
# --------------------------------------------------------------------------------------------------
def test_selection_and_downsampling(tmp_path, rng):
    fake = make_7scenes(tmp_path, rng, n=6)
    full = SevenScenesDataset(fake["root"])
    ds = SevenScenesDataset(fake["root"], downsample=2, start=1, stop=6, stride=2)
    assert ds.indices == [1, 3, 5] and len(ds) == 3
    assert [f.timestamp for f in ds] == [1.0, 3.0, 5.0]
    K, K0 = ds.intrinsics, full.intrinsics
    assert (K.width, K.height) == (20, 15)
    assert (K.fx, K.fy, K.cx, K.cy) == (K0.fx / 2, K0.fy / 2, K0.cx / 2, K0.cy / 2)
    f, f0 = ds[1], full[3]
    np.testing.assert_array_equal(f.depth, f0.depth[::2, ::2])
    np.testing.assert_array_equal(f.color, f0.color[::2, ::2])
    assert f.depth.flags.c_contiguous and f.intrinsics == K
    np.testing.assert_array_equal(f.gt_pose, f0.gt_pose)
    assert ds.frame_by_raw_index(4).timestamp == 4.0
    # Odd sizes round up, as img[::3, ::3] does.
    ds3 = SevenScenesDataset(fake["root"], downsample=3)
    assert ds3[0].depth.shape == (ds3.intrinsics.height, ds3.intrinsics.width) == (10, 14)
    stamps, _ = ds.ground_truth()
    assert stamps.tolist() == [1.0, 3.0, 5.0]


def test_open_dataset_applies_config(tmp_path, rng):
    fake = make_tum(tmp_path, rng)
    ds = open_dataset(DatasetConfig(path=str(fake["root"]), downsample=2, start=1, stride=2))
    assert isinstance(ds, TUMDataset) and len(ds) == 2 and ds[0].depth.shape == (15, 20)


def test_detect_each_format(tmp_path, rng):
    tum = make_tum(tmp_path / "a", rng, n=2)["root"]
    icl = make_icl(tmp_path / "b", rng, n=2)["root"]
    seven = make_7scenes(tmp_path / "c", rng, n=2)["root"]
    assert detect_format(tum) == "tum"
    assert detect_format(icl) == "iclnuim"
    assert detect_format(seven) == "7scenes"
    for root, cls in ((tum, TUMDataset), (icl, ICLNUIMDataset), (seven, SevenScenesDataset)):
        assert type(open_dataset(DatasetConfig(path=str(root)))) is cls
    # A TUM folder whose images have integer names (and no .gt.freiburg) stays TUM.
    (tum / "depth.txt").write_text("0 depth/0.png\n")
    write_depth(tum / "depth" / "0.png", random_depth(rng, 5000.0))
    assert detect_format(tum) == "tum"
    with pytest.raises(InputError, match="unrecognised"):
        detect_format(tmp_path)
    with pytest.raises(InputError, match="unknown dataset format"):
        open_dataset(DatasetConfig(path=str(tum), format="kitti"))


# --------------------------------------------------------------------------------------------------
# Bad input: InputError naming the file and the problem
# --------------------------------------------------------------------------------------------------
def _corrupt(path: Path) -> None:
    path.write_bytes(b"\x89PNG\r\n\x1a\nthis is not really a png")


def _bad_tum(kind: str, tmp_path: Path, rng) -> tuple[Path, str, str]:
    """(dataset root, file name the message must name, fragment of the problem)."""
    root = make_tum(tmp_path, rng, n=3)["root"]
    first_depth = sorted((root / "depth").iterdir())[0]
    first_rgb = sorted((root / "rgb").iterdir())[0]
    if kind == "missing listed rgb":
        first_rgb.unlink()
        return root, first_rgb.name, "does not exist"
    if kind == "missing listed depth":
        first_depth.unlink()
        return root, first_depth.name, "does not exist"
    if kind == "8-bit depth":
        cv2.imwrite(str(first_depth), rng.integers(0, 255, (H, W), dtype=np.uint8))
        return root, first_depth.name, "8-bit"
    if kind == "colour depth":
        cv2.imwrite(str(first_depth), random_color(rng))
        return root, first_depth.name, "channels"
    if kind == "corrupt depth":
        _corrupt(first_depth)
        return root, first_depth.name, "corrupt"
    if kind == "corrupt colour":
        _corrupt(first_rgb)
        return root, first_rgb.name, "corrupt"
    if kind == "colour size":
        write_color(first_rgb, rng.integers(0, 255, (H + 2, W, 3), dtype=np.uint8))
        return root, first_rgb.name, "40x32"
    if kind == "depth size":
        write_depth(sorted((root / "depth").iterdir())[1], np.ones((H, W + 4), np.uint16))
        return root, sorted((root / "depth").iterdir())[1].name, "44x30"
    if kind == "empty depth.txt":
        (root / "depth.txt").write_text("# nothing\n")
        return root, "depth.txt", "empty sequence"
    if kind == "no association":
        (root / "rgb.txt").write_text("1.0 rgb/" + first_rgb.name + "\n")
        return root, "rgb.txt", "empty sequence"
    if kind == "bad depth.txt line":
        (root / "depth.txt").write_text("abc depth/x.png\n")
        return root, "depth.txt", "line 1"
    if kind == "ground truth NaN":
        gt = root / "groundtruth.txt"
        lines = gt.read_text().splitlines()
        lines[4] = "1305031102.0 nan 0 0 0 0 0 1"
        gt.write_text("\n".join(lines))
        return root, "groundtruth.txt", "line 5"
    if kind == "ground truth not unit quaternion":
        gt = root / "groundtruth.txt"
        gt.write_text("1305031102.0 0 0 0 0 0 0 2\n")
        return root, "groundtruth.txt", "quaternion"
    if kind == "intrinsics file":
        (root / "intrinsics.txt").write_text("500 501 20\n")
        return root, "intrinsics.txt", "expected 4 numbers"
    raise AssertionError(kind)


TUM_CASES = ["missing listed rgb", "missing listed depth", "8-bit depth", "colour depth", "corrupt depth",
             "corrupt colour", "colour size", "depth size", "empty depth.txt", "no association",
             "bad depth.txt line", "ground truth NaN", "ground truth not unit quaternion", "intrinsics file"]


@pytest.mark.parametrize("kind", TUM_CASES)
def test_tum_bad_input(tmp_path, rng, kind):
    root, name, problem = _bad_tum(kind, tmp_path, rng)
    with pytest.raises(InputError) as info:
        ds = TUMDataset(root)
        for f in ds:
            pass
    assert name in str(info.value) and problem in str(info.value), str(info.value)


def _bad_7scenes(kind: str, tmp_path: Path, rng) -> tuple[Path, str, str]:
    root = make_7scenes(tmp_path, rng, n=3)["root"]
    pose = root / "frame-000001.pose.txt"
    T = se3_exp(rng.normal(0, 0.3, 6))
    if kind == "pose NaN":
        T[1, 2] = np.nan
        np.savetxt(pose, T)
        return root, pose.name, "line 2: contains NaN"
    if kind == "pose wrong shape":
        np.savetxt(pose, T[:3])
        return root, pose.name, "16 numbers"
    if kind == "pose scaled rotation":
        T[:3, :3] *= 1.1
        np.savetxt(pose, T)
        return root, pose.name, "not orthonormal"
    if kind == "pose reflection":
        T[:3, 0] *= -1
        np.savetxt(pose, T)
        return root, pose.name, "reflection"
    if kind == "pose last row":
        T[3, 0] = 0.5
        np.savetxt(pose, T)
        return root, pose.name, "last row"
    if kind == "pose text":
        pose.write_text("identity\n")
        return root, pose.name, "expected numbers"
    if kind == "8-bit depth":
        cv2.imwrite(str(root / "frame-000002.depth.png"), np.zeros((H, W), np.uint8))
        return root, "frame-000002.depth.png", "8-bit"
    if kind == "colour size":
        write_color(root / "frame-000000.color.png", np.zeros((H, W + 1, 3), np.uint8))
        return root, "frame-000000.color.png", "41x30"
    if kind == "corrupt colour":
        _corrupt(root / "frame-000002.color.png")
        return root, "frame-000002.color.png", "corrupt"
    if kind == "empty":
        for p in root.glob("frame-*.depth.png"):
            p.unlink()
        return root, root.name, "empty sequence"
    if kind == "intrinsics":
        (root / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n0 1 1\n")
        return root, "camera-intrinsics.txt", "last row"
    raise AssertionError(kind)


SEVEN_CASES = ["pose NaN", "pose wrong shape", "pose scaled rotation", "pose reflection", "pose last row",
               "pose text", "8-bit depth", "colour size", "corrupt colour", "empty", "intrinsics"]


@pytest.mark.parametrize("kind", SEVEN_CASES)
def test_7scenes_bad_input(tmp_path, rng, kind):
    root, name, problem = _bad_7scenes(kind, tmp_path, rng)
    with pytest.raises(InputError) as info:
        for f in SevenScenesDataset(root):
            pass
    assert name in str(info.value) and problem in str(info.value), str(info.value)


@pytest.mark.parametrize("kind", ["missing rgb", "empty depth", "16-bit colour depth", "gt not frame numbers"])
def test_iclnuim_bad_input(tmp_path, rng, kind):
    root = make_icl(tmp_path, rng, n=3)["root"]
    if kind == "missing rgb":
        (root / "rgb" / "1.png").unlink()
        name, problem = "1.png", "does not exist"
    elif kind == "empty depth":
        for p in (root / "depth").iterdir():
            p.unlink()
        name, problem = "depth", "empty sequence"
    elif kind == "16-bit colour depth":
        cv2.imwrite(str(root / "depth" / "2.png"), np.zeros((H, W, 3), np.uint16))
        name, problem = "2.png", "3 channels"
    else:
        (root / "livingRoom0.gt.freiburg").write_text("0.5 0 0 0 0 0 0 1\n")
        name, problem = "livingRoom0.gt.freiburg", "frame numbers"
    with pytest.raises(InputError) as info:
        for f in ICLNUIMDataset(root):
            pass
    assert name in str(info.value) and problem in str(info.value), str(info.value)


@pytest.mark.parametrize("cls", [TUMDataset, ICLNUIMDataset, SevenScenesDataset])
def test_missing_folder(tmp_path, cls):
    missing = tmp_path / "no_such_sequence"
    with pytest.raises(InputError, match="no_such_sequence.*does not exist"):
        cls(missing)
    for fmt in ("auto", "tum"):
        with pytest.raises(InputError, match="no_such_sequence"):
            open_dataset(DatasetConfig(path=str(missing), format=fmt))
        file = tmp_path / "depth.png"
        file.write_bytes(b"")
        with pytest.raises(InputError, match="depth.png: not a folder"):
            open_dataset(DatasetConfig(path=str(file), format=fmt))


def test_tum_missing_depth_txt_names_file(tmp_path):
    (tmp_path / "seq").mkdir()
    with pytest.raises(InputError, match="depth.txt.*not found"):
        TUMDataset(tmp_path / "seq")


# --------------------------------------------------------------------------------------------------
# Real data: the shared 7-Scenes redkitchen frames
# --------------------------------------------------------------------------------------------------
def test_redkitchen_loads_with_poses(redkitchen):
    ds = open_dataset(DatasetConfig(path=str(redkitchen)))
    assert isinstance(ds, SevenScenesDataset) and len(ds) == 500 and ds.has_ground_truth
    assert ds.intrinsics.as_tuple() == (585.0, 585.0, 320.0, 240.0)
    assert (ds.intrinsics.width, ds.intrinsics.height) == (640, 480)
    stamps, poses = ds.ground_truth()
    assert stamps.tolist() == list(range(500))  # every frame has a pose
    for T in poses:
        assert rigidity_error(T) is None
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
    # Same poses as the shared TUM-format file (9 printed decimals, derived before orthonormalising).
    gt_stamps, gt_poses = read_tum(redkitchen / "groundtruth_tum.txt")
    np.testing.assert_array_equal(gt_stamps, stamps)
    np.testing.assert_allclose(poses, gt_poses, atol=1e-4)
    for i in (0, 250, 499):
        f = ds[i]
        assert f.timestamp == i and f.depth.shape == (480, 640) and f.color.shape == (480, 640, 3)
        valid = f.depth[f.depth > 0]
        assert valid.size > 0.5 * f.depth.size
        assert 0.3 < valid.min() and valid.max() <= 5.0
        assert 0.5 < np.median(valid) < 4.0
        np.testing.assert_array_equal(f.gt_pose, poses[i])


# --------------------------------------------------------------------------------------------------
# What a user needs to trust the frames: detection by evidence, the scale and intrinsics in use,
# frames reordered or dropped said aloud, selections that select nothing refused
# --------------------------------------------------------------------------------------------------
def _numbered_folder(root: Path, rng, n: int = 3) -> Path:
    """rgb/N.png + depth/N.png and nothing else: the layout of many recordings, not only ICL-NUIM's."""
    for k in range(n):
        write_depth(root / "depth" / f"{k}.png", random_depth(rng, 1000.0))
        write_color(root / "rgb" / f"{k}.png", random_color(rng))
    return root


def test_numbered_pngs_alone_are_not_taken_for_iclnuim(tmp_path, rng):
    root = _numbered_folder(tmp_path / "realsense", rng)
    with pytest.raises(InputError) as info:
        open_dataset(DatasetConfig(path=str(root)))
    message = str(info.value)
    assert message.startswith(str(root)) and "depth scale and intrinsics are unknown" in message
    assert "--format iclnuim" in message
    # Said explicitly, it is read as ICL-NUIM, and the format line says it was given, not detected.
    ds = open_dataset(DatasetConfig(path=str(root), format="iclnuim"))
    assert isinstance(ds, ICLNUIMDataset) and ds.describe()["format_from"] == "given by --format or dataset.format"
    # ICL-NUIM's ground-truth file is what identifies it.
    (root / "livingRoom2.gt.freiburg").write_text("1 0 0 0 0 0 0 1\n")
    assert detect(root) == ("iclnuim", "livingRoom2.gt.freiburg")


def test_a_folder_with_two_formats_files_is_refused(tmp_path, rng):
    root = make_tum(tmp_path, rng, n=2)["root"]
    write_depth(root / "frame-000000.depth.png", random_depth(rng, 1000.0))
    with pytest.raises(InputError, match="more than one format: tum \\(depth.txt\\), 7scenes "
                                         "\\(frame-000000.depth.png files\\); pass --format tum or --format 7scenes"):
        open_dataset(DatasetConfig(path=str(root)))
    assert isinstance(open_dataset(DatasetConfig(path=str(root), format="tum")), TUMDataset)
    (root / "living.gt.freiburg").write_text("")
    with pytest.raises(InputError, match="--format tum or --format iclnuim or --format 7scenes"):
        detect_format(root)


def test_detection_evidence(tmp_path, rng):
    assert detect(make_tum(tmp_path / "a", rng, n=2)["root"]) == ("tum", "depth.txt")
    assert detect(make_icl(tmp_path / "b", rng, n=2)["root"]) == ("iclnuim", "livingRoom0.gt.freiburg")
    assert detect(make_7scenes(tmp_path / "c", rng, n=2)["root"]) == ("7scenes", "frame-000000.depth.png files")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "rgb.txt").write_text("")
    with pytest.raises(InputError, match="unrecognised dataset layout.*or pass --format"):
        detect(tmp_path / "d")


def test_the_unrecognised_layout_line_names_what_identifies_each_format(tmp_path):
    with pytest.raises(InputError) as info:
        detect(tmp_path)
    assert str(info.value) == (f"{tmp_path}: unrecognised dataset layout: expected TUM (depth.txt), ICL-NUIM "
                               "(*.gt.freiburg), 7-Scenes (frame-XXXXXX.depth.png), a ROS 2 bag (metadata.yaml, "
                               "*.mcap) or a run log (log.mcap); or pass --format")


class OneFileFormat(Dataset):
    """A reader as a contributor adds one: this class and one line in ti_fusion/io/formats.py."""

    format = "onefile"
    identified_by = "a one-file sequence (frames.npz)"
    single_file = True

    def __init__(self, root, config=None, **selection):
        super().__init__(root, **selection)
        path = self.root if self.root.is_file() else self.root / "frames.npz"
        self._depth = np.load(path)["depth"]

    @staticmethod
    def detect(root: Path) -> str | None:
        root = Path(root)
        if root.is_file():
            return "a .npz file" if root.suffix == ".npz" else None
        return "frames.npz" if (root / "frames.npz").is_file() else None

    def _num_raw_frames(self) -> int:
        return len(self._depth)

    def _load_raw(self, raw_index: int) -> Frame:
        return Frame(index=raw_index, timestamp=float(raw_index), depth=self._depth[raw_index],
                     intrinsics=self.raw_intrinsics)

    @property
    def raw_intrinsics(self) -> Intrinsics:
        return Intrinsics(50.0, 50.0, (W - 1) / 2, (H - 1) / 2, W, H)


def test_a_reader_registered_by_one_line_is_detected_opened_and_named(tmp_path, monkeypatch, rng):
    from ti_fusion.config import load_config
    from ti_fusion.io import formats

    monkeypatch.setitem(formats.LOADERS, "onefile", f"{__name__}:OneFileFormat")
    root = tmp_path / "seq"
    root.mkdir()
    np.savez(root / "frames.npz", depth=rng.uniform(0.5, 3.0, (4, H, W)).astype(np.float32))
    assert detect(root) == ("onefile", "frames.npz")
    assert detect(root / "frames.npz") == ("onefile", "a .npz file")  # single_file: the file alone is an input
    ds = open_dataset(DatasetConfig(path=str(root), stride=2))
    assert isinstance(ds, OneFileFormat) and len(ds) == 2 and ds.format_from == "detected from frames.npz"
    assert load_config(None, ["dataset.format=onefile"]).dataset.format == "onefile"  # the config's choices
    with pytest.raises(InputError, match=r"expected TUM \(depth.txt\), .*, a run log \(log.mcap\) or a one-file "
                                         r"sequence \(frames.npz\); or pass --format"):
        detect(tmp_path)


def test_describe_and_the_format_line_say_scale_intrinsics_and_their_source(tmp_path, rng, caplog):
    tum = make_tum(tmp_path / "a", rng, n=3)["root"]  # rgbd_dataset_freiburg1_fake
    with caplog.at_level(logging.INFO, logger="ti_fusion"):
        ds = open_dataset(DatasetConfig(path=str(tum)))
    d = ds.describe()
    assert d["format"] == "tum" and d["format_from"] == "detected from depth.txt"
    assert d["depth_scale"] == 5000.0
    assert d["intrinsics"] == {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3, "width": W, "height": H,
                               "source": "the TUM freiburg1 calibration, named by the folder name"}
    assert d["ground_truth_frames"] == 2 and d["dropped_frames"] == 1 and d["color"] is True
    json.dumps(d)  # goes into summary.json and the log's metadata as it is
    assert ("format: tum (detected from depth.txt); depth 5000 units per metre; intrinsics fx 517.3 fy 516.5 "
            f"cx 318.6 cy 255.3 at {W}x{H} (the TUM freiburg1 calibration, named by the folder name)") in caplog.messages
    icl = open_dataset(DatasetConfig(path=str(make_icl(tmp_path / "b", rng, n=2)["root"]))).describe()
    assert icl["depth_scale"] == 5000.0 and icl["intrinsics"]["source"] == "ICL-NUIM's published intrinsics"
    seven = open_dataset(DatasetConfig(path=str(make_7scenes(tmp_path / "c", rng, n=2)["root"]))).describe()
    assert seven["depth_scale"] == 1000.0 and seven["intrinsics"]["source"] == "camera-intrinsics.txt in the dataset folder"
    assert seven["intrinsics"]["fx"] == 58.0


def test_tum_default_intrinsics_are_a_warned_guess(tmp_path, rng, caplog):
    root = make_tum(tmp_path, rng, n=2, name="my_recording")["root"]
    with caplog.at_level(logging.WARNING, logger="ti_fusion"):
        ds = TUMDataset(root)
    assert ds.intrinsics_source == "the ROS default: a guess"
    assert any("ROS default 525, 525, 319.5, 239.5" in m and "intrinsics.txt" in m for m in caplog.messages)


def test_tum_depth_list_out_of_time_order_is_sorted_and_said(tmp_path, rng, caplog):
    fake = make_tum(tmp_path, rng, n=5)
    depth_txt = fake["root"] / "depth.txt"
    header, *lines = [l for l in depth_txt.read_text().splitlines() if not l.startswith("# timestamp")]
    depth_txt.write_text("\n".join([header, lines[3], lines[0], lines[4], lines[2], lines[1]]) + "\n")
    with caplog.at_level(logging.WARNING, logger="ti_fusion"):
        ds = TUMDataset(fake["root"])
    stamps = [f.timestamp for f in ds]
    assert stamps == sorted(stamps) and len(stamps) == 4  # the last depth image has no rgb partner
    for k, f in enumerate(ds):
        np.testing.assert_array_equal(f.depth, fake["raws"][k].astype(np.float32) / 5000.0 * (fake["raws"][k] <= 20000))
    note = "depth.txt lists its 5 images out of time order: they are taken in timestamp order"
    assert note in ds.describe()["notes"] and any(note in m for m in caplog.messages)


def test_tum_depth_list_with_a_repeated_timestamp_is_refused(tmp_path, rng):
    fake = make_tum(tmp_path, rng, n=3)
    depth_txt = fake["root"] / "depth.txt"
    first = [l for l in depth_txt.read_text().splitlines() if not l.startswith("#")][0]
    depth_txt.write_text(depth_txt.read_text() + first + "\n")
    with pytest.raises(InputError, match=r"depth.txt: timestamp 1305031102.000000 is listed twice \(lines 3 and 6\)"):
        TUMDataset(fake["root"])


def test_tum_depth_images_without_rgb_are_counted_and_named(tmp_path, rng, caplog):
    fake = make_tum(tmp_path, rng, n=5)  # the last depth image has no rgb image within 0.02 s
    with caplog.at_level(logging.WARNING, logger="ti_fusion"):
        ds = TUMDataset(fake["root"])
    d = ds.describe()
    assert len(ds) == 4 and d["frames"] == 4 and d["dropped_frames"] == 1
    note = f"1 of 5 depth images have no rgb image within 0.02 s and are left out (timestamps {fake['depth_stamps'][4]:.6f})"
    assert d["notes"] == [note] and any(note in m for m in caplog.messages)
    assert TUMDataset(make_tum(tmp_path / "b", rng, n=2)["root"]).describe()["dropped_frames"] == 1


def test_a_missing_color_image_stops_every_format(tmp_path, rng):
    """A file missing from a sequence that has one per frame stops the loader, in each format (no frame
    quietly without colour, no frame quietly left out); a sequence with no colour at all is depth-only."""
    seven = make_7scenes(tmp_path / "a", rng, n=4)["root"]
    (seven / "frame-000002.color.png").unlink()
    with pytest.raises(InputError, match="frame-000002.color.png: colour image of frame-000002.depth.png does not exist"):
        SevenScenesDataset(seven)
    for p in seven.glob("*.color.png"):
        p.unlink()
    ds = SevenScenesDataset(seven)
    assert len(ds) == 4 and ds[0].color is None and ds.describe()["color"] is False
    icl = make_icl(tmp_path / "b", rng, n=3)["root"]
    (icl / "rgb" / "1.png").unlink()
    with pytest.raises(InputError, match="1.png: colour image for depth/1.png does not exist"):
        ICLNUIMDataset(icl)
    tum = make_tum(tmp_path / "c", rng, n=3)["root"]
    sorted((tum / "rgb").iterdir())[1].unlink()
    with pytest.raises(InputError, match="image listed in rgb.txt \\(line 3\\) does not exist"):
        TUMDataset(tum)
    for cls, root in ((SevenScenesDataset, seven), (ICLNUIMDataset, make_icl(tmp_path / "d", rng, n=2)["root"])):
        assert open_dataset(DatasetConfig(path=str(root))).describe()["dropped_frames"] == 0


@pytest.mark.parametrize("selection, message", [
    (dict(start=6), "no frames selected: the sequence has 6 frames (0 to 5), and start 6, stride 1 select none"),
    (dict(start=2, stop=2), "start 2, stop 2, stride 1 select none"),
    (dict(downsample=6), "--downsample 6 turns the 40x30 frames into 7x5: at least 8 pixels per side are "
                         "needed, so at most --downsample 4"),
    (dict(start=-1), "dataset.start = -1: must be an integer of at least 0"),
    (dict(stop=-2), "dataset.stop = -2: must be an integer of at least 0"),
    (dict(stride=0), "dataset.stride = 0: must be an integer of at least 1"),
    (dict(downsample=0), "dataset.downsample = 0: must be an integer of at least 1"),
])
def test_selections_that_select_nothing_are_refused(tmp_path, rng, selection, message):
    root = make_7scenes(tmp_path, rng, n=6)["root"]
    with pytest.raises(InputError) as info:
        open_dataset(DatasetConfig(path=str(root), **selection))
    assert message in str(info.value)
    assert len(open_dataset(DatasetConfig(path=str(root), downsample=4))) == 6  # 10x8: the smallest allowed


def test_a_selection_past_the_end_says_how_many_frames_it_takes(tmp_path, rng, caplog):
    root = make_7scenes(tmp_path, rng, n=6)["root"]
    with caplog.at_level(logging.WARNING, logger="ti_fusion"):
        ds = open_dataset(DatasetConfig(path=str(root), start=2, stop=600))
    note = "the selection runs to frame 599, the sequence ends at frame 5: 4 frames are taken"
    assert len(ds) == 4 and ds.describe()["notes"] == [note] and any(note in m for m in caplog.messages)
    assert open_dataset(DatasetConfig(path=str(root), stop=6)).describe()["notes"] == []


def test_frame_numbers_are_never_counted_from_the_end(tmp_path, rng):
    ds = SevenScenesDataset(make_7scenes(tmp_path, rng, n=3)["root"])
    for i in (-1, 3):
        with pytest.raises(IndexError):
            ds.frame_by_raw_index(i)
    assert ds.frame_by_raw_index(2).index == 2


def test_a_corrupt_image_is_one_line_and_nothing_else(tmp_path, rng, capfd):
    """libpng writes its own 'libpng error: ...' straight to the process's stderr; only our line remains."""
    root = make_7scenes(tmp_path, rng, n=2)["root"]
    depth = root / "frame-000001.depth.png"
    data = depth.read_bytes()
    for broken in (data[:-12], data[:40] + bytes([data[40] ^ 0xFF]) + data[41:]):
        depth.write_bytes(broken)
        with pytest.raises(InputError, match="frame-000001.depth.png: unreadable or corrupt image"):
            SevenScenesDataset(root)[1]
    out, err = capfd.readouterr()
    assert out == "" and err == ""


@pytest.mark.parametrize("text", ["1 2 3\n4 5 6\n", "1,2,3\n\n 4\t5 6 \n", "# K\n585 0 320\n0 585 240\n0 0 1\n",
                                  "", "1e-3 -0.5\r\n2 3\r\n", "1 2 x\n", "1 2\nnan 3\n", "1 2\ninf 3\n"])
def test_read_numbers_is_the_line_by_line_reading(tmp_path, text):
    """The whole-file parse gives the numbers, or the error naming the line, that reading line by line gives."""
    from ti_fusion.io.datasets.imageio import read_numbers
    from ti_fusion.io.tables import parse_floats, read_table

    path = tmp_path / "numbers.txt"
    path.write_text(text)

    def line_by_line():
        parsed = [parse_floats(fields, path, lineno) for lineno, fields in read_table(path, "file")]
        return np.concatenate(parsed) if parsed else np.zeros(0)

    try:
        want = line_by_line()
    except InputError as exc:
        with pytest.raises(InputError) as info:
            read_numbers(path, "file")
        assert str(info.value) == str(exc)
    else:
        got = read_numbers(path, "file")
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)
    with pytest.raises(InputError, match="not found"):
        read_numbers(tmp_path / "missing.txt", "file")
