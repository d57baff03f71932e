"""A run's outputs: the folder it owns (unique default name, one run at a time, an earlier run replaced
only when asked) and files written whole or not at all (a full disk leaves no truncated file).

No Taichi needed."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.errors import OutputError
from ti_fusion.io import outputs
from ti_fusion.io.mcap_log import RunLogger
from ti_fusion.io.outputs import MARKER, RunDir, atomic_write, default_out_dir, write_image
from ti_fusion.io.ply import read_ply, write_ply
from ti_fusion.io.trajectory import read_tum, write_tum

try:
    import resource
except ImportError:  # Windows
    resource = None


# --------------------------------------------------------------------------------------------------
# The run folder
# --------------------------------------------------------------------------------------------------
def test_default_folder_has_milliseconds_and_never_collides(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert default_out_dir("slam", datetime(2026, 11, 25, 3, 4, 5, 678_900)) == Path("logs/slam-20261125-030405-678")
    # Two runs in the same millisecond: the second gets the next free name.
    same = Path("logs/slam-20261125-030405-678")
    monkeypatch.setattr(outputs, "default_out_dir", lambda command: same)
    first, second, third = RunDir("slam"), RunDir("slam"), RunDir("slam")
    assert [first.path.name, second.path.name, third.path.name] == [same.name, same.name + "-2", same.name + "-3"]
    assert all(r.path.is_dir() for r in (first, second, third))


def test_new_and_empty_folders_are_taken(tmp_path):
    new = RunDir("slam", tmp_path / "a" / "b")
    assert new.path.is_dir() and (new.path / MARKER).is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    run = RunDir("slam", empty)
    record = json.loads((empty / MARKER).read_text())
    assert record["command"] == "slam" and record["pid"] == os.getpid()
    run.release()


def test_a_second_run_on_the_same_folder_stops(tmp_path):
    first = RunDir("slam", tmp_path / "run")
    with pytest.raises(OutputError, match=r"run: in use by another run \(slam, process \d+"):
        RunDir("vo", tmp_path / "run")
    with pytest.raises(OutputError, match="in use by another run"):
        RunDir("vo", tmp_path / "run", overwrite=True)  # --overwrite never takes a folder from a live run
    first.release()


def _hold_in_subprocess(folder: Path, then: str) -> subprocess.Popen:
    """A process that takes ``folder`` as its run folder, prints "ready", then ``then`` ("wait" or "die")."""
    code = textwrap.dedent(f"""
        import os, sys
        from ti_fusion.io.outputs import RunDir
        run = RunDir("slam", {str(folder)!r})
        (run.path / "log.mcap").write_bytes(b"partial")
        print("ready", flush=True)
        if {then!r} == "die":
            os._exit(9)  # as SIGKILL: no cleanup at all
        sys.stdin.read()
    """)
    return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def test_a_second_process_on_the_same_folder_stops(tmp_path):
    proc = _hold_in_subprocess(tmp_path / "run", "wait")
    try:
        assert proc.stdout.readline().strip() == "ready"
        with pytest.raises(OutputError, match=f"in use by another run \\(slam, process {proc.pid}"):
            RunDir("slam", tmp_path / "run", overwrite=True)
    finally:
        proc.communicate("", timeout=60)
    # The holder has ended: its folder is an earlier run now.
    with pytest.raises(OutputError, match="holds an earlier run"):
        RunDir("slam", tmp_path / "run")


def test_a_killed_run_leaves_no_stale_lock(tmp_path):
    proc = _hold_in_subprocess(tmp_path / "run", "die")
    assert proc.stdout.readline().strip() == "ready"
    proc.wait(timeout=60)
    with pytest.raises(OutputError, match="holds an earlier run.*--overwrite"):
        RunDir("slam", tmp_path / "run")
    run = RunDir("slam", tmp_path / "run", overwrite=True)
    assert sorted(os.listdir(run.path)) == [MARKER]


def test_an_earlier_run_is_replaced_only_with_overwrite(tmp_path):
    folder = tmp_path / "run"
    with RunDir("slam", folder) as first:
        first.write_summary({"command": "slam", "frames": 3})
        (folder / "map.ply").write_bytes(b"old map")
        (folder / "views").mkdir()
        (folder / "views" / "a.png").write_bytes(b"old")
    with pytest.raises(OutputError) as info:
        RunDir("slam", folder)
    assert "holds an earlier run (slam" in str(info.value) and "--overwrite" in str(info.value)
    assert (folder / "map.ply").read_bytes() == b"old map"  # refused: nothing touched
    with RunDir("vo", folder, overwrite=True):
        assert sorted(os.listdir(folder)) == [MARKER]  # the old run's files are gone before anything is written
        assert json.loads((folder / MARKER).read_text())["command"] == "vo"


def test_resume_continues_an_earlier_run_of_the_same_command_only(tmp_path):
    folder = tmp_path / "batch"
    with RunDir("batch", folder) as first:
        (folder / "results.csv").write_text("rows")
        assert not first.resumed
    with RunDir("batch", folder, resume=True) as again:  # ti-fusion batch resuming: its files stay
        assert again.resumed and (folder / "results.csv").read_text() == "rows"
    with pytest.raises(OutputError, match="holds an earlier run"):
        RunDir("slam", folder, resume=True)  # another command's folder is never taken as its own
    with RunDir("batch", folder, overwrite=True, resume=True) as fresh:  # --overwrite still starts afresh
        assert not fresh.resumed and sorted(os.listdir(folder)) == [MARKER]


def test_a_run_folder_from_before_the_marker_is_recognised(tmp_path):
    folder = tmp_path / "old"
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"command": "slam", "frames": 10}))
    (folder / "trajectory.tum").write_text("# old\n")
    with pytest.raises(OutputError, match="holds an earlier run \\(slam\\)"):
        RunDir("slam", folder)
    RunDir("slam", folder, overwrite=True).release()
    assert not (folder / "trajectory.tum").exists()


def test_a_folder_that_holds_no_run_is_never_emptied(tmp_path):
    folder = tmp_path / "thesis"
    folder.mkdir()
    (folder / "chapter1.tex").write_text("precious")
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="is not empty \\(chapter1.tex\\) and holds no earlier ti-fusion run"):
            RunDir("slam", folder, overwrite=overwrite)
    assert sorted(os.listdir(folder)) == ["chapter1.tex"]  # and no marker left behind


def test_out_that_is_a_file_or_under_a_file(tmp_path):
    file = tmp_path / "notes.txt"
    file.write_text("x")
    with pytest.raises(OutputError, match="notes.txt: exists and is not a folder"):
        RunDir("slam", file)
    with pytest.raises(OutputError, match="cannot create the output folder: Not a directory"):
        RunDir("slam", file / "run")


def test_out_that_cannot_be_written(tmp_path, monkeypatch):
    folder = tmp_path / "read-only"
    folder.mkdir()
    real_open = os.open

    def refusing_open(path, flags, *args, **kwargs):  # what a read-only folder does (tests may run as root)
        if Path(path).parent == folder and flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing_open)
    with pytest.raises(OutputError, match="read-only: cannot write in this folder: Permission denied"):
        RunDir("slam", folder)


@pytest.mark.skipif(os.name == "nt" or os.geteuid() == 0, reason="permissions do not bind root")
def test_out_in_a_read_only_folder(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="cannot write in this folder: Permission denied"):
            RunDir("slam", folder)
        with pytest.raises(OutputError, match="cannot create the output folder: Permission denied"):
            RunDir("slam", folder / "sub")
    finally:
        folder.chmod(0o755)


def test_release_removes_only_an_empty_folder_it_created(tmp_path):
    created = RunDir("slam", tmp_path / "new")
    created.release()
    assert not (tmp_path / "new").exists()
    existing = tmp_path / "existing"
    existing.mkdir()
    RunDir("slam", existing).release()
    assert existing.is_dir() and os.listdir(existing) == []
    kept = RunDir("slam", tmp_path / "kept")
    (kept.path / "trajectory.tum").write_text("# t\n")
    kept.release()
    assert sorted(os.listdir(tmp_path / "kept")) == [MARKER, "trajectory.tum"]
    # released: the folder is free for the next run (with --overwrite, since it holds this one)
    RunDir("slam", tmp_path / "kept", overwrite=True).release()


# --------------------------------------------------------------------------------------------------
# Files written whole or not at all
# --------------------------------------------------------------------------------------------------
class _FullDisk:
    """``open`` for the writers of ``ti_fusion.io.outputs``: files named ``names`` take ``room`` bytes, then
    every write fails with ENOSPC, as on a full disk."""

    def __init__(self, names: set[str], room: int = 100):
        self.names, self.room = names, room

    def __call__(self, path, mode="r", *args, **kwargs):
        f = open(path, mode, *args, **kwargs)
        if not any(Path(path).name.startswith(f".{Path(n).stem}.") for n in self.names):
            return f
        room = self.room

        class Full:
            def __enter__(self):
                return self

            def __exit__(self, *exc):
                f.close()
                return False

            def write(self, data):
                nonlocal room
                f.write(data[:room])
                room -= min(room, len(data))
                if room == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return len(data)

        return Full()


def _points(n=1000):
    rng = np.random.default_rng(1)
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.integers(0, 256, (n, 3))


@pytest.mark.parametrize("name", ["map.ply", "trajectory.tum", "summary.json"])
def test_full_disk_leaves_the_earlier_file_or_none(tmp_path, monkeypatch, name):
    run = RunDir("slam", tmp_path / "run")
    path = run.file(name)
    stamps, poses = np.arange(50.0), np.tile(np.eye(4), (50, 1, 1))
    writers = {
        "map.ply": lambda: write_ply(path, *_points()),
        "trajectory.tum": lambda: write_tum(path, stamps, poses),
        "summary.json": lambda: run.write_summary({"command": "slam", "frames": list(range(500))}),
    }

    def written() -> list[str]:
        return sorted(set(os.listdir(run.path)) - {MARKER})

    monkeypatch.setattr(outputs, "open", _FullDisk({name}), raising=False)
    with pytest.raises(OutputError) as info:
        writers[name]()
    assert str(info.value) == f"{path}: cannot be written: No space left on device"
    assert written() == []  # no truncated file, no temporary file left behind
    # Over an earlier complete file: that file stays as it was.
    path.write_bytes(b"earlier")
    with pytest.raises(OutputError):
        writers[name]()
    assert written() == [name] and path.read_bytes() == b"earlier"
    monkeypatch.undo()
    writers[name]()
    assert written() == [name] and path.stat().st_size > 100


@pytest.mark.skipif(resource is None, reason="no file size limit (RLIMIT_FSIZE) on this platform")
def test_a_real_write_failure_leaves_no_truncated_ply(tmp_path):
    """The operating system refuses the write (a file size limit: Python ignores SIGXFSZ, so the write
    fails with EFBIG the way a full disk fails it with ENOSPC)."""
    path = tmp_path / "map.ply"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (16384, hard))
    try:
        with pytest.raises(OutputError, match="map.ply: cannot be written: File too large"):
            write_ply(path, *_points(5000))  # 27 bytes a point: 135 kB
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert os.listdir(tmp_path) == []
    write_ply(path, *_points(5000))
    assert len(read_ply(path)) == 5000


def test_write_image_is_atomic_and_names_the_file(tmp_path, monkeypatch):
    image = np.arange(12 * 16, dtype=np.uint16).reshape(12, 16)
    import cv2

    write_image(tmp_path / "depth.png", image)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "depth.png"), cv2.IMREAD_UNCHANGED), image)
    monkeypatch.setattr(outputs, "open", _FullDisk({"view.png"}), raising=False)
    with pytest.raises(OutputError, match="view.png: cannot be written: No space left on device"):
        write_image(tmp_path / "view.png", np.zeros((480, 640, 3), np.uint8))
    assert sorted(os.listdir(tmp_path)) == ["depth.png"]


def test_atomic_write_passes_other_errors_and_cleans_up(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(tmp_path / "trajectory.tum") as f:
            f.write("half")
            raise KeyboardInterrupt  # Ctrl-C or SIGTERM in the middle of a write
    assert os.listdir(tmp_path) == []


def test_the_log_names_itself_when_the_disk_fills(tmp_path, monkeypatch):
    from ti_fusion.io import mcap_log

    class Full:
        def __init__(self, path, mode):
            pass

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(mcap_log, "open", Full, raising=False)
    with pytest.raises(OutputError, match="log.mcap: cannot be written: No space left on device"):
        RunLogger(tmp_path / "log.mcap")


def test_overwrite_removes_only_the_earlier_runs_files(tmp_path):
    """The marker lists what a run left; a killed run's marker lists nothing, and then only names runs
    write count as its files. Anything else in the folder is the user's: refused, nothing removed."""
    folder = tmp_path / "run"
    with RunDir("slam", folder) as first:
        first.write_summary({"command": "slam"})
        (folder / "map.ply").write_bytes(b"old map")
    assert json.loads((folder / MARKER).read_text())["files"] == ["map.ply", "summary.json"]
    (folder / "notes.png").write_bytes(b"mine")  # a run's kind of name, but not in this run's list
    with pytest.raises(OutputError, match=r"files it did not write \(notes.png\)"):
        RunDir("slam", folder, overwrite=True)
    assert sorted(os.listdir(folder)) == [MARKER, "map.ply", "notes.png", "summary.json"]
    (folder / "notes.png").unlink()
    RunDir("vo", folder, overwrite=True).release()
    assert os.listdir(folder) == []

    proc = _hold_in_subprocess(folder, "die")  # killed: its marker lists no files
    assert proc.stdout.readline().strip() == "ready"
    proc.wait(timeout=60)
    (folder / "trajectory.tum").write_text("# the killed run's\n")
    (folder / "notes.txt").write_text("mine\n")
    with pytest.raises(OutputError, match=r"files it did not write \(notes.txt\)"):
        RunDir("slam", folder, overwrite=True)
    (folder / "notes.txt").unlink()
    RunDir("slam", folder, overwrite=True).release()
    assert not (folder / "trajectory.tum").exists()


# --------------------------------------------------------------------------------------------------
# The progress bar
# --------------------------------------------------------------------------------------------------
class _Terminal:
    """stderr as a terminal (the bar is drawn only on one)."""

    def __init__(self):
        self.text = ""

    def write(self, s: str) -> None:
        self.text += s

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return True


def test_the_progress_bar_of_a_stream_counts_frames_and_ends_its_line_when_the_loop_stops_early(monkeypatch):
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    for i in outputs.progress(range(1000), None, "slam"):  # an endless stream: no total to show
        if i == 2:
            break  # (a Ctrl-C that ended the stream)
    assert "\rslam: 2 frames" in terminal.text and "(Ctrl-C ends the stream)" in terminal.text
    assert terminal.text.endswith("\x1b[K\n")  # the line after it starts on its own
    terminal.text = ""
    assert list(outputs.progress(range(3), 3, "vo")) == [0, 1, 2]
    assert "\rvo [" in terminal.text and " 3/3 " in terminal.text and terminal.text.endswith("\x1b[K\n")
