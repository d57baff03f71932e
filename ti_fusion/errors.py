"""Errors that reach the user as one line: what is wrong and, where there is one, which file."""

from __future__ import annotations

from pathlib import Path


def displayable(text: str) -> str:
    """``text`` as UTF-8 can hold it: bytes of a path that are not UTF-8 (Python keeps them as lone surrogates,
    which UTF-8 writers refuse) written as ``\\xff`` escapes."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


class TiFusionError(Exception):
    """Base class of every error the CLI reports as a one-line message (exit code 2)."""

    exit_code = 2


class InputError(TiFusionError):
    """Bad input data: a missing folder, an unreadable image, a pose that is not rigid, ..."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)

    def __reduce__(self):  # pickled by a frame reader process (ti_fusion.io.frame_workers)
        return type(self), (self.path, self.problem)


class NotLocalised(InputError):
    """A session against a saved map that never found itself in it: no frame got a pose (exit code 3)."""

    exit_code = 3


class OutputError(TiFusionError):
    """An output that cannot be written: the run folder is taken or not writable, the disk is full, ..."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        return type(self), (self.path, self.problem)


class BackendUnavailable(TiFusionError):
    """The requested Taichi backend is absent on this machine."""


class MapCapacityError(TiFusionError):
    """The surfel map is full and growth is disabled."""
