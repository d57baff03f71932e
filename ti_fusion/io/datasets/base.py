"""The one interface every dataset loader implements."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Iterator

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError
from ti_fusion.frame import Frame  # noqa: F401 (the loaders build frames; it lives below tracking)

log = logging.getLogger(__name__)

# Pixels per side of the smallest frame a loader hands out (after --downsample): a frame of a few pixels
# has nothing to track, and OpenCV's ORB fails outright on one of 1x1.
MIN_FRAME_SIZE = 8


class Dataset(ABC):
    """A sequence of RGB-D frames with intrinsics and, where it has them, ground-truth poses.

    Subclasses implement ``_num_raw_frames`` and ``_load_raw(i)`` at full resolution; the base class
    applies frame selection (start/stop/stride: positions from the first frame, never counted from the
    end) and integer downsampling (``img[::f, ::f]``: plain subsampling, so no depth is averaged across
    an edge, and the intrinsics scale exactly).

    What a user needs to trust the frames is in ``describe()``: how the format was chosen, the depth
    scale and intrinsics in use and where they come from, and what the loader dropped or reordered
    (``note``: also logged as a warning, which the CLI prints).
    """

    name: str = "dataset"
    format: str = "?"
    depth_scale: float | None = None  # raw depth units per metre; None where depth is not read from images
    # the colour images are registered to depth, pixel for pixel (the photometric tracking term needs it)
    color_registered: bool = False
    # ``dataset[i]`` may run in several readers at once, in any order (``ti_fusion.io.prefetch``)
    concurrent_reads: bool = False
    # What ``open_dataset`` asks of a format registered in ti_fusion/io/formats.py (besides ``detect``):
    identified_by: str | None = None  # the files ``detect`` looks for, as the line for an unknown layout names them
    single_file: bool = False         # an input may be one file (a bag, a run log) rather than a folder
    replaceable_calibration: bool = False  # dataset.intrinsics and dataset.depth_scale replace the format's own
    reads_color_camera: bool = False  # reads dataset.color_extrinsics and color_intrinsics itself (a bag's topics)
    # which of the settings that only some formats read (ground_truth, the bag topics, intrinsics, depth_scale)
    # this one does: open_dataset refuses the others in one line rather than ignore them
    reads: frozenset[str] = frozenset()
    # ``dataset[i]`` may run in a reader process, on a pickled copy of the dataset (files and bags)
    reads_in_process: bool = False

    def __init__(self, root: str | Path, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        self.root = Path(root)
        for key, value, least in (("downsample", downsample, 1), ("stride", stride, 1), ("start", start, 0),
                                  ("stop", 0 if stop is None else stop, 0)):
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
                raise InputError(None, f"dataset.{key} = {value}: must be an integer of at least {least}")
        self.downsample = int(downsample)
        self._selection = (start, stop, stride)
        self._indices: list[int] | None = None
        self.format_from = "given"           # how the format was chosen: open_dataset says "detected from ..."
        self.intrinsics_source = "default"   # where the intrinsics come from (a file, a calibration table, ...)
        self.notes: list[str] = []           # what the loader changed in or dropped from the sequence
        self.dropped_frames = 0              # frames left out of the sequence (``notes`` say which and why)

    # -- implemented by each format -------------------------------------------------------------
    @staticmethod
    def detect(root: Path) -> str | None:
        """What identifies ``root`` (a folder; a file where ``single_file``) as this format, as the format line
        says it (``"depth.txt"``), or None. Only files that no other format has count: a wrong guess gives
        wrong depths without any error. The default, None, is a format that is never guessed."""
        return None

    @abstractmethod
    def _num_raw_frames(self) -> int: ...

    @abstractmethod
    def _load_raw(self, raw_index: int) -> Frame:
        """Frame ``raw_index`` at full resolution (its ``index`` is the raw index)."""

    @property
    @abstractmethod
    def raw_intrinsics(self) -> Intrinsics: ...

    @property
    def has_ground_truth(self) -> bool:
        return False

    @property
    def endless(self) -> bool:
        """A stream without an end of its own (a live camera without --frames): its run ends at the first
        Ctrl-C as at a recording's end, with every output (``ti_fusion.interrupts.stream_end``)."""
        return False

    @property
    def color_for_tracking(self) -> bool:
        """Whether the photometric tracking term may use this set's colour: only colour registered to depth.
        A format whose registration is the user's word (a folder, a log) overrides this with
        ``dataset.color_registered``."""
        return bool(self.color_registered)

    # -- shared behaviour -----------------------------------------------------------------------
    @property
    def indices(self) -> list[int]:
        if self._indices is None:
            start, stop, stride = self._selection
            self._indices = list(range(self._num_raw_frames()))[start:stop:stride]
        return self._indices

    @property
    def intrinsics(self) -> Intrinsics:
        """The frames' intrinsics: a pinhole camera (a calibration's distortion and skew are undistorted away
        in ``__getitem__``), downsampled."""
        return self.raw_intrinsics.undistorted().downsampled(self.downsample)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Frame:
        frame = self._load_raw(self.indices[i])
        frame.color_registered = frame.color is not None and self.color_for_tracking
        if not frame.intrinsics.pinhole:  # at full resolution, before downsampling
            from ti_fusion.io.datasets.undistort import undistort

            frame.depth, frame.color, frame.intrinsics = undistort(frame.depth, frame.color, frame.intrinsics)
        f = self.downsample
        if f > 1:
            frame.depth = np.ascontiguousarray(frame.depth[::f, ::f])
            if frame.color is not None:
                frame.color = np.ascontiguousarray(frame.color[::f, ::f])
            frame.intrinsics = frame.intrinsics.downsampled(f)
        return frame

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def frame_by_raw_index(self, raw_index: int) -> Frame:
        """The frame with dataset index ``raw_index`` (as in ``--source 10``), ignoring the stride.

        IndexError when there is no such frame: a negative index is not counted from the end.
        """
        if raw_index < 0 or raw_index >= self._num_raw_frames():
            raise IndexError(raw_index)
        saved = self._indices
        self._indices = [raw_index]
        try:
            return self[0]
        finally:
            self._indices = saved

    def check_selection(self) -> None:
        """InputError when the selection holds no frame or ``downsample`` leaves frames too small to use; a
        note when it asks for frames past the end."""
        start, stop, stride = self._selection
        n = self._num_raw_frames()
        if not self.indices:
            synthetic = self.format == "synthetic"
            stop_text = f", stop {stop}" if stop is not None else ""
            raise InputError(None if synthetic else self.root,
                             f"no frames selected: the {'synthetic ' * synthetic}sequence has {n} frame"
                             f"{'s' * (n != 1)} (0 to {n - 1}), and start {start}{stop_text}, stride {stride} "
                             "select none")
        if stop is not None and stop > n:
            self.note(f"the selection runs to frame {stop - 1}, the sequence ends at frame {n - 1}: "
                      f"{len(self.indices)} frames are taken")
        K, f = self.raw_intrinsics, self.downsample
        small = K.downsampled(f)
        if min(small.width, small.height) < MIN_FRAME_SIZE:
            most = (min(K.width, K.height) - 1) // (MIN_FRAME_SIZE - 1)  # ceil(side / f) >= MIN_FRAME_SIZE
            raise InputError(None, f"--downsample {f} turns the {K.width}x{K.height} frames into {small.width}x"
                                   f"{small.height}: at least {MIN_FRAME_SIZE} pixels per side are needed, so "
                                   f"at most --downsample {max(most, 1)}")

    def note(self, message: str) -> None:
        """Record something the user must know about the frames (a reordering, dropped frames) and warn."""
        self.notes.append(message)
        log.warning("%s: %s", self.root, message)

    def describe_format(self) -> str:
        """One line: the format and how it was chosen, the depth scale, the intrinsics and their source."""
        K = self.raw_intrinsics
        scale = f"depth {self.depth_scale:g} units per metre; " if self.depth_scale else ""
        return (f"format: {self.format} ({self.format_from}); {scale}intrinsics fx {K.fx:g} fy {K.fy:g} "
                f"cx {K.cx:g} cy {K.cy:g} at {K.width}x{K.height} ({self.intrinsics_source}){_lens(K)}")

    def describe(self) -> dict:
        K = self.intrinsics
        raw = self.raw_intrinsics
        return {
            "name": self.name,
            "format": self.format,
            "format_from": self.format_from,
            "root": str(self.root),
            "frames": None if self.endless else len(self),  # None: until Ctrl-C
            "width": K.width,
            "height": K.height,
            "downsample": self.downsample,
            "depth_scale": self.depth_scale,
            "intrinsics": {"fx": raw.fx, "fy": raw.fy, "cx": raw.cx, "cy": raw.cy, "width": raw.width,
                           "height": raw.height, "source": self.intrinsics_source,
                           **({} if raw.pinhole else {"skew": raw.skew, "distortion": list(raw.distortion),
                                                      "distortion_model": raw.distortion_model,
                                                      "undistorted": True})},
            "ground_truth": self.has_ground_truth,
            "color_for_tracking": self.color_for_tracking,
            "dropped_frames": self.dropped_frames,
            "notes": list(self.notes),
        }


