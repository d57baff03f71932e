"""--camera realsense (ti_fusion/io/datasets/realsense_live.py) without a camera: pyrealsense2's playback of
the shared D435 recording runs the same SDK calls as a device (skipped with the reason when the extra or
the recording is absent); the lines a user gets without the extra, without a camera, with a wrong kind."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.datasets.realsense_live import parse_camera

RECORDING = Path(__file__).resolve().parents[3] / "shared/data/realsense-d435-2frames/single_depth_color_640x480.bag"


def _pyrealsense2_missing() -> str | None:
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:
        return f"the realsense extra is not installed (pip install 'ti-fusion[realsense]'): {exc}"
    return None


needs_sdk = pytest.mark.skipif(_pyrealsense2_missing() is not None, reason=str(_pyrealsense2_missing()))
needs_recording = pytest.mark.skipif(not RECORDING.is_file(), reason=f"the shared recording is absent ({RECORDING})")


@needs_sdk
@needs_recording
def test_the_sdks_playback_gives_what_the_recording_reader_reads():
    """Depth units, both cameras and the extrinsics through pyrealsense2 equal the ROS 1 reader's; the
    frame is the recording's depth in metres with its registered-to-be colour camera attached."""
    camera = open_dataset(DatasetConfig(camera=f"realsense:{RECORDING}"))
    bag = open_dataset(DatasetConfig(path=str(RECORDING)))
    try:
        assert camera.format == "realsense" and camera.depth_scale == bag.depth_scale == 1000
        assert camera.intrinsics.as_tuple() == pytest.approx(bag.intrinsics.as_tuple(), abs=1e-3)
        np.testing.assert_allclose(camera.color_extrinsics, bag.color_extrinsics, atol=1e-6)
        assert camera.color_intrinsics.as_tuple() == pytest.approx(bag.color_intrinsics.as_tuple(), abs=1e-3)
        frame = camera[0]
        assert frame.depth.shape == (480, 640) and frame.color.shape == (480, 640, 3)
        assert frame.meta["color_camera"][0] == camera.color_intrinsics and frame.color_registered is False
        np.testing.assert_array_equal(frame.depth, bag[0].depth)  # the recording's first frame: none is lost
        assert camera.describe()["frames"] is None and camera.endless  # until Ctrl-C
    finally:
        camera.close()
        bag.close()
    counted = open_dataset(DatasetConfig(camera=f"realsense:{RECORDING}", stop=1))  # --frames 1: Ctrl-C stops it
    try:
        assert not counted.endless and counted.describe()["frames"] == 1
    finally:
        counted.close()


@needs_sdk
@needs_recording
def test_slam_on_the_camera_path_ends_with_the_recording(cpu, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["slam", "--camera", f"realsense:{RECORDING}", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"]["format"] == "realsense" and summary["frames"] == 2  # every frame of the recording
    assert summary["tracking_failures"] == 0 and (out / "trajectory.tum").is_file()
    err = capsys.readouterr()
    assert "frames until Ctrl-C at 640x480" in err.out + err.err


@needs_sdk
@needs_recording
def test_ctrl_c_on_the_camera_path_ends_the_stream_and_the_run_finishes(cpu, tmp_path, capsys, monkeypatch,
                                                                          terminal_ctrl_c):
    """Ctrl-C as the recording's first frame is registered: the stream ends after it, as a live camera's would,
    and the run writes its map, saved map and summary (exit 0), not only the trajectory (130)."""
    import signal

    from ti_fusion.cli.main import FINISHING
    from ti_fusion.slam.slam_step import SLAMStep

    original = SLAMStep.register_frame

    def register_frame(self, frame):
        result = original(self, frame)
        signal.raise_signal(signal.SIGINT)  # to this thread: handled before it returns
        return result

    monkeypatch.setattr(SLAMStep, "register_frame", register_frame)
    out = tmp_path / "run"
    assert main(["slam", "--camera", f"realsense:{RECORDING}", "--downsample", "2", "--out", str(out), "--quiet"]) == 0
    assert FINISHING in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"]["format"] == "realsense" and summary["frames"] == 1
    assert (out / "map.ply").is_file() and (out / "map" / "map.json").is_file() and (out / "trajectory.tum").is_file()


def test_without_the_extra_one_line_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as when it is not installed
    with pytest.raises(InputError, match=r"needs pyrealsense2, which is not installed: pip install "
                                         r"'ti-fusion\[realsense\]'"):
        open_dataset(DatasetConfig(camera="realsense"))


@needs_sdk
def test_without_a_camera_one_line_says_so():
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is attached")
    with pytest.raises(InputError, match="no RealSense camera is attached"):
        open_dataset(DatasetConfig(camera="realsense:123456"))


def test_camera_specs_and_what_is_refused(tmp_path):
    assert parse_camera("realsense") == (None, None) and parse_camera("realsense:0123") == ("0123", None)
    with pytest.raises(InputError, match="unknown camera kind 'kinect'"):
        parse_camera("kinect")
    with pytest.raises(InputError, match="does not exist"):
        parse_camera(f"realsense:{tmp_path / 'x.bag'}")
    with pytest.raises(InputError, match="give one source of frames"):
        open_dataset(DatasetConfig(camera="realsense", path=str(tmp_path)))
    assert main(["slam", "--camera", "kinect", "--out", str(tmp_path / "o"), "--quiet"]) == 2


def test_ci_installs_the_sdk_where_a_wheel_exists():
    """The SDK's tests ran nowhere: CI installed only the test extra. .ci/run asks for the realsense extra
    where pip finds a pyrealsense2 wheel (with libusb, which it links), and setup_env.sh installs the extras
    it is given."""
    from pathlib import Path

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    root = Path(__file__).resolve().parents[2]
    ci = (root / ".ci" / "run").read_text()
    assert "pip download" in ci and "'pyrealsense2>=2.54'" in ci and 'TI_FUSION_EXTRAS="test,realsense"' in ci
    assert "libusb-1.0-0" in ci
    assert ci.index("TI_FUSION_EXTRAS") < ci.index("scripts/test.sh")
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert "pyrealsense2>=2.54" in extras["realsense"]
    assert '-e ".[$EXTRAS]"' in (root / "scripts" / "setup_env.sh").read_text()
