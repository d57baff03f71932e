"""TUM RGB-D benchmark sequences (``rgbd_dataset_freiburg*``).

Layout: ``depth.txt`` and ``rgb.txt`` list "timestamp filename" per image, ``groundtruth.txt`` holds
the motion-capture trajectory "timestamp tx ty tz qx qy qz qw" (camera-to-world, ~100 Hz). Depth PNGs
are 16-bit with 5000 units per metre.

- Frames are the depth images, in time order: a ``depth.txt`` listed out of order is sorted by
  timestamp (and a note says so); a timestamp listed twice is refused.
- Each depth image is paired with the rgb image found by TUM's associate.py rule (greedy by smallest
  time difference, at most ``DatasetConfig.max_time_difference`` = 0.02 s). A depth image with no rgb
  partner in time is left out, as associate.py leaves it out, and a note says how many and which
  (``describe()["dropped_frames"]``): in the benchmark's sequences a few frames at either end have
  none. A file that a list names but that does not exist stops the loader (``InputError``), as a
  missing file does in every format. Without ``rgb.txt`` the sequence is depth-only (colour None).
- The frame timestamp is the depth timestamp.
- Ground truth is INTERPOLATED at the depth timestamp: linear in translation, slerp in rotation,
  between the two motion-capture samples around it when both lie within the tolerance of it;
  otherwise the nearest sample within the tolerance; otherwise the frame has no ground truth (None).
- Intrinsics, first match wins: ``DatasetConfig.intrinsics_file``; ``intrinsics.txt`` in the folder
  ("fx fy cx cy" or a 3×3 K); the freiburg1/2/3 calibration named by the folder name; else the
  ROS default 525, 525, 319.5, 239.5, with a warning (it is a guess). Image size from the first depth
  image. ``describe()`` and the CLI's ``format:`` line say which one is in use.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, so3_exp, so3_log
from ti_fusion.io.trajectory import associate, read_tum
from ti_fusion.io.datasets.base import ImageFileDataset
from ti_fusion.io.datasets.imageio import parse_floats, read_depth_png, read_intrinsics_file, read_table

DEPTH_SCALE = 5000.0

# (fx, fy, cx, cy) of the TUM benchmark's per-camera calibrations.
FREIBURG_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)


def freiburg_camera(name: str) -> str | None:
    """"freiburg1" etc. when a folder name says which TUM camera recorded it ("freiburg2", "fr3_...")."""
    m = re.search(r"(?<![a-z])(?:freiburg|fr)([123])(?![0-9])", name.lower())
    return f"freiburg{m.group(1)}" if m else None


def read_image_list(path: Path) -> tuple[np.ndarray, list[Path], list[int]]:
    """(timestamps, files, line numbers) of a TUM "timestamp filename" list, in file order; every listed
    file must exist."""
    stamps, files, lines = [], [], []
    for lineno, fields in read_table(path, path.name):
        if len(fields) < 2:
            raise InputError(path, f"line {lineno}: expected 'timestamp filename'")
        stamps.append(parse_floats(fields[:1], path, lineno)[0])
        file = path.parent / fields[1]
        if not file.is_file():
            raise InputError(file, f"image listed in {path.name} (line {lineno}) does not exist")
        files.append(file)
        lines.append(lineno)
    return np.asarray(stamps, dtype=np.float64), files, lines


def time_order(path: Path, stamps: np.ndarray, lines: list[int]) -> np.ndarray | None:
    """The order that sorts a list's ``stamps``, or None when they are already increasing; a timestamp
    listed twice is refused (two images of one instant: which one is the frame?)."""
    order = np.argsort(stamps, kind="stable")
    repeated = np.flatnonzero(np.diff(stamps[order]) == 0)
    if len(repeated):
        a, b = order[repeated[0]], order[repeated[0] + 1]
        raise InputError(path, f"timestamp {stamps[a]:.6f} is listed twice (lines {lines[a]} and {lines[b]})")
    return None if np.all(np.diff(stamps) > 0) else order


def interpolate_pose(stamps: np.ndarray, poses: np.ndarray, t: float, tolerance: float) -> np.ndarray | None:
    """The pose at time ``t`` from a sorted trajectory: interpolated (slerp) between the samples around
    ``t`` when both are within ``tolerance``, else the nearest sample within it, else None."""
    k = int(np.searchsorted(stamps, t, side="left"))
    if k < len(stamps) and stamps[k] == t:
        return poses[k].copy()
    before, after = k - 1, k
    ok_before = before >= 0 and t - stamps[before] <= tolerance
    ok_after = after < len(stamps) and stamps[after] - t <= tolerance
    if ok_before and ok_after:
        s = (t - stamps[before]) / (stamps[after] - stamps[before])
        T0, T1 = poses[before], poses[after]
        R = T0[:3, :3] @ so3_exp(s * so3_log(T0[:3, :3].T @ T1[:3, :3]))
        return make_pose(R, (1.0 - s) * T0[:3, 3] + s * T1[:3, 3])
    if ok_before or ok_after:
        nearest = before if not ok_after or (ok_before and t - stamps[before] <= stamps[after] - t) else after
        return poses[nearest].copy()
    return None


class TUMDataset(ImageFileDataset):
    """A TUM RGB-D sequence folder (see the module docstring for association, ground truth, intrinsics)."""

    format = "tum"
    identified_by = "TUM (depth.txt)"
    replaceable_calibration = True
    reads = frozenset({"intrinsics", "depth_scale"})
    color_registered = True  # the TUM tools register depth to colour

    depth_scale = DEPTH_SCALE

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, config, downsample, start, stop, stride)
        tolerance = self.config.max_time_difference

        depth_list = self.root / "depth.txt"
        depth_stamps, depth_files, lines = read_image_list(depth_list)
        if not depth_files:
            raise InputError(depth_list, "empty sequence: no depth images listed")
        order = time_order(depth_list, depth_stamps, lines)
        if order is not None:
            depth_stamps, depth_files = depth_stamps[order], [depth_files[i] for i in order]
            self.note(f"depth.txt lists its {len(order)} images out of time order: they are taken in "
                      "timestamp order")
        self._color_files: list[Path | None]
        if (self.root / "rgb.txt").is_file():
            rgb_stamps, rgb_files, _ = read_image_list(self.root / "rgb.txt")
            i_depth, i_rgb = associate(depth_stamps, rgb_stamps, tolerance)
            if len(i_depth) == 0:
                raise InputError(self.root / "rgb.txt",
                                 f"empty sequence: no rgb image within {tolerance} s of any depth image")
            self._color_files = [rgb_files[j] for j in i_rgb]
            self._note_unpaired(depth_stamps, depth_files, i_depth, tolerance)
        else:
            i_depth = np.arange(len(depth_files))
            self._color_files = [None] * len(depth_files)
        self._depth_files = [depth_files[i] for i in i_depth]
        self._stamps = depth_stamps[i_depth]

        self._gt_poses: list[np.ndarray | None] = [None] * len(self._stamps)
        gt_path = self.root / "groundtruth.txt"
        if gt_path.is_file():
            gt_stamps, gt_poses = read_tum(gt_path)
            order = np.argsort(gt_stamps, kind="stable")
            gt_stamps, gt_poses = gt_stamps[order], gt_poses[order]
            self._gt_poses = [interpolate_pose(gt_stamps, gt_poses, t, tolerance) for t in self._stamps]

        height, width = read_depth_png(self._depth_files[0]).shape
        self._intrinsics = self._find_intrinsics(width, height)

    def _note_unpaired(self, stamps: np.ndarray, files: list[Path], paired: np.ndarray, tolerance: float) -> None:
        unpaired = np.setdiff1d(np.arange(len(files)), paired)
        if len(unpaired):
            self.dropped_frames = len(unpaired)
            shown = ", ".join(f"{stamps[i]:.6f}" for i in unpaired[:5]) + (", ..." if len(unpaired) > 5 else "")
            self.note(f"{len(unpaired)} of {len(files)} depth images have no rgb image within {tolerance:g} s "
                      f"and are left out (timestamps {shown})")

    def _find_intrinsics(self, width: int, height: int) -> Intrinsics:
        if self.config.intrinsics_file:
            self.intrinsics_source = f"{self.config.intrinsics_file} (dataset.intrinsics_file)"
            return read_intrinsics_file(self.config.intrinsics_file, width, height)
        if (self.root / "intrinsics.txt").is_file():
            self.intrinsics_source = "intrinsics.txt in the dataset folder"
            return read_intrinsics_file(self.root / "intrinsics.txt", width, height)
        camera = freiburg_camera(self.root.resolve().name)
        if camera:
            self.intrinsics_source = f"the TUM {camera} calibration, named by the folder name"
            return Intrinsics(*FREIBURG_INTRINSICS[camera], width, height)
        self.intrinsics_source = "the ROS default: a guess"
        self.note("no intrinsics.txt and no freiburg1/2/3 in the folder name: the intrinsics are the ROS default "
                  f"{', '.join(f'{v:g}' for v in DEFAULT_INTRINSICS)} (give the camera's with intrinsics.txt "
                  "in the folder or --set dataset.intrinsics_file=FILE)")
        return Intrinsics(*DEFAULT_INTRINSICS, width, height)

    @staticmethod
    def detect(root: Path) -> str | None:
        """The file that identifies a TUM folder (its depth list), or None."""
        return "depth.txt" if (Path(root) / "depth.txt").is_file() else None
