"""ICL-NUIM in its TUM-compatible release (the ``living_room_trajN_frei_png`` folders).

Layout: ``rgb/N.png`` and ``depth/N.png`` for frame numbers N = 0, 1, ...; 16-bit depth with 5000
units per metre; the ground truth ``livingRoomN.gt.freiburg`` (or ``groundtruth.txt``) holds
"i tx ty tz qx qy qz qw" lines whose "timestamp" i is the frame number. The timestamp of frame N is N,
so a written trajectory compares directly with the .gt.freiburg file. Frame 0 has no ground-truth
line in the original release (its gt_pose is None).

Intrinsics: fx 481.20, fy 480.0, cx 319.5, cy 239.5. The original POV-Ray renders use fy = −480.0
(y up in the image); the TUM-compatible PNGs and the .gt.freiburg poses are given for the flipped,
y-down camera, so fy = +480.0 and the poses are used as they are (camera-to-world, x right, y down,
z forward). ``DatasetConfig.intrinsics_file`` overrides the intrinsics.

Detection: only the ``*.gt.freiburg`` file identifies a folder as ICL-NUIM. ``rgb/N.png`` and
``depth/N.png`` alone are the layout of many recordings whose depth is not in ICL-NUIM's units (a
RealSense's millimetres read at 5000 units per metre come out 5 times too near), so such a folder is
read as ICL-NUIM only when ``--format iclnuim`` says so.

Missing files: when ``rgb/`` holds colour images, every depth image needs its own; one that is missing
stops the loader (``InputError``), as in every format, rather than leaving a frame without colour or
out of the sequence. No frame is dropped (``describe()["dropped_frames"]`` is 0).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.trajectory import read_tum
from ti_fusion.io.datasets.base import ImageFileDataset
from ti_fusion.io.datasets.imageio import read_depth_png, read_intrinsics_file

DEPTH_SCALE = 5000.0
ICL_INTRINSICS = (481.20, 480.0, 319.5, 239.5)  # fy after the y flip (−480.0 in the original renders)

_NUMBERED_PNG = re.compile(r"^(\d+)\.png$")


def numbered_pngs(folder: Path) -> dict[int, Path]:
    """{N: folder/N.png} for the integer-named PNGs of a folder."""
    if not folder.is_dir():
        return {}
    found = {}
    for path in folder.iterdir():
        m = _NUMBERED_PNG.match(path.name)
        if m:
            found[int(m.group(1))] = path
    return found


def _ground_truth_file(root: Path) -> Path | None:
    candidates = sorted(root.glob("*.gt.freiburg"))
    if len(candidates) > 1:
        raise InputError(root, f"several ground-truth files ({', '.join(p.name for p in candidates)}): keep one")
    if candidates:
        return candidates[0]
    return root / "groundtruth.txt" if (root / "groundtruth.txt").is_file() else None


class ICLNUIMDataset(ImageFileDataset):
    """An ICL-NUIM sequence in TUM layout (see the module docstring for conventions)."""

    format = "iclnuim"
    identified_by = "ICL-NUIM (*.gt.freiburg)"
    replaceable_calibration = True
    reads = frozenset({"intrinsics", "depth_scale"})
    color_registered = True  # rendered: colour and depth from the same camera

    depth_scale = DEPTH_SCALE

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, config, downsample, start, stop, stride)
        depth_dir, rgb_dir = self.root / "depth", self.root / "rgb"
        if not depth_dir.is_dir():
            raise InputError(depth_dir, "depth folder does not exist")
        depth = numbered_pngs(depth_dir)
        if not depth:
            raise InputError(depth_dir, "empty sequence: no numbered depth images (N.png)")
        self._numbers = sorted(depth)
        self._depth_files = [depth[n] for n in self._numbers]
        self._stamps = [float(n) for n in self._numbers]  # frame numbers are the timestamps

        color = numbered_pngs(rgb_dir)
        self._color_files: list[Path | None] = [None] * len(self._numbers)
        if color:
            for k, n in enumerate(self._numbers):
                if n not in color:
                    raise InputError(rgb_dir / f"{n}.png", f"colour image for depth/{n}.png does not exist")
                self._color_files[k] = color[n]

        self._gt_poses: list[np.ndarray | None] = [None] * len(self._numbers)
        gt_path = _ground_truth_file(self.root)
        if gt_path is not None:
            stamps, poses = read_tum(gt_path)
            by_number = {int(round(t)): T for t, T in zip(stamps, poses) if abs(t - round(t)) < 1e-6}
            if not by_number:
                raise InputError(gt_path, "timestamps are not frame numbers (expected 'i tx ty tz qx qy qz qw')")
            self._gt_poses = [by_number.get(n) for n in self._numbers]

        height, width = read_depth_png(self._depth_files[0]).shape
        if self.config.intrinsics_file:
            self.intrinsics_source = f"{self.config.intrinsics_file} (dataset.intrinsics_file)"
            self._intrinsics = read_intrinsics_file(self.config.intrinsics_file, width, height)
        else:
            self.intrinsics_source = "ICL-NUIM's published intrinsics"
            self._intrinsics = Intrinsics(*ICL_INTRINSICS, width, height)

    @staticmethod
    def detect(root: Path) -> str | None:
        """The file that identifies an ICL-NUIM folder (its ``*.gt.freiburg`` ground truth), or None."""
        found = sorted(Path(root).glob("*.gt.freiburg"))
        return found[0].name if found else None
