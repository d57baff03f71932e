"""A plain RGB-D folder (``--format folder``): the synthetic sequence written as one tracks as its TUM-format
copy does; what the user must state is asked for in one line; calibration files of every kind."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.config import Config, DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import detect, open_dataset
from ti_fusion.io.datasets.folder import FolderDataset
from ti_fusion.io.datasets.imageio import parse_intrinsics, read_intrinsics_file
from ti_fusion.io.trajectory import read_tum

FRAMES = 20
K = (262.5, 262.5, 159.5, 119.5)  # the synthetic camera at 320×240
W, H = 40, 30                     # the small hand-made folders


# --------------------------------------------------------------------------------------------------
# The synthetic sequence in TUM format, and as plain folders
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory):
    """``ti-fusion synth``'s TUM folder of FRAMES frames at 320×240."""
    from ti_fusion.backend import init_backend
    from ti_fusion.cli.synth import write_tum_sequence
    from ti_fusion.synthetic.scene import SyntheticSequence

    init_backend("cpu")
    root = tmp_path_factory.mktemp("synthetic") / "tum"
    write_tum_sequence(SyntheticSequence(SynthConfig(frames=FRAMES, width=320, height=240, fx=K[0])), root)
    return root


def associations(tum: Path) -> list[tuple[str, str, str]]:
    """(timestamp text, rgb file, depth file) of each frame of a TUM folder written by ``synth``."""
    return [(t, rgb, depth) for t, rgb, _, depth in (line.split() for line in
                                                     (tum / "associations.txt").read_text().splitlines())]


def tum_to_folder(tum: Path, root: Path, millimetres: bool) -> Path:
    """The TUM sequence as a plain folder. ``millimetres``: depth re-quantised to 1 mm (as a RealSense writes
    it), plain frame numbers, colour in color/, no timestamps.txt, ground truth by frame number in poses.tum,
    a camera_info YAML as camera.yaml. Otherwise: the TUM PNGs as they are (5000 units per metre), zero-padded
    names, rgb/, timestamps.txt and groundtruth.txt."""
    frames = associations(tum)
    (root / "depth").mkdir(parents=True)
    color = root / ("color" if millimetres else "rgb")
    color.mkdir()
    for i, (_, rgb, depth) in enumerate(frames):
        name = f"{i}.png" if millimetres else f"{i:06d}.png"
        if millimetres:
            raw = cv2.imread(str(tum / depth), cv2.IMREAD_UNCHANGED)
            assert cv2.imwrite(str(root / "depth" / name), np.round(raw / 5.0).astype(np.uint16))
        else:
            shutil.copy(tum / depth, root / "depth" / name)
        shutil.copy(tum / rgb, color / name)
    gt = [line.split() for line in (tum / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]
    if millimetres:
        (root / "poses.tum").write_text("".join(f"{i} {' '.join(g[1:])}\n" for i, g in enumerate(gt)))
        (root / "camera.yaml").write_text(camera_info_yaml(*K, 320, 240))
    else:
        (root / "timestamps.txt").write_text("".join(f"{t}\n" for t, _, _ in frames))
        shutil.copy(tum / "groundtruth.txt", root / "groundtruth.txt")
    return root


def camera_info_yaml(fx, fy, cx, cy, width, height) -> str:
    """A camera_info YAML as camera_calibration_parsers writes it."""
    return (f"image_width: {width}\nimage_height: {height}\ncamera_name: depth\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
            f"  data: [{fx}, 0, {cx}, 0, {fy}, {cy}, 0, 0, 1]\ndistortion_model: plumb_bob\n"
            "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n")


def slam(dataset_cfg: DatasetConfig, out: Path) -> dict:
    from ti_fusion.backend import current_backend
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    cfg = Config()
    cfg.dataset = dataset_cfg
    cfg.log.progress = False
    summary = SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, RunDir("slam", out), current_backend(),
                           show_progress=False).run()
    summary["trajectory"] = read_tum(out / "trajectory.tum")
    return summary


@pytest.fixture(scope="module")
def tum_run(tum_sequence, tmp_path_factory):
    return slam(DatasetConfig(path=str(tum_sequence)), tmp_path_factory.mktemp("runs") / "tum")


