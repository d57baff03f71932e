"""Where a run writes: its own output folder, files written whole or not at all, ``summary.json`` and
the terminal progress bar."""

from __future__ import annotations

import fnmatch
import json
import os
import secrets
import shutil
import socket
import sys
import weakref
from contextlib import contextmanager, suppress
from datetime import datetime
from pathlib import Path
from typing import IO, Callable, Iterable, Iterator, TypeVar

import numpy as np

from ti_fusion.errors import OutputError
from ti_fusion.timing import Stopwatch

try:
    import fcntl
except ImportError:  # Windows has none: there the marker is written but not locked
    fcntl = None

T = TypeVar("T")

# The file that marks a folder as a run's and that the run holds locked while it writes there. When the run
# ends it lists the names the run left there ("files"), which is what --overwrite may remove.
MARKER = ".ti-fusion-run"
# What a run whose marker lists no files (killed before it ended, or from before the list) may have written:
# every command's outputs, synth's TUM layout, batch's folders and tables, and the temporary names of files
# being written.
RUN_OUTPUT_PATTERNS = ("summary.json", "*.mcap", "*.tum", "*.ply", "*.glb", "*.png", ".*.tmp*", "map", "rgb",
                       "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "associations.txt", "runs", "jobs", "results.csv",
                       "results.md")


def default_out_dir(command: str, now: datetime | None = None) -> Path:
    """``logs/<command>-<YYYYmmdd-HHMMSS-mmm>``; RunDir adds ``-2``, ``-3``, ... when it is taken."""
    now = now or datetime.now()
    return Path("logs") / f"{command}-{now:%Y%m%d-%H%M%S}-{now.microsecond // 1000:03d}"


