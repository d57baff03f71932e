"""The command line as a user meets it: one line for every bad argument and unusable output folder, a
run that owns its folder, SIGTERM and SIGHUP handled as Ctrl-C, a full disk named in one line, the
dataset's format, scale and intrinsics said aloud.

Runs ``ti_fusion.cli.main.main`` in-process (the Taichi commands on tiny frames) and, where the process
boundary is the point (a signal from outside, a closed pipe), ``python -m ti_fusion`` in a subprocess.
"""

from __future__ import annotations

import errno
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
from ti_fusion.errors import InputError
from ti_fusion.io import outputs
from ti_fusion.io.mcap_log import RunLogger, read_log
from ti_fusion.io.outputs import MARKER, RunDir
from ti_fusion.io.trajectory import read_tum

TINY = ["--frames", "3", "--downsample", "4", "--quiet"]  # 160x120 synthetic frames


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def _small_log(path: Path) -> Path:
    with RunLogger(path) as log:
        for i in range(4):
            log.log_pose(i, np.eye(4), np.eye(4))
            log.log_stats(i, {"frame": i, "status": "ok", "ms": {"track": 1.0}})
    return path


# --------------------------------------------------------------------------------------------------
# Bad arguments: one line, exit code 2, no folder left behind
# --------------------------------------------------------------------------------------------------
BAD_ARGUMENTS = [
    (["vo", "--frames", "-5"], "ti-fusion vo: error: --frames -5: must be at least 1"),
    (["vo", "--frames", "0"], "--frames 0: must be at least 1"),
    (["vo", "--start", "-5"], "--start -5: must be at least 0"),
    (["vo", "--stop", "-1"], "--stop -1: must be at least 1"),
    (["vo", "--start", "20", "--stop", "10"], "--stop 10 must be greater than --start 20"),
    (["vo", "--downsample", "0"], "--downsample 0: must be at least 1"),
    (["vo", "--stride", "0"], "--stride 0: must be at least 1"),
    (["vo", "--frames", "5", "--stop", "9"], "give --frames or --stop, not both"),
    (["vo", "--downsample", "1000"], "--downsample 1000 turns the 640x480 frames into 1x1: at least 8 pixels "
                                     "per side are needed, so at most --downsample 68"),
    (["vo", "--start", "500", "--stop", "510"], "no frames selected: the synthetic sequence has 120 frames "
                                                "(0 to 119), and start 500, stop 510, stride 1 select none"),
    (["vo", "--set", "dataset.start=-3"], "--set: dataset.start = -3: must be an integer >= 0"),
    (["slam", "--frames", "0"], "ti-fusion slam: error: --frames 0: must be at least 1"),
    (["slam", "--start", "200", "--downsample", "4"], "no frames selected"),
    (["icp", "--source", "-1", "--downsample", "4"], "--source -1: the synthetic sequence has frames 0 to 119"),
    (["synth", "{out}", "--width", "0"], "ti-fusion synth: error: --width 0: must be at least 8"),
    (["synth", "{out}", "--height", "3"], "--height 3: must be at least 8"),
    (["synth", "{out}", "--frames", "-2"], "--frames -2: must be at least 1"),
]


@pytest.mark.parametrize("argv, expected", BAD_ARGUMENTS, ids=[" ".join(a) for a, _ in BAD_ARGUMENTS])
def test_bad_arguments_are_one_line(tmp_path, capsys, argv, expected):
    out = tmp_path / "run"
    argv = [a.replace("{out}", str(out)) for a in argv]
    if argv[0] != "synth":
        argv += ["--out", str(out)]
    assert main(argv + ["--quiet"]) == 2
    assert expected in _one_line(capsys)
    assert not out.exists()  # a run that wrote nothing leaves no folder


def test_synth_names_its_output_with_its_positional_only(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["synth", str(tmp_path / "seq"), "--out", str(tmp_path / "other")])
    assert info.value.code == 2 and "unrecognized arguments: --out" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------