def _lens(K: Intrinsics) -> str:
    """What the format line adds for a calibration that is not a plain pinhole camera."""
    if K.pinhole:
        return ""
    parts = ([f"skew {K.skew:g}"] if K.skew else []) + \
        ([f"{K.distortion_model} distortion [{', '.join(f'{d:g}' for d in K.distortion)}]"] if K.distortion else [])
    return f"; {' and '.join(parts)}: every frame is undistorted to the pinhole camera"


class RecordedSequence(Dataset):
    """A recorded sequence: a subclass sets ``_intrinsics`` and ``_gt_poses`` (one 4×4 or None per raw
    frame); the intrinsics, the ground-truth questions and the frame's assembly are answered here once."""

    @property
    def raw_intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def has_ground_truth(self) -> bool:
        return any(T is not None for T in self._gt_poses)

    def ground_truth_frames(self) -> int:
        """How many of the selected frames have a ground-truth pose."""
        return sum(self._gt_poses[i] is not None for i in self.indices)

    def _frame(self, raw_index: int, timestamp: float, depth: np.ndarray, color, meta: dict) -> Frame:
        gt = self._gt_poses[raw_index]
        return Frame(index=raw_index, timestamp=timestamp, depth=depth, intrinsics=self._intrinsics, color=color,
                     gt_pose=None if gt is None else gt.copy(), meta=meta)


