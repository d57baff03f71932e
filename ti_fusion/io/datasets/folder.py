"""A plain RGB-D folder (``--format folder``): numbered depth images as a RealSense, an Azure Kinect or
one's own recorder writes them.

Layout::

    depth/            numbered 16-bit PNGs: 0.png, 000123.png, frame_000123.png (the number that ends the
                      name), taken in numeric order
    rgb/ or color/    optional colour images (PNG or JPEG) with the same names (numbers) as the depth images
    timestamps.txt    optional: one time in seconds per frame, in frame order; or "N t" lines that give
                      frame N's time t
    groundtruth.txt   optional ground truth in TUM format ("t tx ty tz qx qy qz qw", camera-to-world);
    or poses.tum      its times are the frames' times, or the frame numbers when there is no timestamps.txt
    camera.yaml or    optional intrinsics (a ROS camera_info or OpenCV calibration YAML; "fx fy cx cy"
    intrinsics.txt    or a 3×3 K)

The files do not say what their depth units are, nor which camera took them, so the user does:

- ``--depth-scale UNITS_PER_METRE`` (``dataset.depth_scale``), always: 1000 for millimetres (RealSense,
  Azure Kinect), 5000 for TUM's convention. A folder without it is refused.
- ``--intrinsics fx,fy,cx,cy`` or ``--intrinsics FILE`` (``dataset.intrinsics``); else ``camera.yaml``,
  else ``intrinsics.txt`` in the folder (``describe()`` names the one used); else refused.

Frames and times: a frame's timestamp is its line of ``timestamps.txt``, else its number. Ground truth
(``dataset.ground_truth``, else ``groundtruth.txt`` or ``poses.tum`` in the folder) is interpolated at
the frame's timestamp as TUM's is (within ``dataset.max_time_difference``): with frame numbers as times,
that is the line of the same number. A frame outside the ground truth has none.

Colour: an image of the depth image's size is taken as registered to it (pixel (u, v) of both sees the
same point: the case after a RealSense's ``align_to`` or an Azure Kinect's transformation). One of
another size cannot be: it is resized to the depth image's size for the map's colours only, and
``describe()`` and a note say that it is not registered. When some frames have colour, every frame
needs its own.

Never auto-detected: numbered PNGs in ``depth/`` are also ICL-NUIM's layout, and nothing in them tells
the units (millimetres read as ICL-NUIM's fifths of a millimetre come out five times too near).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Frame, ImageFileDataset
from ti_fusion.io.datasets.imageio import (depth_to_metres, parse_floats, parse_intrinsics, read_color,
                                           read_depth_png, read_intrinsics_file, read_table)

COLOR_FOLDERS = ("rgb", "color", "colour")
COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
GROUND_TRUTH_FILES = ("groundtruth.txt", "poses.tum")
INTRINSICS_FILES = ("camera.yaml", "intrinsics.txt")

_NUMBERED = re.compile(r"(\d+)$")


def numbered_images(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """{N: file} for the files of ``folder`` whose name (without suffix) ends in the number N; two files
    of one number are refused."""
    found: dict[int, Path] = {}
    for path in sorted(folder.iterdir()):
        m = _NUMBERED.search(path.stem)
        if path.suffix.lower() not in suffixes or not m or not path.is_file():
            continue
        n = int(m.group(1))
        if n in found:
            raise InputError(folder, f"{found[n].name} and {path.name} both have frame number {n}: keep one")
        found[n] = path
    return found


class FolderDataset(ImageFileDataset):
    """A plain RGB-D folder (see the module docstring for the layout and what the user states)."""

    format = "folder"
    reads = frozenset({"intrinsics", "depth_scale", "ground_truth"})

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, config, downsample, start, stop, stride)
        cfg = self.config
        depth_dir = self.root / "depth"
        if not depth_dir.is_dir():
            raise InputError(depth_dir, "depth folder does not exist (a plain folder holds depth/ with numbered "
                                        "16-bit PNGs)")
        depth = numbered_images(depth_dir, (".png",))
        if not depth:
            raise InputError(depth_dir, "empty sequence: no numbered 16-bit PNGs (e.g. 000000.png)")
        self._numbers = sorted(depth)
        self._depth_files = [depth[n] for n in self._numbers]
        self._color_files = self._find_color()
        self._stamps = self._read_timestamps()

        missing = self._missing_options()
        if missing:
            raise InputError(self.root, missing)
        self.depth_scale = float(cfg.depth_scale)
        self.depth_scale_source = "--depth-scale / dataset.depth_scale"

        self._gt_poses = self._read_ground_truth()
        height, width = read_depth_png(self._depth_files[0]).shape
        self._intrinsics = self._find_intrinsics(width, height)
        self.color_registered = self._check_color_size(width, height)

    # -- what the user states -------------------------------------------------------------------
    def _intrinsics_file(self) -> Path | None:
        return next((self.root / n for n in INTRINSICS_FILES if (self.root / n).is_file()), None)

    def _missing_options(self) -> str | None:
        """The line that asks for what the folder cannot say (its depth units, its camera), or None."""
        cfg, what, options = self.config, [], []
        if not cfg.depth_scale or cfg.depth_scale <= 0:
            what.append("its depth units")
            options.append("--depth-scale UNITS_PER_METRE (1000 for millimetres, as a RealSense or an Azure "
                           "Kinect writes them; 5000 for TUM's)")
        if not cfg.intrinsics and not cfg.intrinsics_file and self._intrinsics_file() is None:
            what.append("its camera's intrinsics")
            options.append(f"--intrinsics fx,fy,cx,cy or --intrinsics FILE (or put {' or '.join(INTRINSICS_FILES)} "
                           "in the folder)")
        if not what:
            return None
        return f"a plain folder does not say {' nor '.join(what)}: pass {' and '.join(options)}"

    def _find_intrinsics(self, width: int, height: int):
        cfg = self.config
        if cfg.intrinsics:
            self.intrinsics_source = f"{_spec_text(cfg.intrinsics)} (--intrinsics / dataset.intrinsics)"
            return parse_intrinsics(cfg.intrinsics, width, height)
        if cfg.intrinsics_file:
            self.intrinsics_source = f"{cfg.intrinsics_file} (dataset.intrinsics_file)"
            return read_intrinsics_file(cfg.intrinsics_file, width, height)
        path = self._intrinsics_file()
        self.intrinsics_source = f"{path.name} in the dataset folder"
        return read_intrinsics_file(path, width, height)

    # -- the folder's own files -----------------------------------------------------------------
    def _find_color(self) -> list[Path | None]:
        folders = [self.root / n for n in COLOR_FOLDERS if (self.root / n).is_dir()]
        if len(folders) > 1:
            raise InputError(self.root, f"holds {' and '.join(f.name + '/' for f in folders)}: keep one colour folder")
        if not folders:
            return [None] * len(self._numbers)
        folder = folders[0]
        by_number = numbered_images(folder, COLOR_SUFFIXES)
        if not by_number:
            return [None] * len(self._numbers)
        files = [by_number.get(n) for n in self._numbers]
        missing = [p for p, c in zip(self._depth_files, files) if c is None]
        if missing:
            more = f" ({len(missing)} depth images have none)" if len(missing) > 1 else ""
            raise InputError(folder / (missing[0].stem + ".png"),
                             f"colour image of depth/{missing[0].name} does not exist (a .png or .jpg of the "
                             f"same number), while other frames have one{more}")
        return files

    def _read_timestamps(self) -> list[float]:
        path = self.root / "timestamps.txt"
        if not path.is_file():
            self.timestamps_from = "the frame numbers (no timestamps.txt)"
            return [float(n) for n in self._numbers]
        self.timestamps_from = "timestamps.txt"
        rows = read_table(path, "timestamps file")
        widths = {len(fields) for _, fields in rows}
        if widths == {1}:
            if len(rows) != len(self._numbers):
                raise InputError(path, f"{len(rows)} timestamps for {len(self._numbers)} depth images (one time "
                                       "per frame, in frame order; or 'N t' lines)")
            stamps = [parse_floats(fields, path, lineno)[0] for lineno, fields in rows]
            lines = [lineno for lineno, _ in rows]
        elif widths == {2}:
            by_number = {}
            for lineno, (name, value) in rows:
                m = _NUMBERED.search(Path(name).stem)
                if not m:
                    raise InputError(path, f"line {lineno}: expected 'N t' (frame number, time), got {name!r}")
                by_number[int(m.group(1))] = (parse_floats([value], path, lineno)[0], lineno)
            absent = [n for n in self._numbers if n not in by_number]
            if absent:
                raise InputError(path, f"no time for frame {absent[0]}" + (f" ({len(absent)} frames have none)"
                                                                           if len(absent) > 1 else ""))
            stamps = [by_number[n][0] for n in self._numbers]
            lines = [by_number[n][1] for n in self._numbers]
        else:
            raise InputError(path, "expected one time per line, or 'N t' lines (frame number, time)")
        for k in range(1, len(stamps)):
            if stamps[k] <= stamps[k - 1]:
                raise InputError(path, f"line {lines[k]}: time {stamps[k]:.6f} of frame {self._numbers[k]} is not "
                                       f"after {stamps[k - 1]:.6f} of frame {self._numbers[k - 1]}")
        return stamps

    def _read_ground_truth(self) -> list[np.ndarray | None]:
        from ti_fusion.io.datasets.tum import interpolate_pose
        from ti_fusion.io.trajectory import read_tum

        if self.config.ground_truth:
            path = Path(self.config.ground_truth)
            self.ground_truth_source = f"{path} (dataset.ground_truth)"
        else:
            found = [self.root / n for n in GROUND_TRUTH_FILES if (self.root / n).is_file()]
            if len(found) > 1:
                raise InputError(self.root, f"holds {' and '.join(p.name for p in found)}: keep one ground truth")
            if not found:
                self.ground_truth_source = None
                return [None] * len(self._numbers)
            path = found[0]
            self.ground_truth_source = f"{path.name} in the dataset folder"
        stamps, poses = read_tum(path)
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        tolerance = self.config.max_time_difference
        gt = [interpolate_pose(stamps, poses, t, tolerance) for t in self._stamps]
        if all(T is None for T in gt):
            raise InputError(path, f"no pose within {tolerance:g} s of any frame's time ({self.timestamps_from}: "
                                   f"{self._stamps[0]:.6f} to {self._stamps[-1]:.6f}; the file: {stamps[0]:.6f} to "
                                   f"{stamps[-1]:.6f})")
        matched = sum(T is not None for T in gt)
        if 2 * matched < len(gt):  # a few matches on two clocks are chance, not ground truth
            span = (f"{self.timestamps_from}: {self._stamps[0]:.6f} to {self._stamps[-1]:.6f}; the file: "
                    f"{stamps[0]:.6f} to {stamps[-1]:.6f}")
            if not self._has_timestamps_file():
                raise InputError(path, f"only {matched} of {len(gt)} frames have a pose within {tolerance:g} s of "
                                       f"their time ({span}): without timestamps.txt a frame's time is its number, "
                                       "so these match by chance; add timestamps.txt (one time per frame, on the "
                                       "ground truth's clock), or give poses by frame number")
            self.note(f"only {matched} of {len(gt)} frames have a ground-truth pose within {tolerance:g} s of their "
                      f"time ({span}): no ATE is given over fewer than half")
        return gt

    def _has_timestamps_file(self) -> bool:
        return self.timestamps_from == "timestamps.txt"

    def _check_color_size(self, width: int, height: int) -> bool | None:
        """True when the colour images are the depth images' size (taken as registered), False when not
        (then a note), None without colour."""
        first = next((c for c in self._color_files if c is not None), None)
        if first is None:
            return None
        h, w = read_color(first).shape[:2]
        if (w, h) == (width, height):
            return True
        self.note(f"the colour images are {w}x{h} and the depth images {width}x{height}: colour is not registered "
                  "to depth, so it is resized to the depth images' size and only colours the map")
        return False

    @property
    def color_for_tracking(self) -> bool:
        # a colour image of the depth's size may still be unregistered (a raw Kinect's): the user's word
        return bool(self.color_registered) and self.config.color_registered

    # -- frames ---------------------------------------------------------------------------------
    def _load_raw(self, raw_index: int) -> Frame:
        depth_path, color_path = self._depth_files[raw_index], self._color_files[raw_index]
        K = self._intrinsics
        raw = read_depth_png(depth_path)
        if raw.shape != (K.height, K.width):
            raise InputError(depth_path, f"depth image is {raw.shape[1]}x{raw.shape[0]}, "
                                         f"the sequence's first is {K.width}x{K.height}")
        depth = depth_to_metres(raw, self.depth_scale, self.config.depth_max, self.invalid_depth)
        color = None
        if color_path is not None:
            color = read_color(color_path)
            if color.shape[:2] != raw.shape:
                if self.color_registered:
                    raise InputError(color_path, f"colour image is {color.shape[1]}x{color.shape[0]}, the "
                                                 f"depth images and the first colour image {K.width}x{K.height}")
                if getattr(self, "color_camera", None) is None:  # else registered at full size in the run loop
                    color = cv2.resize(color, (K.width, K.height), interpolation=cv2.INTER_AREA)
        return self._frame(raw_index, float(self._stamps[raw_index]), depth, color,
                           {"depth_file": str(depth_path), "color_file": str(color_path) if color_path else None})

    def describe(self) -> dict:
        info = super().describe()
        info.update(depth_scale_from=self.depth_scale_source, timestamps_from=self.timestamps_from,
                    ground_truth_from=self.ground_truth_source, color_registered=self.color_registered)
        return info


def _spec_text(spec) -> str:
    return ",".join(str(v) for v in spec) if isinstance(spec, (list, tuple)) else " ".join(str(spec).split())