@pytest.mark.slow
def test_the_tum_pngs_as_a_plain_folder_give_the_same_trajectory(cpu, tum_sequence, tum_run, tmp_path):
    root = tum_to_folder(tum_sequence, tmp_path / "plain", millimetres=False)
    cfg = DatasetConfig(path=str(root), format="folder", depth_scale=5000, intrinsics=",".join(map(str, K)),
                        color_registered=True)  # as TUM's are: colour tracking (the default) on in both runs
    run = slam(cfg, tmp_path / "run")
    d = run["dataset"]
    assert d["format"] == "folder" and d["frames"] == FRAMES and d["color_registered"] is True
    assert d["timestamps_from"] == "timestamps.txt" and d["ground_truth_from"] == "groundtruth.txt in the dataset folder"
    stamps, poses = run["trajectory"]
    tum_stamps, tum_poses = tum_run["trajectory"]
    np.testing.assert_array_equal(stamps, tum_stamps)
    np.testing.assert_allclose(poses, tum_poses, atol=1e-6)
    assert run["ate_rmse_m"] == pytest.approx(tum_run["ate_rmse_m"], abs=1e-6)


@pytest.mark.slow
def test_three_reader_processes_give_the_same_run(cpu, tum_sequence, tum_run, tmp_path):
    """Image files read by three processes at once (``dataset.read_workers``): the frames come in order, so
    the trajectory is the default run's, bit for bit."""
    three = slam(DatasetConfig(path=str(tum_sequence), read_workers=3), tmp_path / "three")
    assert (three["read_mode"], three["read_workers"]) == ("processes", 3) and three["frames"] == FRAMES
    assert tum_run["read_mode"] == "processes"
    np.testing.assert_array_equal(three["trajectory"][1], tum_run["trajectory"][1])


def test_opencv_log_level_comes_back_after_overlapping_readers():
    """Readers on several threads silence OpenCV's log, a process-wide level, around each decode: the
    level before the first one is the level after the last one, however their spans overlap."""
    import threading

    from ti_fusion.io.datasets.imageio import _opencv_silenced

    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        pytest.skip("this OpenCV build has no cv2.utils.logging")
    before = logging.getLogLevel()
    inside, leave = threading.Barrier(2), threading.Event()

    def reader(wait: bool):
        with _opencv_silenced():
            inside.wait(timeout=60)
            assert logging.getLogLevel() == logging.LOG_LEVEL_SILENT
            if wait:
                leave.wait(timeout=60)  # the other leaves first: the level must stay silent for this one

    a = threading.Thread(target=reader, args=(True,))
    a.start()
    reader(False)  # leaves first
    assert logging.getLogLevel() == logging.LOG_LEVEL_SILENT
    leave.set()
    a.join()
    assert logging.getLogLevel() == before


