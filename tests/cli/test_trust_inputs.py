"""What a user meets at the command line when the input is not what it seems: calibrations with distortion or
skew used or refused, intrinsics that cannot be the images' camera, a killed run's log replayed, ground
truth on another clock, depth in the wrong units or beyond the range, frames too small for ICP's pyramid,
and a negative number given to --intrinsics."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from ti_fusion.cli.main import main

FRAMES = 12
W, H = 160, 120
K = (131.25, 131.25, 79.5, 59.5)  # the synthetic camera at 160x120
DISTORTION = [0.25, -0.8, 0.001, 0.002, 0.9]


def _stderr_lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def tum(tmp_path_factory):
    """``ti-fusion synth``'s TUM folder: FRAMES frames at 160x120 (depth 5000 units per metre)."""
    from ti_fusion.backend import init_backend

    init_backend("cpu")
    root = tmp_path_factory.mktemp("synthetic") / "tum"
    assert main(["synth", str(root), "--frames", str(FRAMES), "--width", str(W), "--quiet"]) == 0
    return root


def folder(tum: Path, root: Path, camera: str | None = None) -> Path:
    """The TUM sequence as a plain folder: depth/N.png (5000 units per metre), rgb/N.png, no timestamps.txt;
    ``camera``: the text of its camera.yaml."""
    (root / "depth").mkdir(parents=True)
    (root / "rgb").mkdir()
    for i, line in enumerate((tum / "associations.txt").read_text().splitlines()):
        _, rgb, _, depth = line.split()
        shutil.copy(tum / depth, root / "depth" / f"{i}.png")
        shutil.copy(tum / rgb, root / "rgb" / f"{i}.png")
    if camera is not None:
        (root / "camera.yaml").write_text(camera)
    return root


def camera_info(d=(0, 0, 0, 0, 0), model="plumb_bob", skew=0.0) -> str:
    fx, fy, cx, cy = K
    return (f"header:\n  frame_id: cam\nheight: {H}\nwidth: {W}\ndistortion_model: {model}\n"
            f"d: [{', '.join(map(str, d))}]\nk: [{fx}, {skew}, {cx}, 0.0, {fy}, {cy}, 0.0, 0.0, 1.0]\n")


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