# A run owns its folder
# --------------------------------------------------------------------------------------------------
def test_out_that_is_a_file_or_cannot_be_written(tmp_path, capsys, monkeypatch):
    log = _small_log(tmp_path / "log.mcap")
    file = tmp_path / "notes.txt"
    file.write_text("x")
    assert main(["inspect", str(log), "--out", str(file)]) == 2
    assert _one_line(capsys) == f"ti-fusion inspect: error: {file}: exists and is not a folder: choose another --out"
    assert main(["inspect", str(log), "--out", str(file / "run")]) == 2
    assert "cannot create the output folder: Not a directory" in _one_line(capsys)

    read_only = tmp_path / "read-only"
    read_only.mkdir()
    real_open = os.open

    def refusing_open(path, flags, *args, **kwargs):  # a read-only folder, even when the tests run as root
        if Path(path).parent == read_only and flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing_open)
    assert main(["inspect", str(log), "--out", str(read_only)]) == 2
    assert _one_line(capsys) == (f"ti-fusion inspect: error: {read_only}: cannot write in this folder: "
                                 "Permission denied")


def test_an_earlier_run_is_refused_then_replaced_with_overwrite(tmp_path, capsys):
    log = _small_log(tmp_path / "log.mcap")
    out = tmp_path / "run"
    assert main(["inspect", str(log), "--out", str(out), "--plot"]) == 0
    assert (out / "stats.png").is_file()
    capsys.readouterr()
    assert main(["inspect", str(log), "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert f"{out}: holds an earlier run (inspect, process" in line and "pass --overwrite to replace it" in line
    assert (out / "stats.png").is_file()  # refused: nothing touched
    assert main(["inspect", str(log), "--out", str(out), "--overwrite"]) == 0
    assert sorted(os.listdir(out)) == [MARKER, "summary.json"]  # the old run's plot is gone
    # --overwrite never deletes an input: the log inspected lives in the output folder
    assert main(["inspect", str(out / "summary.json"), "--out", str(out), "--overwrite"]) == 2
    assert "holds the input" in _one_line(capsys) and (out / "summary.json").is_file()


def test_overwrite_keeps_the_users_own_files(tmp_path, capsys):
    """--overwrite removes what the earlier run wrote, and nothing of the user's: a folder that holds the
    user's files too is refused with one line, and nothing in it is touched."""
    log = _small_log(tmp_path / "log.mcap")
    out = tmp_path / "run"
    assert main(["inspect", str(log), "--out", str(out), "--plot"]) == 0
    (out / "notes.txt").write_text("calibrated at 9:00\n")
    (out / "photos").mkdir()
    (out / "photos" / "rig.jpg").write_bytes(b"jpeg")
    capsys.readouterr()
    assert main(["inspect", str(log), "--out", str(out), "--overwrite"]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"ti-fusion inspect: error: {out}: holds an earlier run (inspect, process ")
    assert line.endswith("and files it did not write (notes.txt, photos): --overwrite removes only a run's own "
                         "files; move those, or choose another --out")
    assert sorted(os.listdir(out)) == sorted([MARKER, "notes.txt", "photos", "stats.png", "summary.json"])
    (out / "notes.txt").unlink()
    (out / "photos" / "rig.jpg").unlink()
    (out / "photos").rmdir()
    assert main(["inspect", str(log), "--out", str(out), "--overwrite"]) == 0
    assert sorted(os.listdir(out)) == [MARKER, "summary.json"]


def test_a_folder_in_use_by_another_run_stops_the_second(tmp_path, capsys):
    log = _small_log(tmp_path / "log.mcap")
    holder = RunDir("slam", tmp_path / "run")  # a run still writing there (another process would do the same)
    try:
        for extra in ([], ["--overwrite"]):
            assert main(["inspect", str(log), "--out", str(tmp_path / "run"), *extra]) == 2
            assert "run: in use by another run (slam, process" in _one_line(capsys)
    finally:
        holder.release()


def test_default_folders_are_unique_within_one_second(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    log = _small_log(tmp_path / "log.mcap")
    same = Path("logs") / "inspect-20261125-030405-678"
    monkeypatch.setattr(outputs, "default_out_dir", lambda command: same)  # two runs in one millisecond
    assert main(["inspect", str(log), "--plot"]) == 0 and main(["inspect", str(log), "--plot"]) == 0
    assert sorted(os.listdir("logs")) == [same.name, same.name + "-2"]
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    assert main(["inspect", str(log), "--plot"]) == 0
    (newest,) = set(os.listdir("logs")) - {same.name, same.name + "-2"}  # not by mtime: it ticks coarsely
    assert newest.startswith("inspect-") and len(newest.split("-")) == 4  # ...-HHMMSS-mmm


def test_synth_out_dir_follows_the_same_rules(tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "mine.txt").write_text("x")
    args = ["--frames", "1", "--width", "16", "--quiet"]
    assert main(["synth", str(seq), *args]) == 2
    assert "is not empty (mine.txt) and holds no earlier ti-fusion run" in _one_line(capsys)
    (seq / "mine.txt").unlink()
    assert main(["synth", str(seq), *args]) == 0
    assert main(["synth", str(seq), *args]) == 2
    assert "holds an earlier run (synth" in _one_line(capsys)
    assert main(["synth", str(seq), "--overwrite", "--seed", "3", *args]) == 0
    assert json.loads((seq / "summary.json").read_text())["seed"] == 3


# --------------------------------------------------------------------------------------------------
# SIGTERM and SIGHUP: handled as Ctrl-C
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("signum, endless", [(signal.SIGTERM, False), (signal.SIGHUP, True)],
                         ids=["SIGTERM", "SIGHUP-live-stream"])
def test_sigterm_and_sighup_keep_what_was_done(cpu, tmp_path, capsys, monkeypatch, signum, endless):
    """Also during a live camera's stream (``endless``), which Ctrl-C would end with its map: these stop it."""
    from ti_fusion.io.datasets.synthetic import SyntheticDataset
    from ti_fusion.slam.slam_step import SLAMStep

    if endless:
        monkeypatch.setattr(SyntheticDataset, "endless", property(lambda self: True))
    original = SLAMStep.register_frame

    def signalled(self, frame):  # (the frames are rendered in a reader process: signalled here, in the loop)
        if frame.index == 3:
            os.kill(os.getpid(), signum)  # as `kill`, `timeout` or systemd would, at the fourth frame
        return original(self, frame)

    monkeypatch.setattr(SLAMStep, "register_frame", signalled)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    out = tmp_path / "run"
    assert main(["slam", "--frames", "8", "--downsample", "4", "--out", str(out), "--quiet"]) == 128 + signum
    name = signal.Signals(signum).name
    assert _one_line(capsys) == f"ti-fusion slam: stopped by {name}; what was written is in {out}/"
    stamps, _ = read_tum(out / "trajectory.tum")
    assert len(stamps) == 3
    log = read_log(out / "log.mcap")
    assert log.complete and len(log.stats) == 3
    assert not (out / "map.ply").exists() and not (out / "map").exists()  # the map's files: only at a run's end
    assert {s: signal.getsignal(s) for s in handlers} == handlers  # restored for whoever called main


# --------------------------------------------------------------------------------------------------
# Ctrl-C during an endless stream (a live camera): the first ends the stream, the run finishes
# --------------------------------------------------------------------------------------------------
def test_the_first_ctrl_c_ends_an_endless_streams_loop_the_second_stops(capfd, terminal_ctrl_c):
    from ti_fusion.cli.main import FINISHING, _stop_signals_raise
    from ti_fusion.interrupts import stream_end

    with _stop_signals_raise():
        with pytest.raises(KeyboardInterrupt):
            with stream_end() as end:
                signal.raise_signal(signal.SIGINT)  # to this thread, handled before it returns
                assert end.requested  # and nothing raised: the loop ends when it sees it
                signal.raise_signal(signal.SIGINT)
        with stream_end() as end:  # a stream's loop after another's end: its first Ctrl-C ends it again
            signal.raise_signal(signal.SIGINT)
            assert end.requested
        with pytest.raises(KeyboardInterrupt):  # outside a stream's loop (a dataset, finishing): a stop at once
            signal.raise_signal(signal.SIGINT)
    assert capfd.readouterr().err == 2 * (FINISHING + "\n")  # to stderr's file itself (not the buffered stream)


def _signals_at(monkeypatch, signals: list[int], endless: bool = True, at: int = 3) -> None:
    """``signals`` sent to the run as frame ``at`` is registered, each handled before the next is sent; with
    ``endless``, the synthetic sequence is a live camera's stream (a length, but no end of its own)."""
    from ti_fusion.io.datasets.synthetic import SyntheticDataset
    from ti_fusion.slam.slam_step import SLAMStep

    if endless:
        monkeypatch.setattr(SyntheticDataset, "endless", property(lambda self: True))
    original = SLAMStep.register_frame

    def register_frame(self, frame):
        result = original(self, frame)
        if frame.index == at:
            for signum in signals:
                signal.raise_signal(signum)  # to this thread: handled before it returns (os.kill's may wait)
        return result

    monkeypatch.setattr(SLAMStep, "register_frame", register_frame)


@pytest.mark.slow
def test_ctrl_c_finishes_a_live_streams_run_with_its_map(cpu, tmp_path, capsys, monkeypatch, terminal_ctrl_c):
    from ti_fusion.cli.main import FINISHING

    _signals_at(monkeypatch, [signal.SIGINT])
    out = tmp_path / "run"
    assert main(["slam", "--frames", "8", "--downsample", "4", "--mesh", "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert FINISHING in err and "interrupted" not in err, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4 and summary["dataset"]["frames"] is None  # frames 0 to 3: the one Ctrl-C came in
    stamps, _ = read_tum(out / "trajectory.tum")
    log = read_log(out / "log.mcap")
    assert len(stamps) == 4 and log.complete and len(log.stats) == 4
    assert (out / "map.ply").is_file() and (out / "map" / "map.json").is_file() and (out / "mesh.ply").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("endless", [True, False], ids=["live-stream-twice", "dataset-once"])
def test_ctrl_c_stops_a_dataset_and_a_second_ctrl_c_a_live_stream(cpu, tmp_path, capsys, monkeypatch,
                                                                   terminal_ctrl_c, endless):
    """Today's stop: a dataset's run at its first Ctrl-C, a live stream's at its second."""
    from ti_fusion.cli.main import FINISHING

    _signals_at(monkeypatch, [signal.SIGINT] * (1 + endless), endless)
    out = tmp_path / "run"
    assert main(["slam", "--frames", "8", "--downsample", "4", "--out", str(out), "--quiet"]) == 130
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err == [FINISHING] * endless + [f"ti-fusion slam: interrupted; what was written is in {out}/"]
    stamps, _ = read_tum(out / "trajectory.tum")
    log = read_log(out / "log.mcap")
    assert len(stamps) == 3 and log.complete and len(log.stats) == 3  # frame 3 is left out: its Ctrl-C stopped it
    assert not (out / "map.ply").exists() and not (out / "map").exists() and not (out / "summary.json").exists()


def test_a_stop_during_an_import_waits_for_the_import(tmp_path, monkeypatch):
    """Raised inside an extension module's initialisation (GTSAM's, imported as loop closure starts) the stop
    came out as ``ImportError: initialization failed`` and exit 1; it is sent again once the import ends."""
    from ti_fusion.cli.main import Stopped, _stop_signals_raise

    (tmp_path / "slow_to_import.py").write_text(
        "import signal\nsignal.raise_signal(signal.SIGTERM)\nDONE = True\n")  # the stop, halfway through
    monkeypatch.syspath_prepend(str(tmp_path))
    imported = None
    with _stop_signals_raise():
        with pytest.raises(Stopped):
            import slow_to_import

            imported = slow_to_import.DONE
            deadline = time.monotonic() + 60  # a bound for a broken hand-over, not a timing the test depends on
            while time.monotonic() < deadline:
                time.sleep(0.01)  # the stop arrives here, from the thread that waited for the import's end
    monkeypatch.delitem(sys.modules, "slow_to_import", raising=False)
    assert imported  # the module's whole body ran before the stop


def test_a_run_started_by_an_import_is_stopped_at_once(tmp_path, monkeypatch):
    """A script without a ``__main__`` guard, imported (``python -c "import exp"``, a notebook's ``import``),
    runs the whole run inside that import: its stops must not wait for the import's end."""
    (tmp_path / "starts_a_run.py").write_text(
        "import signal\nfrom ti_fusion.cli.main import Stopped, _stop_signals_raise\nSTOPPED = False\n"
        "try:\n    with _stop_signals_raise():\n        signal.raise_signal(signal.SIGTERM)\n"
        "        raise SystemExit('not stopped')\nexcept Stopped:\n    STOPPED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import starts_a_run

    monkeypatch.delitem(sys.modules, "starts_a_run")
    assert starts_a_run.STOPPED


def test_sigterm_from_outside_the_process(tmp_path):
    """Whenever it lands (a log write is finished first: tests/cli/test_run_checks.py checks that deterministically)."""
    out = tmp_path / "run"

    def stats_so_far(log: Path) -> int:  # the log of a run in progress: absent, then empty until its first flush
        try:
            return len(read_log(log).stats)
        except (OSError, InputError):
            return 0

    proc = subprocess.Popen([sys.executable, "-m", "ti_fusion", "vo", "--frames", "5000", "--downsample", "4",
                             "--set", "log.map_every=1", "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300  # a bound for a broken run, not a timing the test depends on
        while time.monotonic() < deadline and proc.poll() is None:
            if stats_so_far(out / "log.mcap") >= 3:
                break
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.strip() == f"ti-fusion vo: stopped by SIGTERM; what was written is in {out}/"
    stamps, _ = read_tum(out / "trajectory.tum")
    log = read_log(out / "log.mcap")
    assert log.complete and len(stamps) >= 3 and len(log.stats) >= len(stamps)


def test_an_environment_taichi_cannot_start_in_is_one_line(tmp_path):
    """No $HOME (a service, env -i) and an unknown $TI_ARCH made Taichi abort the process (exit 134) without a
    word: the first now works, the second is one line, and no output folder is left behind."""
    env = {k: v for k, v in os.environ.items() if k != "HOME"}
    proc = subprocess.run([sys.executable, "-m", "ti_fusion", "--help"], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0 and "usage: ti-fusion" in proc.stdout, proc.stderr[-2000:]
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "ti_fusion", "slam", "--frames", "2", "--out", str(out)],
                          env={**os.environ, "TI_ARCH": "nonsense"}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("ti-fusion slam: error: environment variable TI_ARCH='nonsense' is not a Taichi "
                                   "backend (Taichi reads it instead of --arch): unset it, or set one of cpu, cuda, "
                                   "vulkan")
    assert not out.exists()


# --------------------------------------------------------------------------------------------------
# Output errors: one line naming the file
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_full_disk_is_one_line_and_leaves_no_truncated_map(cpu, tmp_path, capsys, monkeypatch):
    real_open = open

    def full_for_the_map(path, mode="r", *args, **kwargs):
        if Path(path).name.startswith(".map.") and "w" in mode:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_open(path, mode, *args, **kwargs)

    monkeypatch.setattr(outputs, "open", full_for_the_map, raising=False)
    out = tmp_path / "run"
    assert main(["slam", *TINY, "--out", str(out)]) == 2
    assert _one_line(capsys) == (f"ti-fusion slam: error: {out / 'map.ply'}: cannot be written: No space left on device"
                                 f" (nor {Path('map') / 'map.json'})")  # the saved map, refused for the same reason
    assert not (out / "map.ply").exists() and not [p for p in os.listdir(out) if ".tmp" in p]
    assert not (out / "map" / "map.json").exists()
    assert len(read_tum(out / "trajectory.tum")[0]) == 3 and read_log(out / "log.mcap").complete


def test_inspect_into_a_closed_pipe_says_nothing(tmp_path):
    """``ti-fusion inspect LOG | head``: the reader goes away; no BrokenPipeError traceback."""
    log = _small_log(tmp_path / "log.mcap")
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the first line
    try:
        proc = subprocess.run([sys.executable, "-m", "ti_fusion", "inspect", str(log), "--out", str(tmp_path / "o")],
                              stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(write_end)
    assert proc.returncode == 128 + signal.SIGPIPE and proc.stderr == ""


# --------------------------------------------------------------------------------------------------
# The dataset: format, scale and intrinsics said; a folder that says nothing refused
# --------------------------------------------------------------------------------------------------
def test_numbered_pngs_without_evidence_are_refused(tmp_path, capsys):
    import cv2

    data = tmp_path / "realsense"
    for k in range(3):
        (data / "depth").mkdir(parents=True, exist_ok=True)
        (data / "rgb").mkdir(exist_ok=True)
        cv2.imwrite(str(data / "depth" / f"{k}.png"), np.full((48, 64), 1500, np.uint16))  # millimetres
        cv2.imwrite(str(data / "rgb" / f"{k}.png"), np.zeros((48, 64, 3), np.uint8))
    assert main(["vo", str(data), "--out", str(tmp_path / "run")]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"ti-fusion vo: error: {data}: ") and "pass --format iclnuim" in line
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_the_format_line_warnings_and_summary_say_what_was_read(cpu, tmp_path, capsys):
    seq = tmp_path / "seq"
    assert main(["synth", str(seq), "--frames", "4", "--width", "160", "--quiet"]) == 0
    depth_txt = seq / "depth.txt"
    lines = depth_txt.read_text().splitlines()
    comments, entries = lines[:3], lines[3:]
    depth_txt.write_text("\n".join(comments + [entries[2], entries[0], entries[3], entries[1]]) + "\n")
    rgb_txt = seq / "rgb.txt"
    rgb_txt.write_text("\n".join(rgb_txt.read_text().splitlines()[:-1]) + "\n")  # the last frame loses its rgb
    capsys.readouterr()

    out = tmp_path / "run"
    assert main(["vo", str(seq), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert ("format: tum (detected from depth.txt); depth 5000 units per metre; intrinsics fx 131.25 fy 131.25 "
            "cx 79.5 cy 59.5 at 160x120 (intrinsics.txt in the dataset folder)") in captured.out.splitlines()
    warnings = captured.err.splitlines()
    assert len(warnings) == 2 and all(w.startswith(f"ti-fusion vo: warning: {seq}: ") for w in warnings)
    assert "depth.txt lists its 4 images out of time order: they are taken in timestamp order" in warnings[0]
    assert "1 of 4 depth images have no rgb image within 0.02 s and are left out (timestamps 1.100000)" in warnings[1]
    stamps, _ = read_tum(out / "trajectory.tum")
    assert list(stamps) == sorted(stamps) and len(stamps) == 3  # in time order, whatever the file's order
    dataset = json.loads((out / "summary.json").read_text())["dataset"]
    assert dataset["format_from"] == "detected from depth.txt" and dataset["depth_scale"] == 5000.0
    assert dataset["intrinsics"]["source"] == "intrinsics.txt in the dataset folder"
    assert dataset["dropped_frames"] == 1 and len(dataset["notes"]) == 2
    metadata = read_log(out / "log.mcap").metadata["dataset"]
    assert json.loads(metadata["intrinsics"])["fx"] == 131.25 and json.loads(metadata["depth_scale"]) == 5000.0

    # --quiet: the format line (what was understood of the input) and the warnings, nothing else
    assert main(["vo", str(seq), "--out", str(tmp_path / "quiet"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert ("format: tum (detected from depth.txt); depth 5000 units per metre; intrinsics fx 131.25 fy 131.25 "
            "cx 79.5 cy 59.5 at 160x120 (intrinsics.txt in the dataset folder)") in captured.out.splitlines()
    assert not any(line.startswith("backend:") for line in captured.out.splitlines())
    assert len(captured.err.splitlines()) == 2


def test_a_command_builds_only_its_own_parser():
    """``ti-fusion COMMAND`` imports that command's module alone (``build_parser(only)``): ``batch``'s driver and
    its manifest reader load no Taichi; a slam command line parses as with every command's parser."""
    from ti_fusion.cli.main import build_parser

    code = ("import sys; from ti_fusion.cli.main import build_parser; build_parser('batch'); "
            "from ti_fusion.batch.manifest import slam_options; slam_options(); "
            "sys.exit(1 if 'taichi' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0
    argv = ["slam", "--frames", "3", "--set", "icp.dist_threshold=0.05", "--scene", "loop"]
    parsers = [build_parser(only)[0] for only in (None, "slam")]
    assert vars(parsers[0].parse_args(argv)) == vars(parsers[1].parse_args(argv))
    assert set(build_parser("slam")[1]) == {"slam"} and "batch" in build_parser()[1]


# --------------------------------------------------------------------------------------------------
# The command's end: end_process
# --------------------------------------------------------------------------------------------------
_ENDS = """
import atexit, sys, threading, time
from ti_fusion.cli.main import end_process
atexit.register(lambda: print("atexit ran", flush=False))
print("buffered", end=" ")
def last():  # it ends only once the interpreter's exit waits for it: with os._exit it would never print
    while threading.main_thread().is_alive():
        time.sleep(0.01)
    print("thread done", end=" ")
if sys.argv[1] == "thread":  # a thread the interpreter waits for: the usual exit, after it
    threading.Thread(target=last).start()
end_process(int(sys.argv[2]))
print("not reached")
"""


@pytest.mark.parametrize("case", ["plain", "thread"])
def test_end_process_runs_the_atexit_handlers_flushes_and_keeps_the_code(case):
    proc = subprocess.run([sys.executable, "-c", _ENDS, case, "3"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr[-2000:]
    want = "buffered thread done atexit ran" if case == "thread" else "buffered atexit ran"
    assert proc.stdout.strip() == want and "not reached" not in proc.stdout


def test_end_process_leaves_a_profilers_report_to_be_written(tmp_path):
    """Under ``python -m cProfile -o FILE`` the profile is written after the command returns: end_process then
    exits the usual way, and FILE is there."""
    script, profile = tmp_path / "ends.py", tmp_path / "run.prof"
    script.write_text("from ti_fusion.cli.main import end_process\nend_process(0)\n")
    proc = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), str(script)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and profile.is_file(), proc.stderr[-2000:]


def test_end_process_writes_the_kernels_compiled_into_the_offline_cache(tmp_path):
    """os._exit skips the interpreter's teardown, where Taichi writes what it compiled: end_process resets Taichi
    first, so a second process loads the kernel instead of compiling it."""
    script = """
import sys, time
import taichi as ti
from ti_fusion.cli.main import end_process
ti.init(arch=ti.cpu, offline_cache=True, offline_cache_file_path=sys.argv[1], log_level=ti.ERROR)
x = ti.field(ti.f32, shape=8)
@ti.kernel
def fill(v: ti.f32):
    for i in x:
        x[i] = v * i + 0.25
fill(2.0)
assert x[3] == 6.25
end_process(0)
"""
    cache, path = tmp_path / "cache", tmp_path / "kernel.py"  # (Taichi reads a kernel's source from its file)
    path.write_text(script)
    for _ in range(2):
        proc = subprocess.run([sys.executable, str(path), str(cache)], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert list(cache.glob("*.tic")) and (cache / "ticache.tcb").is_file()


@pytest.mark.parametrize("given", [None, "OFF"])
def test_the_command_leaves_taichis_version_check_out_unless_asked(given):
    env = {k: v for k, v in os.environ.items() if k != "TI_SKIP_VERSION_CHECK"}
    if given is not None:
        env["TI_SKIP_VERSION_CHECK"] = given
    code = "import os, ti_fusion.cli.main; print(os.environ['TI_SKIP_VERSION_CHECK'])"
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == (given or "ON"), proc.stderr[-2000:]