class RunDir:
    """The output folder of one run (``--out``, default ``logs/<command>-<YYYYmmdd-HHMMSS-mmm>/``).

    A run owns its folder:
    - the default folder is created exclusively: a name another run took in the same millisecond gets
      ``-2``, ``-3``, ...;
    - a given folder is created if missing; an existing one must be empty, or hold an earlier run and
      ``overwrite`` be set, and then the earlier run's files are removed before anything is written. A
      non-empty folder that holds no run is never emptied, nor one that holds files besides the earlier
      run's (the user's own notes kept there): both are refused with one line;
    - ``resume``: a folder that holds an earlier run of the same command is taken as it is, its files kept
      (``ti-fusion batch`` goes on with the jobs it had not finished); ``overwrite`` still replaces it;
    - the marker file ``.ti-fusion-run`` (command, process, start time) is kept locked while the run
      lives (``flock``: the kernel releases it however the process ends, so a killed run leaves no
      stale lock), and a second run given the same folder stops at once with ``OutputError``.
    ``release()`` (or the end of a ``with`` block) unlocks it; a run that wrote nothing leaves no trace.
    """

    def __init__(self, command: str, out: str | Path | None = None, overwrite: bool = False, resume: bool = False,
                 add_to: bool = False):
        self.command = command
        self.resumed = False
        # add_to: ``out`` holds an earlier run that this command adds files to (ti-fusion mesh RUN_DIR): its
        # files are kept, and the marker goes on naming that run (and, after, every file in the folder)
        self.adding = add_to
        self._fd: int | None = None
        self._created = False
        self._record: dict = {}  # what the marker says of this run
        for _ in range(5):  # another run may remove the folder it emptied between our steps: start again
            if out:
                self.path = Path(out)
                self._created = _make_folder(self.path)
            else:
                self.path = _make_default_folder(command)
                self._created = True
            if self._lock(overwrite, resume):
                break
        else:
            raise OutputError(self.path, "the folder keeps disappearing (another process is removing it)")
        self._finalizer = weakref.finalize(self, os.close, self._fd)

    def __enter__(self) -> "RunDir":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.release()
        return False

    def file(self, name: str) -> Path:
        return self.path / name

    def write_summary(self, summary: dict) -> Path:
        path = self.file("summary.json")
        with atomic_write(path, "w") as f:
            f.write(json.dumps(jsonable(summary), indent=2) + "\n")
        return path

    def release(self) -> None:
        """Unlock the folder. If the run wrote nothing there, leave no trace: the marker goes, and the
        folder too when this run created it (idempotent)."""
        if self._fd is None:
            return
        try:
            entries = _entries(self.path)
            if entries == []:
                with suppress(OSError):
                    (self.path / MARKER).unlink()
                    if self._created:
                        self.path.rmdir()
            else:
                with suppress(OSError):  # what a later --overwrite may remove: this run's files
                    data = json.dumps({**self._record, "files": sorted(entries)}).encode()
                    os.ftruncate(self._fd, 0)
                    os.pwrite(self._fd, data, 0)
        finally:
            self._finalizer()
            self._fd = None

    # -- internals --------------------------------------------------------------------------------
    def _lock(self, overwrite: bool, resume: bool = False) -> bool:
        """Take the marker's lock and check what the folder holds; False if the folder went away."""
        marker = self.path / MARKER
        new_marker = True
        try:
            try:
                fd = os.open(marker, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                new_marker = False
                fd = os.open(marker, os.O_RDWR)
        except FileNotFoundError:
            return False
        except OSError as exc:
            raise OutputError(self.path, f"cannot write in this folder: {exc.strerror}") from None
        try:
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    raise OutputError(self.path, f"in use by another run ({describe_run(_read_marker(fd))}): "
                                                 "choose another --out") from None
                try:
                    if os.stat(marker).st_ino != os.fstat(fd).st_ino:
                        raise FileNotFoundError
                except FileNotFoundError:  # the run that held it removed it with its empty folder
                    os.close(fd)
                    return False
            try:
                self._check_contents(fd, new_marker, overwrite, resume)
            except BaseException:
                if new_marker:  # we hold the lock: nobody else uses the marker we made
                    with suppress(OSError):
                        marker.unlink()
                raise
            if self.adding:
                self._record = {k: v for k, v in (_read_marker(fd) or _legacy_run(self.path) or {}).items()
                                if k != "files"}
            else:
                self._record = {"command": self.command, "pid": os.getpid(), "host": socket.gethostname(),
                                "started": datetime.now().isoformat(timespec="seconds")}
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(self._record).encode(), 0)
        except BaseException:
            with suppress(OSError):
                os.close(fd)
            raise
        self._fd = fd
        return True

    def _check_contents(self, fd: int, new_marker: bool, overwrite: bool, resume: bool = False) -> None:
        entries = _entries(self.path)
        if not entries and self.adding:
            raise OutputError(self.path, "holds no run to add to")
        if not entries:
            return
        earlier = _legacy_run(self.path) if new_marker else (_read_marker(fd) or {})
        if self.adding and earlier is not None:
            return
        if earlier is None:
            shown = ", ".join(sorted(entries)[:3]) + (", ..." if len(entries) > 3 else "")
            raise OutputError(self.path, f"is not empty ({shown}) and holds no earlier ti-fusion run: "
                                         "choose another --out")
        if resume and not overwrite and earlier.get("command") == self.command:
            self.resumed = True
            return
        if not overwrite:
            raise OutputError(self.path, f"holds an earlier run ({describe_run(earlier)}): pass --overwrite "
                                         "to replace it, or choose another --out")
        others = [name for name in entries if not _written_by_run(name, earlier)]
        if others:
            shown = ", ".join(sorted(others)[:3]) + (", ..." if len(others) > 3 else "")
            raise OutputError(self.path, f"holds an earlier run ({describe_run(earlier)}) and files it did not write "
                                         f"({shown}): --overwrite removes only a run's own files; move those, or "
                                         "choose another --out")
        for name in entries:
            entry = self.path / name
            try:
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry)
                else:
                    entry.unlink()
            except OSError as exc:
                raise OutputError(entry, f"cannot remove the earlier run's file: {exc.strerror}") from None


def _make_folder(path: Path) -> bool:
    """Create ``path`` if missing; True if this call created it."""
    if path.exists() and not path.is_dir():
        raise OutputError(path, "exists and is not a folder: choose another --out")
    try:
        path.mkdir(parents=True)
        return True
    except FileExistsError:
        if not path.is_dir():
            raise OutputError(path, "exists and is not a folder: choose another --out") from None
        return False
    except OSError as exc:
        raise OutputError(path, f"cannot create the output folder: {exc.strerror}") from None


def _make_default_folder(command: str) -> Path:
    base = default_out_dir(command)
    for k in range(1, 1000):
        path = base if k == 1 else base.with_name(f"{base.name}-{k}")
        try:
            path.mkdir(parents=True)
            return path
        except FileExistsError:
            continue
        except OSError as exc:
            raise OutputError(path, f"cannot create the output folder: {exc.strerror}") from None
    raise OutputError(base, "no free output folder name: pass --out")


def _written_by_run(name: str, record: dict) -> bool:
    """Whether ``name`` is one of the earlier run's files: listed in its marker, or where the marker lists
    none, one of the names runs write."""
    files = record.get("files")
    if isinstance(files, list):
        return name in files
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in RUN_OUTPUT_PATTERNS)


