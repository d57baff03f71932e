"""End-to-end: the dense SLAM loop on a short synthetic sequence (CPU), its outputs and its log."""

import json

import numpy as np
import pytest

from ti_fusion.backend import current_backend
from ti_fusion.cli.main import main
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.mcap_log import read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.slam.pipeline import SLAMPipeline
from ti_fusion.io.trajectory import read_tum

FRAMES = 24


def _config(noise: bool = True) -> Config:
    cfg = Config()
    cfg.synth.noise = noise
    cfg.dataset.downsample = 2  # 320×240
    cfg.dataset.stop = FRAMES
    cfg.log.progress = False
    return cfg


@pytest.mark.slow
def test_slam_command_on_synthetic_default(cpu, tmp_path):
    out = tmp_path / "run"
    assert main(["slam", "--frames", str(FRAMES), "--downsample", "2", "--out", str(out), "--quiet"]) == 0
    for name in ("summary.json", "trajectory.tum", "log.mcap", "map.ply", "trajectory.png",
                 "map_color.png", "map_normals.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["command"] == "slam" and summary["frames"] == FRAMES
    assert summary["backend"] == "cpu"
    assert summary["tracking_failures"] == 0
    # Bound: 1% of the path length (the target for the default run), and 1 cm absolute.
    assert summary["ate_rmse_m"] < 0.01
    assert summary["ate_percent_of_path"] < 1.0
    stamps, poses = read_tum(out / "trajectory.tum")
    assert len(stamps) == FRAMES

    log = read_log(out / "log.mcap")
    assert log.complete
    for topic in ("/tf", "/camera/pose", "/gt/pose", "/slam/stats", "/map/points", "/camera/depth"):
        assert log.channels[topic].count > 0, topic
    assert len(log.stats) == FRAMES
    assert {"frame", "status", "surfels", "ms"} <= set(log.stats[-1])
    assert {"pyramid", "track", "fuse", "log", "load"} <= set(log.stats[-1]["ms"])
    # the time in kernels' first launches, by which the layout's ms plot leaves compiling frames out
    assert all(s["first_launch_ms"] >= 0 for s in log.stats) and log.stats[-1]["first_launch_ms"] == 0
    assert log.metadata_value("backend", "arch") == "cpu"
    # the map snapshot carries the surfels' colours (the textured room), not white
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from ti_fusion.io.mcap_log import points_from_msg

    with open(out / "log.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        clouds = [msg for _, _, _, msg in reader.iter_decoded_messages(topics=["/map/points"])]
    xyz, rgba = points_from_msg(clouds[-1])
    assert len(xyz) == summary["surfels"] or len(xyz) <= Config().log.map_max_points
    assert rgba[:, :3].std() > 10 and rgba[:, :3].mean() < 240


class BlankFrame:
    """A dataset wrapper whose frame ``blank`` has no valid depth (a sensor drop-out)."""

    def __init__(self, dataset, blank: int):
        self.dataset, self.blank = dataset, blank

    def __getattr__(self, name):
        return getattr(self.dataset, name)

    def __len__(self):
        return len(self.dataset)

    def __getitem__(self, i):
        frame = self.dataset[i]
        if i == self.blank:
            frame.depth = np.zeros_like(frame.depth)
        return frame


def test_stable_surfels_only_prediction_tracks_from_the_start(cpu, tmp_path):
    """fusion.render_min_weight > 0 (Keller's stable points): at first no surfel is confirmed, so the
    prediction uses every surfel until the map has had fusion.unstable_age frames (it used to lose every
    frame: an empty prediction, nothing fused, the map never grew)."""
    cfg = _config()
    cfg.dataset.stop = 16
    cfg.fusion.render_min_weight = 2.0
    cfg.fusion.unstable_age = 5
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, run, current_backend(),
                           show_progress=False).run()
    assert summary["tracking_failures"] == 0
    assert summary["ate_rmse_m"] < 0.01


def test_blank_depth_frame_is_a_logged_failure_and_the_run_completes(cpu, tmp_path):
    cfg = _config()
    cfg.dataset.stop = 16
    dataset = BlankFrame(open_dataset(cfg.dataset, cfg.synth), blank=8)
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False).run()
    assert summary["frames"] == 16
    assert summary["tracking_failures"] == 1
    assert summary["failed_frames"][0]["frame"] == 8
    assert summary["ate_rmse_m"] < 0.02  # tracking resumed on the motion model
    log = read_log(run.file("log.mcap"))
    failed = [s for s in log.stats if s["status"] != "ok"]
    assert [s["frame"] for s in failed] == [8]