@pytest.mark.slow
def test_millimetre_folder_from_the_command_line_tracks_as_well(cpu, tum_sequence, tum_run, tmp_path):
    """RealSense-like: millimetres, plain numbers, color/, camera.yaml, ground truth by frame number."""
    root = tum_to_folder(tum_sequence, tmp_path / "realsense", millimetres=True)
    out = tmp_path / "run"
    assert main(["slam", str(root), "--format", "folder", "--depth-scale", "1000", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    d = summary["dataset"]
    assert d["depth_scale"] == 1000 and d["intrinsics"]["source"] == "camera.yaml in the dataset folder"
    assert d["timestamps_from"].startswith("the frame numbers") and d["ground_truth_frames"] == FRAMES
    assert summary["tracking_failures"] == 0
    # 1 mm steps instead of 0.2 mm: the same accuracy within a millimetre, and both well under 1 cm.
    assert summary["ate_rmse_m"] < 0.01 and abs(summary["ate_rmse_m"] - tum_run["ate_rmse_m"]) < 1e-3
    stamps, _ = read_tum(out / "trajectory.tum")
    np.testing.assert_array_equal(stamps, np.arange(FRAMES))


# --------------------------------------------------------------------------------------------------
# Small hand-made folders: layout, options, refusals (no Taichi)
# --------------------------------------------------------------------------------------------------
def make_folder(root: Path, rng, names=("0", "1", "2"), color: str | None = "rgb", color_size=(W, H)) -> Path:
    (root / "depth").mkdir(parents=True)
    for name in names:
        raw = (rng.uniform(0.5, 3.0, (H, W)) * 1000).astype(np.uint16)
        assert cv2.imwrite(str(root / "depth" / f"{name}.png"), raw)
        if color:
            (root / color).mkdir(exist_ok=True)
            image = rng.integers(0, 256, (color_size[1], color_size[0], 3), dtype=np.uint8)
            assert cv2.imwrite(str(root / color / f"{name}.png"), image)
    return root


def folder_cfg(root: Path, **kw) -> DatasetConfig:
    kw.setdefault("depth_scale", 1000.0)
    kw.setdefault("intrinsics", "30,30,19.5,14.5")
    return DatasetConfig(path=str(root), format="folder", **kw)


def test_without_depth_scale_and_intrinsics_one_line_names_both(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng)
    with pytest.raises(InputError) as info:
        open_dataset(DatasetConfig(path=str(root), format="folder"))
    message = str(info.value)
    assert "\n" not in message and "--depth-scale UNITS_PER_METRE" in message and "--intrinsics fx,fy,cx,cy" in message
    with pytest.raises(InputError, match="--depth-scale") as info:
        open_dataset(DatasetConfig(path=str(root), format="folder", intrinsics="30,30,19.5,14.5"))
    assert "--intrinsics" not in str(info.value)
    with pytest.raises(InputError, match="--intrinsics fx,fy,cx,cy") as info:
        open_dataset(DatasetConfig(path=str(root), format="folder", depth_scale=1000))
    assert "--depth-scale" not in str(info.value)


def test_the_cli_refuses_a_folder_without_format_naming_the_options(tmp_path, rng, capsys):
    root = make_folder(tmp_path / "cam", rng)
    with pytest.raises(InputError) as info:
        detect(root)
    assert "--format folder --depth-scale UNITS_PER_METRE --intrinsics fx,fy,cx,cy" in str(info.value)
    assert main(["slam", str(root), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--format folder --depth-scale" in err
    assert main(["slam", str(root), "--format", "folder", "--out", str(tmp_path / "out2"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--depth-scale" in err and "--intrinsics" in err
    assert main(["slam", str(root), "--format", "folder", "--depth-scale", "0", "--quiet"]) == 2
    assert "--depth-scale 0: must be a positive" in capsys.readouterr().err


def test_frames_in_numeric_order_with_depth_in_metres(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng, names=("frame_10", "frame_2", "frame_1"))
    ds = open_dataset(folder_cfg(root))
    assert isinstance(ds, FolderDataset) and len(ds) == 3
    assert [Path(ds[i].meta["depth_file"]).name for i in range(3)] == ["frame_1.png", "frame_2.png", "frame_10.png"]
    assert [ds[i].timestamp for i in range(3)] == [1.0, 2.0, 10.0]
    raw = cv2.imread(str(root / "depth" / "frame_2.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(ds[1].depth, np.where(raw / 1000.0 > 4.0, 0.0, raw / 1000.0), rtol=1e-6)
    assert ds[1].color.shape == (H, W, 3) and ds.describe()["color_registered"] is True


def test_two_files_of_one_number_are_refused(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng, names=("001", "1"))
    with pytest.raises(InputError, match="001.png and 1.png both have frame number 1"):
        open_dataset(folder_cfg(root))


def test_color_of_another_size_is_not_registered_and_said(tmp_path, rng, caplog):
    root = make_folder(tmp_path / "cam", rng, color="color", color_size=(64, 48))
    ds = open_dataset(folder_cfg(root))
    assert ds[0].color.shape == (H, W, 3)
    d = ds.describe()
    assert d["color_registered"] is False and any("not registered" in n for n in d["notes"])
    assert "not registered" in caplog.text


def test_a_missing_color_image_is_refused(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng)
    (root / "rgb" / "1.png").unlink()
    with pytest.raises(InputError, match="colour image of depth/1.png does not exist"):
        open_dataset(folder_cfg(root))


def test_depth_only_folder(tmp_path, rng):
    ds = open_dataset(folder_cfg(make_folder(tmp_path / "cam", rng, color=None)))
    assert ds[0].color is None and ds.describe()["color_registered"] is None


def test_timestamps_one_per_line_or_by_frame_number(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng, names=("0", "1", "2"))
    (root / "timestamps.txt").write_text("100.0\n100.5\n101.0\n")
    assert [f.timestamp for f in open_dataset(folder_cfg(root))] == [100.0, 100.5, 101.0]
    (root / "timestamps.txt").write_text("# frame time\n2 7.0\n0 5.0\n1 6.0\n")
    assert [f.timestamp for f in open_dataset(folder_cfg(root))] == [5.0, 6.0, 7.0]


@pytest.mark.parametrize("text, message", [
    ("1.0\n2.0\n", "2 timestamps for 3 depth images"),
    ("1.0\n3.0\n2.0\n", "line 3: time 2.000000 of frame 2 is not after 3.000000"),
    ("0 1.0\n1 2.0\n", "no time for frame 2"),
    ("1.0 2.0 3.0\n", "expected one time per line"),
    ("1.0\nabc\n2.0\n", "line 2: expected numbers"),
])
def test_bad_timestamps_are_one_line_naming_the_file(tmp_path, rng, text, message):
    root = make_folder(tmp_path / "cam", rng)
    (root / "timestamps.txt").write_text(text)
    with pytest.raises(InputError, match=message) as info:
        open_dataset(folder_cfg(root))
    assert str(info.value).startswith(str(root / "timestamps.txt"))


def test_ground_truth_by_frame_number_or_by_timestamp(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng, names=("0", "1", "2"))
    (root / "groundtruth.txt").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    ds = open_dataset(folder_cfg(root))
    assert ds[1].gt_pose[0, 3] == 1.0 and ds[2].gt_pose is None
    assert ds.describe()["ground_truth_frames"] == 2
    (root / "timestamps.txt").write_text("10.0\n10.1\n10.2\n")
    with pytest.raises(InputError, match="no pose within 0.02 s of any frame's time"):
        open_dataset(folder_cfg(root))
    (root / "groundtruth.txt").write_text("10.0 0 0 0 0 0 0 1\n10.2 2 0 0 0 0 0 1\n")
    ds = open_dataset(folder_cfg(root, max_time_difference=0.15))
    assert ds[1].gt_pose[0, 3] == pytest.approx(1.0)  # interpolated between the two samples
    (root / "poses.tum").write_text("10.0 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="keep one ground truth"):
        open_dataset(folder_cfg(root))
    ds = open_dataset(folder_cfg(root, ground_truth=str(root / "poses.tum")))  # named: no ambiguity
    assert ds.describe()["ground_truth_frames"] == 1


def test_intrinsics_from_the_folder_are_used_and_named(tmp_path, rng):
    root = make_folder(tmp_path / "cam", rng)
    (root / "intrinsics.txt").write_text("31 32 19 14\n")
    ds = open_dataset(folder_cfg(root, intrinsics=""))
    assert ds.intrinsics.as_tuple() == (31.0, 32.0, 19.0, 14.0)
    assert ds.describe()["intrinsics"]["source"] == "intrinsics.txt in the dataset folder"
    assert "intrinsics.txt in the dataset folder" in ds.describe_format()
    (root / "camera.yaml").write_text(camera_info_yaml(33, 34, 20, 15, W, H))
    ds = open_dataset(folder_cfg(root, intrinsics=""))
    assert ds.intrinsics.as_tuple() == (33.0, 34.0, 20.0, 15.0)
    assert ds.describe()["intrinsics"]["source"] == "camera.yaml in the dataset folder"
    ds = open_dataset(folder_cfg(root, intrinsics=[35, 36, 21, 16]))  # a list, as a TOML config gives it
    assert ds.intrinsics.as_tuple() == (35.0, 36.0, 21.0, 16.0)


# --------------------------------------------------------------------------------------------------
# Calibration files (imageio.read_intrinsics_file / parse_intrinsics)
# --------------------------------------------------------------------------------------------------
OPENCV_YAML = """%YAML:1.0
---
image_width: 40
image_height: 30
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 30.5, 0., 19.5, 0., 31.5, 14.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ 0., 0., 0., 0., 0. ]
"""


@pytest.mark.parametrize("name, text, expected", [
    ("k.txt", "30.5 0 19.5\n0 31.5 14.5\n0 0 1\n", (30.5, 31.5, 19.5, 14.5)),
    ("plain.txt", "30.5 31.5 19.5 14.5\n", (30.5, 31.5, 19.5, 14.5)),
    ("camera_info.yaml", "header:\n  frame_id: cam\nheight: 30\nwidth: 40\ndistortion_model: plumb_bob\n"
                         "d: [0.0, 0.0, 0.0, 0.0, 0.0]\nk: [30.5, 0.0, 19.5, 0.0, 31.5, 14.5, 0.0, 0.0, 1.0]\n",
     (30.5, 31.5, 19.5, 14.5)),
    ("ros1.yml", "K: [30.5, 0.0, 19.5, 0.0, 31.5, 14.5, 0.0, 0.0, 1.0]\n", (30.5, 31.5, 19.5, 14.5)),
    ("calibration.yaml", camera_info_yaml(30.5, 31.5, 19.5, 14.5, W, H), (30.5, 31.5, 19.5, 14.5)),
    ("opencv.yaml", OPENCV_YAML, (30.5, 31.5, 19.5, 14.5)),
])
def test_calibration_files(tmp_path, name, text, expected):
    path = tmp_path / name
    path.write_text(text)
    K_ = read_intrinsics_file(path, W, H)
    assert K_.as_tuple() == expected and (K_.width, K_.height) == (W, H)
    assert parse_intrinsics(str(path), W, H).as_tuple() == expected


@pytest.mark.parametrize("name, text, message", [
    ("big.yaml", camera_info_yaml(30, 30, 19.5, 14.5, 640, 480), "calibration is for 640x480 images, the depth "
                                                                   "images are 40x30"),
    ("none.yaml", "camera_name: x\n", "no camera_matrix, k or fx/fy/cx/cy"),
    ("bad.yaml", "k: [1, 2\n", "cannot parse YAML"),
    ("short.yaml", "k: [30, 0, 19.5]\n", "expected 4 numbers"),
    ("negative.txt", "-30 30 19.5 14.5\n", "focal lengths must be positive"),
])
def test_bad_calibration_files_are_one_line(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError, match=message) as info:
        read_intrinsics_file(path, W, H)
    assert "\n" not in str(info.value)


def test_intrinsics_option_numbers_or_file(tmp_path):
    assert parse_intrinsics("525,525,319.5,239.5", 640, 480).as_tuple() == (525.0, 525.0, 319.5, 239.5)
    assert parse_intrinsics("525 525 319.5 239.5", 640, 480).fx == 525.0
    with pytest.raises(InputError, match="--intrinsics 525,525: neither four numbers fx,fy,cx,cy nor an existing file"):
        parse_intrinsics("525,525", 640, 480)
    with pytest.raises(InputError, match="focal lengths must be positive"):
        parse_intrinsics("0,525,319.5,239.5", 640, 480)


def test_intrinsics_option_replaces_a_benchmark_formats_own(tmp_path, rng):
    """--intrinsics also applies to TUM, ICL-NUIM and 7-Scenes folders; with dataset.intrinsics_file it is
    refused (two answers to one question)."""
    root = make_folder(tmp_path / "icl", rng)
    ds = open_dataset(DatasetConfig(path=str(root), format="iclnuim", intrinsics="30,31,19,14"))
    assert ds.intrinsics.as_tuple() == (30.0, 31.0, 19.0, 14.0)
    assert ds.describe()["intrinsics"]["source"] == "30,31,19,14 (--intrinsics / dataset.intrinsics)"
    (tmp_path / "k.txt").write_text("30 31 19 14\n")
    with pytest.raises(InputError, match="keep one"):
        open_dataset(DatasetConfig(path=str(root), format="iclnuim", intrinsics="30,31,19,14",
                                   intrinsics_file=str(tmp_path / "k.txt")))
