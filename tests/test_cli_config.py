"""What a user meets at the command line for the run-trust classes of issue 19 left after the first pass:
config values against their rules, the first usable frame, a partial ground truth, a stop during a log
write, and the smaller messages (one-frame runs, threshold comparisons, output files that cannot be
written, frame numbers of the synthetic sequence, one dataset line)."""

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

    return arm


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
    # the message whose write the stop arrived in was written whole, and the stop came after it
    assert log.complete and [s["frame"] for s in log.stats] == list(range(written + 1))


def test_sigterm_during_a_run_keeps_the_log_whole(cpu, tmp_path, capsys, signal_in_chunk_write):
    """The race behind the occasional failure of test_cli.py::test_sigterm_from_outside_the_process: a
    SIGTERM while the log writer finished a chunk lost that chunk's messages."""
    signal_in_chunk_write(signal.SIGTERM, after=4)
    out = tmp_path / "run"
    assert main(["vo", "--frames", "40", "--downsample", "4", "--set", "log.map_every=1", "--out", str(out),
                 "--quiet"]) == 128 + signal.SIGTERM
    assert _stderr_lines(capsys) == [f"ti-fusion vo: stopped by SIGTERM; what was written is in {out}/"]
    stamps, _ = read_tum(out / "trajectory.tum")
    log = read_log(out / "log.mcap")
    assert log.complete and len(stamps) >= 1 and len(log.stats) == len(stamps)
    assert log.channels["/camera/pose"].count >= len(stamps)
