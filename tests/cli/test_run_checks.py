"""What a user meets at the command line when a run must show whether it can be trusted: config values
against their rules, the first usable frame, a partial ground truth, a stop during a log write, and the
smaller messages (one-frame runs, threshold comparisons, output files that cannot be written, frame numbers
of the synthetic sequence, one dataset line)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.io.mcap_log import RunLogger, read_log
from ti_fusion.io.trajectory import read_tum


def _stderr_lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.strip()]


# --------------------------------------------------------------------------------------------------
# Config values against their rules
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("setting, line", [
    ("icp.dist_threshold=-0.1", "--set: icp.dist_threshold = -0.1: must be a number > 0"),
    ("slam.relocalise=featurs", "--set: slam.relocalise = 'featurs': must be one of features, none"),
    ("icp.iterations=5", "--set: icp.iterations = 5: must be a list of integers >= 0 (at least 1)"),
])
def test_a_config_value_against_its_rule_stops_the_run_with_one_line(tmp_path, capsys, setting, line):
    out = tmp_path / "run"
    assert main(["slam", "--set", setting, "--out", str(out), "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion slam: error: {line}"]
    assert not out.exists()  # refused before anything was written


def test_a_config_file_value_against_its_rule_names_the_file(tmp_path, capsys):
    config = tmp_path / "run.yaml"
    config.write_text("icp:\n  depth_weighting: maybe\n")
    assert main(["vo", "--config", str(config), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion vo: error: {config}: icp.depth_weighting = 'maybe': must be true "
                                     "or false"]


# --------------------------------------------------------------------------------------------------
# A stop during a log write waits for the write to end
# --------------------------------------------------------------------------------------------------
@pytest.fixture
def signal_in_chunk_write(monkeypatch):
    """``arm(signum, after)``: the ``after``-th chunk the MCAP writer compresses raises ``signum`` in this
    thread (its handler runs before ``raise_signal`` returns): a stop in the middle of a chunk write,
    after the chunk was taken from the writer's buffer and before it reached the file."""
    import mcap.writer

    compress = mcap.writer.zstandard.compress
    state = {"signum": None, "after": 0, "chunks": 0}

    def compress_and_signal(data, *args, **kwargs):
        state["chunks"] += 1
        if state["signum"] is not None and state["chunks"] == state["after"]:
            signal.raise_signal(state["signum"])
        return compress(data, *args, **kwargs)

    monkeypatch.setattr(mcap.writer.zstandard, "compress", compress_and_signal)

    def arm(signum: int, after: int = 1):
        state.update(signum=signum, after=after)

    # Ctrl-C enabled, as in a terminal, whatever handler an earlier test in this worker left: the run takes
    # Ctrl-C over only from Python's default handler (an ignored Ctrl-C stays ignored), and then the SIGINT
    # case failed now and then, by the order xdist gave the tests
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield arm
    if previous is not None:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_in_the_middle_of_a_log_write_keeps_every_message(tmp_path, signal_in_chunk_write, signum):
    from ti_fusion.cli.main import _stop_signals_raise

    signal_in_chunk_write(signum, after=2)
    path = tmp_path / "log.mcap"
    written = 0
    with _stop_signals_raise():
        with pytest.raises(KeyboardInterrupt):  # Stopped (SIGTERM) is a KeyboardInterrupt too
            with RunLogger(path, chunk_size=512) as log:
                for i in range(1000):
                    log.log_stats(0.1 * i, {"frame": i, "padding": "x" * 64})
                    written += 1
    log = read_log(path)
    # the chunk the stop arrived in (on the log's writer thread) was written whole; the stop reached the loop
    # after a call returned or at the end of one, once its message was queued: every message is in the log
    frames = [s["frame"] for s in log.stats]
    assert log.complete and frames == list(range(len(frames))) and written <= len(frames) <= written + 1


def test_sigterm_during_a_run_keeps_the_log_whole(cpu, tmp_path, capsys, signal_in_chunk_write):
    """The race behind the occasional failure of tests/cli/test_main.py::test_sigterm_from_outside_the_process: a
    SIGTERM while the log writer finished a chunk lost that chunk's messages."""
    signal_in_chunk_write(signal.SIGTERM, after=4)
    out = tmp_path / "run"
    assert main(["vo", "--frames", "40", "--downsample", "4", "--set", "log.map_every=1", "--out", str(out),
                 "--quiet"]) == 128 + signal.SIGTERM
    assert _stderr_lines(capsys) == [f"ti-fusion vo: stopped by SIGTERM; what was written is in {out}/"]
    stamps, _ = read_tum(out / "trajectory.tum")
    log = read_log(out / "log.mcap")
    # (the stop reaches the loop's thread between any two of its lines: after a frame's stats were logged and
    # before its result was kept, the log has one frame more than the trajectory)
    assert log.complete and len(stamps) >= 1 and len(stamps) <= len(log.stats) <= len(stamps) + 1
    assert log.channels["/camera/pose"].count >= len(stamps)


# --------------------------------------------------------------------------------------------------
# A sequence on disk whose first frames have no depth, or whose ground truth has a gap
# --------------------------------------------------------------------------------------------------
@pytest.fixture
def sequence(cpu, tmp_path, capsys):
    """``sequence(name)``: the synthetic sequence at 160x120, 12 frames, written in TUM format."""
    def make(name: str) -> Path:
        seq = tmp_path / name
        assert main(["synth", str(seq), "--frames", "12", "--width", "160", "--quiet"]) == 0
        capsys.readouterr()
        return seq

    return make