class ImageFileDataset(RecordedSequence):
    """A sequence stored as one depth image (and optionally one colour image) per frame.

    A subclass's ``__init__`` fills, one entry per frame: ``_depth_files``, ``_color_files`` (None where a
    frame has no colour), ``_stamps`` (float timestamps), ``_gt_poses`` (4×4 or None), and sets
    ``_intrinsics`` and ``config``; the class attributes give the depth PNG's units per metre and the raw
    values that mean "no depth".
    """

    depth_scale: float = 1000.0
    invalid_depth: tuple[int, ...] = (0,)
    concurrent_reads = True  # every frame is files of its own
    reads_in_process = True

    def __init__(self, root, config=None, downsample: int = 1, start: int = 0, stop: int | None = None,
                 stride: int = 1):
        from ti_fusion.config import DatasetConfig

        super().__init__(root, downsample=downsample, start=start, stop=stop, stride=stride)
        self.config = config or DatasetConfig()
        self.name = self.root.name
        if not self.root.is_dir():
            raise InputError(self.root, "dataset folder does not exist")

    def _num_raw_frames(self) -> int:
        return len(self._depth_files)

    def _load_raw(self, raw_index: int) -> Frame:
        from ti_fusion.io.datasets.imageio import read_rgbd

        depth_path, color_path = self._depth_files[raw_index], self._color_files[raw_index]
        K = self._intrinsics
        depth, color = read_rgbd(depth_path, color_path, self.depth_scale, self.config.depth_max,
                                 (K.width, K.height), self.invalid_depth)
        return self._frame(raw_index, float(self._stamps[raw_index]), depth, color,
                           {"depth_file": str(depth_path), "color_file": str(color_path) if color_path else None})

    def describe(self) -> dict:
        info = super().describe()
        info["ground_truth_frames"] = self.ground_truth_frames()
        info["color"] = any(c is not None for c in self._color_files)
        return info

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps, camera-to-world poses N×4×4) of the selected frames that have ground truth."""
        keep = [i for i in self.indices if self._gt_poses[i] is not None]
        stamps = np.array([self._stamps[i] for i in keep], dtype=np.float64)
        return stamps, np.array([self._gt_poses[i] for i in keep]).reshape(-1, 4, 4)