def test_interrupted_run_leaves_log_and_trajectory(cpu, tmp_path):
    cfg = _config()
    cfg.dataset.stop = 10

    class Interrupt(BlankFrame):
        def __getitem__(self, i):
            if i == 6:
                raise KeyboardInterrupt
            return self.dataset[i]

    run = RunDir("slam", tmp_path / "run")
    with pytest.raises(KeyboardInterrupt):
        SLAMPipeline(Interrupt(open_dataset(cfg.dataset, cfg.synth), -1), cfg, run, current_backend(),
                     show_progress=False).run()
    stamps, _ = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 6
    log = read_log(run.file("log.mcap"))
    assert log.complete and len(log.stats) == 6


def test_bad_input_in_a_frame_keeps_the_frames_before(cpu, tmp_path):
    """An unreadable frame 5 ends the run with its one-line error; frames 0..4 leave trajectory.tum and a
    finalised log, as an interrupted run does."""
    cfg = _config()
    cfg.dataset.stop = 8

    class Unreadable(BlankFrame):
        def __getitem__(self, i):
            if i == 5:
                raise InputError("frame-000005.depth.png", "cannot read the image")
            return self.dataset[i]

    run = RunDir("slam", tmp_path / "run")
    with pytest.raises(InputError, match="cannot read"):
        SLAMPipeline(Unreadable(open_dataset(cfg.dataset, cfg.synth), -1), cfg, run, current_backend(),
                     show_progress=False).run()
    stamps, _ = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 5
    log = read_log(run.file("log.mcap"))
    assert log.complete and len(log.stats) == 5 and log.channels["/map/points"].count == 1


@pytest.mark.slow
def test_fuse_runs_in_the_same_pipeline(cpu, tmp_path):
    """fuse (at ground-truth poses) gets the pipeline's log and trajectory too, and stops at the first
    frame without a ground-truth pose, keeping the frames before it."""
    from ti_fusion.slam.fuse_step import FuseStep
    from ti_fusion.slam.pipeline import Pipeline

    cfg = _config()
    cfg.dataset.stop = 6

    class NoPose(BlankFrame):
        def __getitem__(self, i):
            frame = self.dataset[i]
            if i == 4:
                frame.gt_pose = None
            return frame

    dataset = NoPose(open_dataset(cfg.dataset, cfg.synth), -1)
    run = RunDir("fuse", tmp_path / "run")
    with pytest.raises(InputError, match="frame 4 has no ground-truth pose"):
        Pipeline(dataset, cfg, run, FuseStep(cfg, dataset), current_backend(), show_progress=False).run()
    stamps, poses = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 4
    np.testing.assert_allclose(poses[3], dataset[3].gt_pose, atol=1e-6)
    log = read_log(run.file("log.mcap"))
    assert log.complete and log.stats_topic == "/fuse/stats" and len(log.stats) == 4
    assert log.stats[-1]["surfels"] > 0 and {"pyramid", "fuse", "log", "load"} <= set(log.stats[-1]["ms"])


def _run_small(tmp_path, arch_name: str) -> dict:
    cfg = _config()
    cfg.dataset.downsample = 4  # 160×120: lavapipe is a software GPU
    cfg.dataset.stop = 12
    run = RunDir("slam", tmp_path / arch_name)
    from ti_fusion.backend import current_backend as backend_now

    return SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, run, backend_now(), show_progress=False).run()