# --------------------------------------------------------------------------------------------------
# Class 1: distortion and skew are used (undistorted every frame) or refused with one line
# --------------------------------------------------------------------------------------------------
def test_a_calibration_with_distortion_and_skew_is_used_and_said(cpu, tum, tmp_path, capsys):
    data = folder(tum, tmp_path / "cam", camera_info(DISTORTION, skew=40.0))
    out = tmp_path / "run"
    assert main(["vo", str(data), "--format", "folder", "--depth-scale", "5000", "--frames", "3", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert ("skew 40 and plumb_bob distortion [0.25, -0.8, 0.001, 0.002, 0.9]: every frame is undistorted to the "
            "pinhole camera") in stdout
    intrinsics = _summary(out)["dataset"]["intrinsics"]
    assert intrinsics["distortion"] == DISTORTION and intrinsics["skew"] == 40.0 and intrinsics["undistorted"]


OPENCV = """%YAML:1.0
---
image_width: 160
image_height: 120
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 131.25, 0., 79.5, 0., 131.25, 59.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ 0.25, -0.8, 0.001, 0.002, 0.9 ]
"""


def test_an_opencv_calibrations_distortion_is_read(tmp_path):
    from ti_fusion.io.datasets.imageio import read_intrinsics_file

    path = tmp_path / "opencv.yaml"
    path.write_text(OPENCV)
    K_ = read_intrinsics_file(path, W, H)
    assert K_.distortion == tuple(DISTORTION) and not K_.pinhole and K_.undistorted().pinhole


@pytest.mark.parametrize("camera, message", [
    (camera_info(DISTORTION, model="double_sphere"), "distortion model 'double_sphere' is not supported (plumb_bob, "
                                                     "rational_polynomial, equidistant): undistort the images first "
                                                     "and give a calibration without it"),
    (camera_info([0.1, 0.2, 0.0], model="plumb_bob"), "3 distortion coefficients for the plumb_bob model, which "
                                                      "takes 4 or 5 or 8 or 12 or 14"),
])
def test_a_distortion_that_cannot_be_undistorted_is_one_line(tum, tmp_path, capsys, camera, message):
    data = folder(tum, tmp_path / "cam", camera)
    assert main(["vo", str(data), "--format", "folder", "--depth-scale", "5000", "--out", str(tmp_path / "run"),
                 "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion vo: error: {data / 'camera.yaml'}: {message}"]


# --------------------------------------------------------------------------------------------------
# Class 4 and 14: intrinsics that cannot be the images' camera; a negative number to --intrinsics
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec, message", [
    ("525,525,5000,-300", "principal point (5000, -300) is outside the 160x120 image (cx in [0, 159], cy in "
                          "[0, 119]; the image's centre is (79.5, 59.5))"),
    ("1e-6,1e-6,79.5,59.5", "fx 1e-06, fy 1e-06 give a 180° x 180° field of view at 160x120: outside 20° to 170°, "
                            "so not this image's camera (a 60° view needs fx about 139; focal lengths are in pixels "
                            "of these images)"),
    ("-525,525,79.5,59.5", "focal lengths must be positive (fx=-525, fy=525)"),
])
def test_intrinsics_that_cannot_be_the_images_camera_are_one_line(tum, tmp_path, capsys, spec, message):
    data = folder(tum, tmp_path / "cam")
    assert main(["vo", str(data), "--format", "folder", "--depth-scale", "5000", "--intrinsics", spec,
                 "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion vo: error: --intrinsics {spec}: {message}"]


# --------------------------------------------------------------------------------------------------
# Class 6: a killed run's log replays up to the cut
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run_log(tum, tmp_path_factory):
    out = tmp_path_factory.mktemp("logged") / "run"
    assert main(["vo", str(tum), "--set", "log.depth_every=1", "--out", str(out), "--quiet"]) == 0
    return out / "log.mcap"


@pytest.mark.slow
@pytest.mark.parametrize("keep, frames", [(-3000, FRAMES), (0.6, None)])
def test_a_killed_runs_log_replays_up_to_the_cut_with_a_note(cpu, run_log, tmp_path, capsys, keep, frames):
    data = run_log.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[:keep] if keep < 0 else data[:int(len(data) * keep)])
    out = tmp_path / "replay"
    assert main(["vo", str(cut), "--out", str(out), "--quiet"]) == 0
    lines = _stderr_lines(capsys)
    replayed = _summary(out)["frames"]
    assert lines[0].startswith(f"ti-fusion vo: warning: {cut}: the log ends without its summary (its run was stopped "
                               f"before finishing it, in the middle of a record): the {replayed} depth images written "
                               "before the cut are replayed")  # (and, where the cut fell inside a frame, that it was left out)
    assert replayed == frames if frames else 2 <= replayed < FRAMES
    assert main(["vo", str(cut), "--format", "log", "--out", str(tmp_path / "again"), "--quiet"]) == 0


# --------------------------------------------------------------------------------------------------
# Class 8: ground truth on another clock
# --------------------------------------------------------------------------------------------------
def test_ground_truth_times_that_are_not_frame_numbers_are_refused(tum, tmp_path, capsys):
    data = folder(tum, tmp_path / "cam", camera_info())
    shutil.copy(tum / "groundtruth.txt", data / "groundtruth.txt")  # TUM times 1.0 to 1.37, frames 0 to 11
    assert main(["vo", str(data), "--format", "folder", "--depth-scale", "5000", "--out", str(tmp_path / "run"),
                 "--quiet"]) == 2
    assert _stderr_lines(capsys) == [
        f"ti-fusion vo: error: {data / 'groundtruth.txt'}: only 1 of {FRAMES} frames have a pose within 0.02 s of "
        "their time (the frame numbers (no timestamps.txt): 0.000000 to 11.000000; the file: 1.000000 to 1.366667): "
        "without timestamps.txt a frame's time is its number, so these match by chance; add timestamps.txt (one time "
        "per frame, on the ground truth's clock), or give poses by frame number"]


def test_no_headline_ate_over_fewer_than_half_of_the_frames(tum, tmp_path, capsys):
    data = tmp_path / "tum"
    shutil.copytree(tum, data)
    lines = (data / "groundtruth.txt").read_text().splitlines()
    (data / "groundtruth.txt").write_text("\n".join(lines[:3 + 4]) + "\n")  # frames 0..3 of 12
    out = tmp_path / "run"
    assert main(["vo", str(data), "--out", str(out), "--quiet"]) == 0
    assert _stderr_lines(capsys) == [f"ti-fusion vo: warning: no ATE or RPE: only 4 of the {FRAMES} posed frames have "
                                     "ground truth, fewer than half (are its times on the frames' clock?)"]
    summary = _summary(out)
    assert "ate_rmse_m" not in summary and summary["gt_frames"] == 4


# --------------------------------------------------------------------------------------------------
# Class 11: depth in the wrong units, or nothing done
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scale, message", [
    ("50", "the first frames' depth with depth scale 50 units per metre (--depth-scale / dataset.depth_scale) is "),
    ("5000000", "the first frames' depth with depth scale 5e+06 units per metre (--depth-scale / "
                "dataset.depth_scale): 95 % of its depth is under 5 cm"),
])
def test_depth_in_the_wrong_units_is_refused_before_the_first_frame(cpu, tum, tmp_path, capsys, scale, message):
    data = folder(tum, tmp_path / "cam", camera_info())
    out = tmp_path / "run"
    assert main(["slam", str(data), "--format", "folder", "--depth-scale", scale, "--out", str(out), "--quiet"]) == 2
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith(f"ti-fusion slam: error: {data}: {message}")
    assert "--depth-scale 5000 would make its median" in lines[0]
    assert not (out / "log.mcap").exists()  # refused before the run


