"""Microsoft 7-Scenes sequences (one ``seq-XX`` folder, or the shared redkitchen-7scenes folder).

Layout: ``frame-XXXXXX.depth.png`` (16-bit, millimetres; 0 and 65535 invalid),
``frame-XXXXXX.color.png`` or ``.color.jpg``, ``frame-XXXXXX.pose.txt`` (4×4 camera-to-world, metres).

- 7-Scenes has no timestamps: the timestamp of frame-XXXXXX is the number XXXXXX, as in the shared
  ``groundtruth_tum.txt``, so written trajectories compare directly with that file.
- Pose rotations are slightly non-orthonormal in the release (det 0.9995..0.9999): each is checked
  to be rigid within tolerance (``geometry.rigidity_error``) and then projected onto SO(3).
- Intrinsics: ``DatasetConfig.intrinsics_file``, else ``camera-intrinsics.txt`` (3×3 K), else the
  nominal 585, 585, 320, 240.
- Colour is NOT registered to depth (a different camera, uncalibrated against depth): use depth for
  geometry and tracking, colour only for display or, with that caveat, for features.
- Missing files: a folder without any colour image is depth-only (colour None). When some frames have
  colour, a frame whose colour image is missing stops the loader (``InputError`` naming the file), as a
  missing file does in every format, rather than passing silently as a frame without colour. A frame
  without a pose file keeps its depth and has no ground truth. No frame is dropped
  (``describe()["dropped_frames"]`` is 0).
"""

from __future__ import annotations

import re
from pathlib import Path


from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import ImageFileDataset
from ti_fusion.io.datasets.imageio import read_depth_png, read_intrinsics_file, read_pose_matrix

DEPTH_SCALE = 1000.0
INVALID_DEPTH = (0, 65535)
DEFAULT_INTRINSICS = (585.0, 585.0, 320.0, 240.0)

_DEPTH_NAME = re.compile(r"^frame-(\d+)\.depth\.png$")


class SevenScenesDataset(ImageFileDataset):
    """A 7-Scenes sequence folder (see the module docstring for conventions)."""

    format = "7scenes"
    identified_by = "7-Scenes (frame-XXXXXX.depth.png)"
    replaceable_calibration = True
    reads = frozenset({"intrinsics", "depth_scale"})
    color_registered = False  # the dataset says so: its colour and depth cameras are not calibrated together

    depth_scale = DEPTH_SCALE
    invalid_depth = INVALID_DEPTH

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, config, downsample, start, stop, stride)
        numbered = {}
        for path in self.root.glob("frame-*.depth.png"):
            m = _DEPTH_NAME.match(path.name)
            if m:
                numbered[int(m.group(1))] = path
        if not numbered:
            raise InputError(self.root, "empty sequence: no frame-XXXXXX.depth.png files")
        self._numbers = sorted(numbered)
        self._depth_files = [numbered[n] for n in self._numbers]
        self._stamps = [float(n) for n in self._numbers]  # frame numbers are the timestamps
        self._color_files = [self._color_file(p) for p in self._depth_files]
        missing = [p for p, c in zip(self._depth_files, self._color_files) if c is None]
        if missing and len(missing) < len(self._depth_files):
            name = missing[0].name.replace(".depth.png", ".color.png")
            more = f" ({len(missing)} frames have none)" if len(missing) > 1 else ""
            raise InputError(self.root / name, f"colour image of {missing[0].name} does not exist (neither .png "
                                               f"nor .jpg), while other frames have one{more}")
        # Poses are small text files: read and check them all now, so a bad one fails on opening.
        self._gt_poses = []
        for p in self._depth_files:
            pose_path = p.with_name(p.name.replace(".depth.png", ".pose.txt"))
            self._gt_poses.append(read_pose_matrix(pose_path) if pose_path.is_file() else None)

        height, width = read_depth_png(self._depth_files[0]).shape
        if self.config.intrinsics_file:
            self.intrinsics_source = f"{self.config.intrinsics_file} (dataset.intrinsics_file)"
            self._intrinsics = read_intrinsics_file(self.config.intrinsics_file, width, height)
        elif (self.root / "camera-intrinsics.txt").is_file():
            self.intrinsics_source = "camera-intrinsics.txt in the dataset folder"
            self._intrinsics = read_intrinsics_file(self.root / "camera-intrinsics.txt", width, height)
        else:
            self.intrinsics_source = "7-Scenes' published nominal intrinsics"
            self._intrinsics = Intrinsics(*DEFAULT_INTRINSICS, width, height)

    @staticmethod
    def _color_file(depth_path: Path) -> Path | None:
        for suffix in (".color.png", ".color.jpg"):
            path = depth_path.with_name(depth_path.name.replace(".depth.png", suffix))
            if path.is_file():
                return path
        return None

    @staticmethod
    def detect(root: Path) -> str | None:
        """The files that identify a 7-Scenes folder (``frame-XXXXXX.depth.png``), or None."""
        found = min((p.name for p in Path(root).glob("frame-*.depth.png") if _DEPTH_NAME.match(p.name)), default=None)
        return f"{found} files" if found else None