def test_slam_on_vulkan_is_as_accurate_as_on_cpu(tmp_path):
    """The GPU code path end to end: the same short sequence on vulkan and cpu.

    Stated bound: the vulkan ATE is within 1.5× the cpu ATE plus 1 mm (float32 reductions on the GPU
    path against float64 on cpu), with no tracking failure on either.
    """
    from tests.conftest import _has_vulkan, _use

    if not _has_vulkan():
        pytest.skip("no Vulkan device (apt-get install mesa-vulkan-drivers for lavapipe)")
    _use("cpu")
    on_cpu = _run_small(tmp_path, "cpu")
    _use("vulkan")
    try:
        on_vulkan = _run_small(tmp_path, "vulkan")
    finally:
        _use("cpu")
    assert on_cpu["tracking_failures"] == 0 and on_vulkan["tracking_failures"] == 0
    assert on_vulkan["ate_rmse_m"] <= 1.5 * on_cpu["ate_rmse_m"] + 0.001, (on_vulkan["ate_rmse_m"], on_cpu["ate_rmse_m"])


class Jump(BlankFrame):
    """Frames 0..k-1, then a jump ahead by ``skip`` frames: too far for ICP from the motion model."""

    def __init__(self, dataset, at: int, skip: int, frames: int):
        super().__init__(dataset, blank=-1)
        self.at, self.skip, self.frames = at, skip, frames

    def __len__(self):
        return self.frames

    def __getitem__(self, i):
        return self.dataset[i if i < self.at else i + self.skip]


@pytest.mark.slow
def test_feature_relocalisation_after_a_jump(cpu, tmp_path):
    """A 20-frame gap (about 20 cm and 10 degrees) under a health check that allows at most 5 cm against
    the motion model: tracking from the motion model is refused, ORB + PnP against the last good frame
    re-initialises ICP, and the frame is tracked ("relocalised") instead of lost."""
    cfg = _config()
    cfg.dataset.stop = 40
    cfg.slam.max_update_m = 0.05
    dataset = Jump(open_dataset(cfg.dataset, cfg.synth), at=6, skip=20, frames=10)
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False).run()
    assert summary["relocalised"] >= 1, summary["failed_frames"]
    assert summary["tracking_failures"] == 0
    assert summary["ate_rmse_m"] < 0.01


@pytest.mark.slow
def test_map_at_half_resolution_tracks(cpu, tmp_path):
    """fusion.level = 1 (the default's choice for 640×480 input): the frame is averaged down to half its
    resolution, and the model is rendered and tracked there."""
    cfg = _config()
    cfg.fusion.level = 1
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, run, current_backend(),
                           show_progress=False).run()
    assert summary["tracking_failures"] == 0 and summary["ate_rmse_m"] < 0.01
    assert summary["resolution"] == {"map_level": 1, "map_size": [160, 120], "tracked_at": [160, 120],
                                     "depth_smooth_radius": 3}


class BlankFirst(BlankFrame):
    """The first ``blank`` frames have no valid depth; frame ``sparse`` (if any) only a 5×5 patch of it."""

    def __init__(self, dataset, blank: int, sparse: int = -1):
        super().__init__(dataset, blank=-1)
        self.first, self.sparse = blank, sparse

    def __getitem__(self, i):
        frame = self.dataset[i]
        if i < self.first:
            frame.depth = np.zeros_like(frame.depth)
        elif i == self.sparse:
            patch = frame.depth[50:55, 50:55].copy()
            frame.depth = np.zeros_like(frame.depth)
            frame.depth[50:55, 50:55] = patch
        return frame