def _entries(path: Path) -> list[str]:
    """The names in a run folder other than the marker."""
    return [name for name in os.listdir(path) if name != MARKER]


def _read_marker(fd: int) -> dict | None:
    try:
        record = json.loads(os.pread(fd, 4096, 0).decode())
        return record if isinstance(record, dict) else None
    except (OSError, ValueError):
        return None


def is_run_folder(folder: str | Path) -> bool:
    """Whether ``folder`` holds a ti-fusion run (its marker, or a summary.json that names a command)."""
    folder = Path(folder)
    return folder.is_dir() and ((folder / MARKER).is_file() or _legacy_run(folder) is not None)


def run_in_progress(folder: str | Path) -> dict | None:
    """The marker's record of a run that holds ``folder`` now (its lock is taken), else None."""
    if fcntl is None:
        return None
    try:
        fd = os.open(Path(folder) / MARKER, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return _read_marker(fd) or {}
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _legacy_run(path: Path) -> dict | None:
    """A run folder written before runs left a marker: its summary.json names a command."""
    try:
        summary = json.loads((path / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return {"command": summary["command"]} if isinstance(summary, dict) and "command" in summary else None


def describe_run(record: dict | None) -> str:
    if not record:
        return "a ti-fusion run"
    words = [str(record.get("command", "ti-fusion"))]
    if "pid" in record:
        words.append(f"process {record['pid']}" + (f" on {record['host']}" if "host" in record else ""))
    if "started" in record:
        words.append(f"started {record['started']}")
    return ", ".join(words)


# --------------------------------------------------------------------------------------------------
# Files written whole or not at all


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary name in ``path``'s folder to write to; when the block ends it replaces ``path``.

    So ``path`` is either absent (or the earlier file) or the complete new file, never a truncated one,
    whatever stops the write (a full disk, Ctrl-C, SIGTERM). The temporary name keeps the suffix, so
    writers that choose the format by it (OpenCV, Matplotlib) work. An ``OSError`` on the way becomes
    an ``OutputError`` naming ``path`` and the reason.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # a write error the page cache still holds surfaces here, not after the rename
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException as exc:
        with suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise OutputError(path, f"cannot be written: {exc.strerror or exc}") from exc
        raise


@contextmanager
def atomic_write(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """``open(path, mode)`` ("w" or "wb") through ``atomic_path``."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as f:
            yield f


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """An image in OpenCV's channel order (BGR, or one channel), encoded by its suffix, written atomically."""
    import cv2

    path = Path(path)
    ok, buf = cv2.imencode(path.suffix, np.ascontiguousarray(image))
    if not ok:
        raise OutputError(path, f"cannot encode a {image.dtype} {'x'.join(map(str, image.shape))} image as {path.suffix}")
    with atomic_write(path, "wb") as f:
        f.write(buf.tobytes())
    return path


# --------------------------------------------------------------------------------------------------
# summary.json and the progress bar


def base_summary(command: str, frames: int, wall_s: float, ms_per_stage: dict) -> dict:
    """The fields every summary.json has."""
    return {
        "command": command,
        "frames": int(frames),
        "wall_s": round(float(wall_s), 3),
        "fps": round(frames / wall_s, 3) if wall_s > 0 else None,
        "ms_per_stage": ms_per_stage,
    }


def jsonable(obj):
    """Plain JSON types: NumPy scalars/arrays unpacked, NaN/inf → null (JSON has no NaN), paths as text."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def progress(items: Iterable[T], total: int | None, desc: str, enabled: bool = True,
             note: Callable[[], str] | None = None) -> Iterator[T]:
    """A one-line progress bar on stderr (only on a terminal, and not with --quiet), ending with ``note()``
    where it says something (e.g. "not localised"); a ``total`` of None (an endless stream) counts frames
    and says how the stream ends."""
    enabled = enabled and sys.stderr.isatty()
    watch = Stopwatch()
    try:
        for i, item in enumerate(items):
            yield item
            if enabled:
                done = i + 1
                rate = done / max(watch.ms / 1e3, 1e-9)
                said = note() if note is not None else ""
                if total is None:
                    line = f"\r{desc}: {done} frames {rate:5.1f} it/s (Ctrl-C ends the stream)"
                else:
                    bar = "#" * int(30 * done / max(total, 1))
                    line = f"\r{desc} [{bar:<30}] {done}/{total} {rate:5.1f} it/s"
                sys.stderr.write(line + (f" {said}\x1b[K" if said else "\x1b[K"))
                sys.stderr.flush()
    finally:  # also when the loop ends early (a stream's end, Ctrl-C): the next line starts on its own
        if enabled:
            sys.stderr.write("\n")