@pytest.mark.slow
def test_blank_first_frames_are_skipped_and_the_map_starts_after_them(sequence, tmp_path, capsys):
    import cv2

    seq = sequence("blank")
    depth_files = sorted((seq / "depth").glob("*.png"))
    for path in depth_files[:2]:
        cv2.imwrite(str(path), np.zeros((120, 160), np.uint16))
    out = tmp_path / "run"
    assert main(["slam", str(seq), "--out", str(out), "--quiet"]) == 0
    assert _stderr_lines(capsys) == ["ti-fusion slam: warning: the first 2 frames (0 to 1) were skipped (no valid "
                                     "depth): the map starts at frame 2"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["map_started_at"] == 2 and summary["tracking_failures"] == 0
    assert summary["skipped_frames"] == [{"frame": 0, "reason": "no valid depth"},
                                         {"frame": 1, "reason": "no valid depth"}]
    assert summary["ate_rmse_m"] < 0.01 and summary["gt_frames"] == 10
    assert len(read_tum(out / "trajectory.tum")[0]) == 10
    assert (out / "map_color.png").is_file()
    # inspect counts what summary.json counts: skipped frames are not tracking failures
    assert main(["inspect", str(out / "log.mcap"), "--out", str(tmp_path / "inspect"), "--quiet"]) == 0
    assert json.loads((tmp_path / "inspect" / "summary.json").read_text())["tracking_failures"] == 0


def test_ate_over_part_of_the_frames_says_how_many(sequence, tmp_path, capsys):
    seq = sequence("partial")
    gt = seq / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:3 + 4] + lines[3 + 8:]) + "\n")  # frames 4..7 lose their ground truth
    out = tmp_path / "run"
    assert main(["vo", str(seq), "--out", str(out), "--quiet"]) == 0
    assert _stderr_lines(capsys) == ["ti-fusion vo: warning: ATE and RPE are over the 8 of 12 posed frames that "
                                     "have ground truth"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["gt_frames"] == 8 and summary["pairs"] == 8 and "ate_rmse_m" in summary


# --------------------------------------------------------------------------------------------------
# The smaller messages
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_one_frame_run_says_why_it_has_no_frame_rate(cpu, tmp_path, capsys):
    assert main(["slam", "--frames", "1", "--downsample", "4", "--out", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "None" not in out
    assert "the synthetic sequence: 1 frames at 160x120" in out.splitlines()  # one dataset line, no format repeated
    assert "(every frame was warm-up)" in out


@pytest.mark.slow
def test_a_tracking_size_too_small_for_icps_pyramid_is_a_warning(cpu, tmp_path, capsys):
    assert main(["slam", "--frames", "1", "--downsample", "7", "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert _stderr_lines(capsys) == [
        "ti-fusion slam: warning: tracking at 92x69 leaves ICP's coarsest level (3 levels in icp.iterations) 23x18 = "
        "414 pixels, too few for icp.min_inliers = 100 correspondences (at this size a fifth to a third of the "
        "pixels find one): expect lost frames. Use a smaller --downsample, fewer levels in icp.iterations or a "
        "lower icp.min_inliers"]
    assert main(["slam", "--frames", "1", "--downsample", "4", "--out", str(tmp_path / "fine"), "--quiet"]) == 0
    assert _stderr_lines(capsys) == []


@pytest.mark.parametrize("option", ["--source", "--target"])
def test_icp_frame_out_of_the_synthetic_sequence_names_the_option_not_a_folder(cpu, tmp_path, capsys, option):
    assert main(["icp", option, "-1", "--downsample", "4", "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion icp: error: {option} -1: the synthetic sequence has frames 0 to 119"]


@pytest.fixture
def disk_full_for(monkeypatch):
    """``disk_full_for("matches.png")``: writing that output fails as on a full disk (at the rename of its
    temporary file, after the writer wrote it). The disk is full in this process only, so trajectory.png is
    drawn here too rather than in the plot's process (which, on a disk really full, fails and leaves it here)."""
    import errno

    from ti_fusion.evaluation.plot_process import PlotProcess

    monkeypatch.setattr(PlotProcess, "start", classmethod(lambda cls: None))
    real_replace = os.replace

    def arm(name: str):
        def replace(src, dst, *args, **kwargs):
            if Path(dst).name == name:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real_replace(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, "replace", replace)

    return arm


@pytest.mark.slow
@pytest.mark.parametrize("argv, name", [
    (["vo", "--frames", "3", "--downsample", "4"], "matches.png"),
    (["vo", "--frames", "3", "--downsample", "4"], "trajectory.png"),
    (["fuse", "--frames", "2", "--downsample", "4"], "map_color.png"),
    (["icp", "--source", "0", "--target", "2", "--downsample", "4"], "icp.png"),
])
def test_an_image_that_cannot_be_written_is_one_line_naming_it(cpu, tmp_path, capsys, disk_full_for, argv, name):
    disk_full_for(name)
    out = tmp_path / "run"
    assert main([*argv, "--out", str(out), "--quiet"]) == 2
    assert _stderr_lines(capsys)[-1] == f"ti-fusion {argv[0]}: error: {out / name}: cannot be written: No space " \
                                        "left on device"
    left = os.listdir(out) if out.exists() else []  # a run that wrote nothing leaves no folder
    assert name not in left and not [p for p in left if ".tmp" in p]


def test_scene_options_on_recorded_data_are_one_line(sequence, tmp_path, capsys):
    seq = sequence("recorded")
    assert main(["slam", str(seq), "--scene", "loop", "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert _stderr_lines(capsys) == [f"ti-fusion slam: error: --scene is for the synthetic sequence (no DATA); "
                                     f"{seq} is recorded data"]
