"""Frames from one's own code: ``rgbd_frame`` checks and converts arrays; frame by frame through
``DenseSLAM`` and as a ``FrameList`` through the pipeline, the synthetic sequence tracks as the command
line's run of it does; the example script and the documented snippet run as written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import FrameList, open_dataset, rgbd_frame
from ti_fusion.io.trajectory import read_tum

DOCS = Path(__file__).resolve().parents[2] / "docs" / "DATA.md"
K = Intrinsics(fx=30.0, fy=30.0, cx=19.5, cy=14.5, width=40, height=30)


# --------------------------------------------------------------------------------------------------
# rgbd_frame (no Taichi)
# --------------------------------------------------------------------------------------------------
def test_millimetres_with_a_scale_and_metres_without():
    raw = np.full((30, 40), 1500, dtype=np.uint16)
    raw[0, 0] = 0
    raw[0, 1] = 5000  # beyond the default 4 m range cut
    frame = rgbd_frame(raw, K, depth_scale=1000, timestamp=12.5, index=3)
    assert frame.depth.dtype == np.float32 and frame.depth[1, 1] == pytest.approx(1.5)
    assert frame.depth[0, 0] == 0 and frame.depth[0, 1] == 0
    assert (frame.timestamp, frame.index, frame.color, frame.gt_pose) == (12.5, 3, None, None)
    metres = np.full((30, 40), 1.5)
    metres[0, :3] = [np.nan, np.inf, -1.0]
    frame = rgbd_frame(metres, K, depth_max=None)
    assert frame.depth[0, :3].tolist() == [0, 0, 0] and frame.depth[1, 1] == pytest.approx(1.5)
    assert frame.timestamp == 0.0  # the index when no time is given
    assert np.isnan(metres[0, 0])  # the caller's array is left as it was


def test_color_grey_is_made_rgb_and_the_pose_is_kept():
    grey = np.arange(1200, dtype=np.uint8).reshape(30, 40)
    frame = rgbd_frame(np.ones((30, 40)), K, color=grey, gt_pose=np.eye(4))
    assert frame.color.shape == (30, 40, 3) and (frame.color[..., 2] == grey).all()
    np.testing.assert_array_equal(frame.gt_pose, np.eye(4))


def test_color_is_registered_unless_said_and_a_frame_list_keeps_it():
    """rgbd_frame's colour is taken as registered to depth (tracking uses it, as the command line does for a
    registered camera) unless color_registered=False; a FrameList of such frames says the same."""
    rgb = np.zeros((30, 40, 3), np.uint8)
    registered = [rgbd_frame(np.ones((30, 40)), K, color=rgb, index=i) for i in range(2)]
    assert all(f.color_registered for f in registered) and not rgbd_frame(np.ones((30, 40)), K).color_registered
    assert FrameList(registered)[1].color_registered and FrameList(registered).describe()["color_for_tracking"]
    resized = [rgbd_frame(np.ones((30, 40)), K, color=rgb, index=i, color_registered=False) for i in range(2)]
    assert not resized[0].color_registered and not FrameList(resized)[0].color_registered


@pytest.mark.parametrize("kwargs, message", [
    (dict(depth=np.ones((30, 40), dtype=np.uint16)), "needs depth_scale"),
    (dict(depth=np.ones((40, 30))), "depth is 30x40, the intrinsics are for 40x30"),
    (dict(depth=np.ones((30, 40, 1))), "must be an H×W array"),
    (dict(depth=np.ones((30, 40)), depth_scale=0), "depth_scale 0: must be a positive"),
    (dict(depth=np.ones((30, 40)), color=np.ones((30, 40, 3))), "colour of type float64"),
    (dict(depth=np.ones((30, 40)), color=np.ones((15, 20, 3), dtype=np.uint8)), "expected 30×40×3 RGB"),
    (dict(depth=np.ones((30, 40)), gt_pose=np.ones((4, 4))), "gt_pose is not a rigid transform"),
])
def test_bad_arrays_are_one_line(kwargs, message):
    with pytest.raises(InputError, match=message) as info:
        rgbd_frame(intrinsics=K, **kwargs)
    assert "\n" not in str(info.value)


def test_a_frame_list_is_a_dataset_and_leaves_the_frames_alone():
    frames = [rgbd_frame(np.full((30, 40), 1.0 + i), K, timestamp=10.0 + i, index=i) for i in range(5)]
    ds = FrameList(frames, start=1, stride=2, downsample=2)
    assert len(ds) == 2 and ds[1].timestamp == 13.0 and ds[0].depth.shape == (15, 20)
    assert frames[1].depth.shape == (30, 40)  # downsampling made a new array
    assert ds.describe()["format"] == "arrays" and not ds.has_ground_truth
    other = Intrinsics(fx=31.0, fy=30.0, cx=19.5, cy=14.5, width=40, height=30)
    mixed = FrameList(frames[:1] + [rgbd_frame(np.ones((30, 40)), other, index=1)])
    with pytest.raises(InputError, match="one camera per FrameList"):
        mixed[1]
    with pytest.raises(InputError, match="no frames"):
        FrameList([])


# --------------------------------------------------------------------------------------------------
# Tracking from Python, as the command line tracks
# --------------------------------------------------------------------------------------------------
FRAMES = 12


def _config() -> Config:
    cfg = Config()
    cfg.synth.width, cfg.synth.height, cfg.synth.fx, cfg.synth.frames = 320, 240, 262.5, FRAMES
    cfg.log.progress = False
    return cfg


def _depth_only_frames(n: int):
    """(config, the synthetic sequence, its first ``n`` frames), tracked with depth only (colour's cost is
    not what the tests that use this measure)."""
    cfg = _config()
    cfg.icp.color_weight = 0.0
    synthetic = open_dataset(cfg.dataset, cfg.synth)
    return cfg, synthetic, [synthetic[i] for i in range(n)]


@pytest.mark.slow
def test_frame_by_frame_and_as_a_frame_list_give_the_command_lines_trajectory(cpu, tmp_path):
    from ti_fusion.backend import current_backend
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.dense import DenseSLAM
    from ti_fusion.slam.pipeline import SLAMPipeline

    cfg = _config()
    cfg.icp.color_weight = 0.0  # depth only: the test's cost (colour's use: test_color_is_registered_unless_said...)
    synthetic = open_dataset(cfg.dataset, cfg.synth)
    reference = SLAMPipeline(synthetic, cfg, RunDir("slam", tmp_path / "synthetic"), current_backend(),
                             show_progress=False).run()
    ref_stamps, ref_poses = read_tum(tmp_path / "synthetic" / "trajectory.tum")

    # One frame at a time, as a driver hands them over: the arrays only (with no range cut, as the
    # synthetic dataset has none: its renderer drops depth beyond synth.max_range itself).
    seq = synthetic.sequence
    slam = DenseSLAM(cfg, seq.intrinsics)
    frames, poses = [], []
    for i in range(FRAMES):
        depth, rgb = seq.frame(i)
        frame = rgbd_frame(depth, seq.intrinsics, color=rgb, timestamp=seq.timestamps[i], index=i,
                           gt_pose=seq.poses[i], depth_max=None)
        result = slam.register_frame(frame)
        assert result.tracked and result.timestamp == seq.timestamps[i]
        frames.append(frame)
        poses.append(result.pose)
    np.testing.assert_allclose(np.stack(poses), ref_poses, atol=1e-6)

    # The same frames as a FrameList: the pipeline's outputs and figures.
    summary = SLAMPipeline(FrameList(frames, name="my-robot"), cfg, RunDir("slam", tmp_path / "list"),
                           current_backend(), show_progress=False).run()
    for name in ("log.mcap", "trajectory.tum", "map.ply", "trajectory.png"):
        assert (tmp_path / "list" / name).is_file(), name
    stamps, list_poses = read_tum(tmp_path / "list" / "trajectory.tum")
    np.testing.assert_array_equal(stamps, ref_stamps)
    np.testing.assert_allclose(list_poses, ref_poses, atol=1e-6)
    assert summary["ate_rmse_m"] == pytest.approx(reference["ate_rmse_m"], abs=1e-6)
    assert summary["dataset"]["name"] == "my-robot"


@pytest.mark.slow
def test_the_example_script_runs(cpu, tmp_path, script, capsys):
    result = script("example_stream").main(["--frames", "10", "--out", str(tmp_path / "out")])
    assert result["frames"] == 10 and result["position_rms_m"] < 0.01
    for name in ("log.mcap", "map.ply", "trajectory.tum"):
        assert (tmp_path / "out" / name).is_file(), name
    assert "position error RMS" in capsys.readouterr().out


@pytest.mark.slow
def test_the_documented_snippet_runs_as_written(cpu, tmp_path, monkeypatch, capsys):
    """docs/DATA.md's "From Python" example, run as a user would paste it."""
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    assert blocks, "docs/DATA.md has no python example"
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], str(DOCS), "exec"), {"__name__": "__main__"})
    assert (tmp_path / "map.ply").is_file()
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) >= 10 and all(" ok " in line or " init " in line for line in lines)