def test_a_32fc1_bag_holding_millimetres_is_refused_naming_the_scale(tmp_path, rng, capsys):
    import dataclasses

    from tests.io.test_rosbag import small_shots, write_bag

    shots = [dataclasses.replace(s, depth=s.depth * 1000) for s in small_shots(rng)]  # 500 to 3000 "metres"
    bag = write_bag(tmp_path / "bag", shots, depth_encoding="32FC1")
    out = tmp_path / "run"
    assert main(["vo", str(bag), "--out", str(out), "--quiet"]) == 2
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith(f"ti-fusion vo: error: {bag}: the first frames' depth with depth "
                                                   "scale 1 units per metre (")
    assert ("100% of it beyond dataset.depth_max = 4 m, so nothing would be left; --depth-scale 1000 would make its "
            "median") in lines[0]


def test_a_run_in_which_no_frame_had_depth_exits_non_zero(cpu, tum, tmp_path, capsys):
    data = folder(tum, tmp_path / "cam", camera_info())
    for path in (data / "depth").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((H, W), np.uint16))
    out = tmp_path / "run"
    assert main(["slam", str(data), "--format", "folder", "--depth-scale", "5000", "--frames", "3", "--out", str(out),
                 "--quiet"]) == 2
    assert _stderr_lines(capsys) == [
        f"ti-fusion slam: error: {data}: none of the 3 frames got a pose (no valid depth): nothing was mapped. Check "
        "the depth's units and range: depth scale 5000 units per metre (--depth-scale), dataset.depth_max = 4 m"]
    assert (out / "log.mcap").is_file()


def test_feature_odometry_that_posed_no_frame_exits_non_zero(tum, tmp_path, capsys):
    data = folder(tum, tmp_path / "cam", camera_info())
    for path in (data / "rgb").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((H, W, 3), np.uint8))  # nothing for ORB to find
    out = tmp_path / "run"
    assert main(["vo", str(data), "--format", "folder", "--depth-scale", "5000", "--frames", "3", "--out", str(out),
                 "--quiet"]) == 2
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith(f"ti-fusion vo: error: {data}: none of the 3 frames got a pose "
                                                   "(rejected: ")
    assert "depth" not in lines[0]  # not a depth problem: no advice about the depth scale