@pytest.mark.slow
def test_the_map_starts_at_the_first_usable_frame(cpu, tmp_path):
    """Blank first frames (a sensor that starts dark) used to leave the map empty and lose every later
    frame; now they are skipped (no pose, status "skipped: ...") and the map starts at the first frame with
    depth enough for ICP to track the next one against."""
    cfg = _config()
    cfg.dataset.stop = 12
    dataset = BlankFirst(open_dataset(cfg.dataset, cfg.synth), blank=2, sparse=2)
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False).run()
    assert summary["map_started_at"] == 3
    assert [s["frame"] for s in summary["skipped_frames"]] == [0, 1, 2]
    assert summary["skipped_frames"][0]["reason"] == "no valid depth"
    assert summary["skipped_frames"][2]["reason"].startswith("25 pixels with depth, fewer than the 100")
    assert summary["tracking_failures"] == 0 and summary["surfels"] > 0
    assert summary["ate_rmse_m"] < 0.01 and summary["gt_frames"] == 9
    stamps, _ = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 9  # skipped frames have no pose
    log = read_log(run.file("log.mcap"))
    assert [s["status"] for s in log.stats[:4]] == ["skipped: no valid depth"] * 2 + [
        "skipped: " + summary["skipped_frames"][2]["reason"], "ok"]
    assert log.channels["/camera/pose"].count == 9


def test_a_sequence_without_usable_depth_is_an_error_naming_the_depth_settings(cpu, tmp_path):
    """Nothing mapped is not a result: the run ends with one InputError, and a finalised log."""
    cfg = _config()
    cfg.dataset.stop = 3
    run = RunDir("slam", tmp_path / "run")
    with pytest.raises(InputError, match=r"none of the 3 frames got a pose \(no valid depth\): nothing was mapped. "
                                         r"Check the depth's units and range: dataset.depth_max = 4 m"):
        SLAMPipeline(BlankFirst(open_dataset(cfg.dataset, cfg.synth), blank=3), cfg, run, current_backend(),
                     show_progress=False).run()
    assert not run.file("trajectory.tum").exists() and read_log(run.file("log.mcap")).complete


class SomeWithoutGroundTruth(BlankFrame):
    def __getitem__(self, i):
        frame = self.dataset[i]
        if 3 <= i < 7:
            frame.gt_pose = None
        return frame


def test_ate_over_the_frames_with_ground_truth_says_how_many(cpu, tmp_path):
    cfg = _config()
    cfg.dataset.stop = 12
    run = RunDir("slam", tmp_path / "run")
    summary = SLAMPipeline(SomeWithoutGroundTruth(open_dataset(cfg.dataset, cfg.synth), -1), cfg, run,
                           current_backend(), show_progress=False).run()
    assert summary["gt_frames"] == 8 and summary["pairs"] == 8 and summary["ate_rmse_m"] < 0.01
    assert summary["gt_note"] == "ATE and RPE are over the 8 of 12 posed frames that have ground truth"


def test_a_failed_health_check_shows_the_value_on_its_side_of_the_limit():
    """'inlier ratio 0.15 < 0.15' said nothing: the value gets the digits that show it is below."""
    from types import SimpleNamespace

    from ti_fusion.slam.dense import DenseSLAM
    from ti_fusion.tracking.icp import ICPResult

    fake = SimpleNamespace(config=Config())
    icp = ICPResult(pose=np.eye(4), inlier_ratio=0.14996, residual_rms=0.001)
    assert DenseSLAM._health(fake, icp, np.eye(4), np.eye(4)) == "inlier ratio 0.14996 < 0.15"
    icp = ICPResult(pose=np.eye(4), inlier_ratio=0.5, residual_rms=0.02004)
    assert DenseSLAM._health(fake, icp, np.eye(4), np.eye(4)) == "residual 20.04 mm > 20 mm"
    jump = np.eye(4)
    jump[0, 3] = 0.30004
    icp = ICPResult(pose=np.eye(4), inlier_ratio=0.5, residual_rms=0.001)
    assert DenseSLAM._health(fake, icp, jump, np.eye(4)) == \
        "jump of 0.0 deg / 30.004 cm from its start (at most 20 deg / 30 cm)"