@pytest.mark.slow
def test_a_second_slam_object_reuses_the_frame_maps_of_one_that_is_gone(cpu):
    """Taichi compiles a kernel per set of fields it is given: a DenseSLAM made after another is collected
    takes over its frame pyramids (kernels.surfels.Pool.lend), so it compiles nothing, and tracks the same;
    one made while another lives gets its own."""
    import gc
    import weakref

    from ti_fusion.slam.dense import DenseSLAM

    cfg, synthetic, frames = _depth_only_frames(3)
    slam = DenseSLAM(cfg, synthetic.intrinsics)
    first = [slam.register_frame(f).pose for f in frames]
    pyramids = weakref.ref(slam.frame_pyramid), weakref.ref(slam.model_pyramid)
    del slam
    gc.collect()
    slam = DenseSLAM(cfg, synthetic.intrinsics)
    assert slam.frame_pyramid is pyramids[0]() and slam.model_pyramid is pyramids[1]()
    other = DenseSLAM(cfg, synthetic.intrinsics)
    assert other.frame_pyramid is not slam.frame_pyramid and other.model_pyramid is not slam.model_pyramid
    np.testing.assert_array_equal(np.stack([slam.register_frame(f).pose for f in frames]), np.stack(first))


def test_maps_filled_in_the_scratch_pyramid_between_frames_change_no_pose(cpu):
    """Loop verification builds an earlier keyframe's maps in ``DenseSLAM.scratch_pyramid`` between frames,
    so that its ICP runs the kernels tracking compiled (no new instance of ICP's or the maps' kernels):
    whatever it leaves there, the next frames track as if it had not been there (each frame renders its
    model anew)."""
    import gc
    from types import SimpleNamespace

    from ti_fusion.kernels import pyramid as kmaps
    from ti_fusion.loop.verification import fill
    from ti_fusion.slam.dense import DenseSLAM

    cfg, synthetic, frames = _depth_only_frames(4)
    slam = DenseSLAM(cfg, synthetic.intrinsics)
    plain = [slam.register_frame(f).pose for f in frames]
    del slam
    gc.collect()
    slam = DenseSLAM(cfg, synthetic.intrinsics)  # the same maps (test above): nothing to compile
    poses = []
    for f in frames:
        poses.append(slam.register_frame(f).pose)
        level = slam.mapper.frame_level(slam.frame_pyramid)  # the keyframe's depth, as loop closure takes it
        depth, K = slam.frame_pyramid.depth[level].to_numpy(), slam.frame_pyramid.intrinsics[level]
        other = np.roll(depth, 17, axis=1) * np.float32(1.2)  # another view: shifted and further away
        fill(slam.scratch_pyramid(), SimpleNamespace(depth=other, depth_intrinsics=K))
        assert np.allclose(slam.scratch_pyramid().depth[0].to_numpy(), other)
        if len(poses) == 2:  # tracking has compiled its kernels: verification's ICP adds no instance
            kernels = (slam.icp._kernels(0).k["iterate"], kmaps.pyramid_down, kmaps.maps_levels)  # shared
            before = [len(k._primal.compiled_kernels) for k in kernels]
            slam.icp.align(slam.scratch_pyramid(), slam.frame_pyramid, init=np.eye(4))
            assert [len(k._primal.compiled_kernels) for k in kernels] == before
    np.testing.assert_array_equal(np.stack(poses), np.stack(plain))


def test_the_pipeline_snippet_uses_only_what_it_defines():
    """docs/DATA.md's SLAMPipeline snippet used an undefined ``backend``: every name it reads is imported or
    assigned in it, or is one of the snippet above it (``frames``, ``Config``)."""
    import ast

    blocks, current = [], None
    for line in DOCS.read_text().splitlines():
        if line.startswith("```"):
            blocks, current = (blocks + ["\n".join(current)], None) if current is not None else (blocks, [])
        elif current is not None:
            current.append(line)
    (block,) = [b for b in blocks if "SLAMPipeline(" in b]
    tree = ast.parse(block)
    defined = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
    defined |= {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign) for t in n.targets
                if isinstance(t, ast.Name)}
    read = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    assert read - defined <= {"frames", "Config"}, read - defined