# --------------------------------------------------------------------------------------------------
# Class 14: frames too small for ICP's pyramid get the setting that fits them
# --------------------------------------------------------------------------------------------------
def test_frames_lost_for_being_small_get_a_hint():
    from ti_fusion.cli.slam import _small_frames_hint
    from ti_fusion.config import Config

    lost = [{"frame": i, "reason": "lost: level 2 iteration 0: too few inliers (46 < 100)"} for i in range(1, 15)]
    summary = {"frames": 15, "tracking_failures": 14, "failed_frames": lost,
               "resolution": {"tracked_at": [64, 48]}}
    assert _small_frames_hint(Config(), summary) == (
        "14 of 15 frames were lost with too few ICP inliers: frames tracked at 64x48 are small for ICP's 3 pyramid "
        "levels (its coarsest 16x12); --set icp.iterations=[10,5] keeps 2 (coarsest 32x24)")
    summary["resolution"]["tracked_at"] = [320, 240]
    assert _small_frames_hint(Config(), summary) is None
    one = {"frames": 1, "tracking_failures": 0, "failed_frames": [], "resolution": {"tracked_at": [64, 48]}}
    assert _small_frames_hint(Config(), one) is None  # nothing lost: nothing to explain


@pytest.mark.parametrize("option", [["--ground-truth", "missing.tum"], ["--depth-topic", "/camera/depth"],
                                    ["--gt-topic", "/vicon"]])
def test_an_option_that_cannot_apply_to_the_input_says_so(tum, tmp_path, capsys, option):
    """A TUM folder has its own ground truth and no topics: --ground-truth (even of a missing file) and the
    bag options were ignored without a word (exit 0)."""
    out = tmp_path / "run"
    assert main(["slam", str(tum), *option, "--out", str(out), "--quiet"]) == 2
    lines = _stderr_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith(f"ti-fusion slam: error: {option[0]} (dataset.")
    assert "does not apply to a tum dataset" in lines[0]
    assert not out.exists()


def test_a_ground_truth_file_that_is_missing_is_exit_2(tum, tmp_path, capsys):
    data = folder(tum, tmp_path / "plain")
    assert main(["slam", str(data), "--format", "folder", "--depth-scale", "5000", "--intrinsics",
                 ",".join(map(str, K)), "--ground-truth", str(tmp_path / "gt.tum"), "--out", str(tmp_path / "run"),
                 "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion slam: error: {tmp_path / 'gt.tum'}: trajectory file not found"]


@pytest.mark.slow
def test_a_dataset_path_that_is_not_utf8(cpu, tum, tmp_path, capsys):
    """A folder name with a byte that is not UTF-8 (Python keeps it as a lone surrogate): the log's metadata
    and the plot's title write it escaped, instead of a UnicodeEncodeError traceback."""
    import os

    from ti_fusion.io.mcap_log import read_log

    data = Path(os.fsdecode(bytes(tmp_path) + b"/caf\xe9"))
    shutil.copytree(tum, data)
    out = tmp_path / "run"
    assert main(["slam", str(data), "--frames", "3", "--out", str(out), "--quiet"]) == 0
    # --quiet keeps the one line that says what was understood of the input
    assert "format: tum (detected from" in capsys.readouterr().out
    assert (out / "trajectory.png").is_file()
    assert read_log(out / "log.mcap").metadata_value("dataset", "name") == "caf\\xe9"


def test_a_late_error_still_writes_summary_json(cpu, tum, tmp_path, capsys):
    """A frame that cannot be read, late in the run: the run ends with exit 2 and one line, and the frames
    done keep their outputs, summary.json included (with the error), as the log and trajectory are kept."""
    data = tmp_path / "tum"
    shutil.copytree(tum, data)
    depth = sorted((data / "depth").iterdir())
    depth[8].write_bytes(b"not a png")
    out = tmp_path / "run"
    assert main(["slam", str(data), "--out", str(out), "--quiet"]) == 2
    (line,) = _stderr_lines(capsys)
    assert line.startswith("ti-fusion slam: error: ") and depth[8].name in line
    summary = _summary(out)
    assert summary["command"] == "slam" and summary["frames"] == 8 and depth[8].name in summary["error"]
    assert {"trajectory.tum", "log.mcap", "map.ply", "summary.json"} <= {p.name for p in out.iterdir()}
