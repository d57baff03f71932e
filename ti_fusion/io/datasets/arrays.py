"""Frames from one's own code: a ``Frame`` made from NumPy arrays, and frames held in a list as a
``Dataset``.

One frame at a time, as a robot's code has them (``scripts/example_stream.py`` runs this)::

    from ti_fusion.backend import init_backend
    from ti_fusion.camera import Intrinsics
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import rgbd_frame
    from ti_fusion.slam.dense import DenseSLAM

    init_backend("cpu")                                   # or "cuda", "vulkan", "auto"
    K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    slam = DenseSLAM(Config(), K)
    for i, (t, depth_mm, rgb) in enumerate(camera):      # uint16 millimetres, uint8 RGB, seconds
        result = slam.register_frame(rgbd_frame(depth_mm, K, depth_scale=1000, color=rgb, timestamp=t, index=i))
        print(result.status, result.pose)                 # "init"/"ok"/"relocalised"/"lost: ...", 4×4 camera-to-world
    slam.mapper.export_ply("map.ply")

A whole recording in memory: ``FrameList(frames)`` is a ``Dataset``, so ``SLAMPipeline(FrameList(frames),
config, RunDir("slam", "out"), current_backend()).run()`` (``ti_fusion.backend.current_backend``) writes
what ``ti-fusion slam`` writes (log.mcap, trajectory.tum, map.ply, the plots, and ATE/RPE when the frames
carry ground truth).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame

DEPTH_MAX = DatasetConfig().depth_max  # the command line's default range cut, so both see the same depth


def rgbd_frame(depth: np.ndarray, intrinsics: Intrinsics, depth_scale: float | None = None,
               color: np.ndarray | None = None, timestamp: float | None = None, index: int = 0,
               gt_pose: np.ndarray | None = None, depth_max: float | None = DEPTH_MAX,
               color_registered: bool = True) -> Frame:
    """A ``Frame`` from arrays, checked and converted to what ``DenseSLAM.register_frame`` takes.

    depth: H×W, in metres (float), or in raw units with ``depth_scale`` units per metre (1000 for
        millimetres); 0, NaN, ±Inf and negative values mean no measurement. Integer depth needs
        ``depth_scale`` (its units cannot be guessed).
    intrinsics: the depth image's intrinsics; its size must be the depth image's. With skew or lens
        distortion (``Intrinsics.distortion``) the frame is undistorted to ``intrinsics.undistorted()``.
    color: None, or uint8 H×W×3 RGB (H×W grey is made RGB), the depth image's size. Depth and colour are
        copied: a camera buffer reused for the next frame does not change this one.
    color_registered: pixel (u, v) of ``color`` sees what depth's (u, v) sees (a camera's aligned colour
        stream): tracking then uses colour too (``icp.color_weight``). False for colour that is only
        resized to depth's size: it then only colours the map.
    timestamp: seconds (trajectory.tum and the log use it); None = ``index``.
    index: the frame's number; each frame given to one ``DenseSLAM`` needs its own, increasing with time.
    gt_pose: 4×4 camera-to-world ground truth, or None.
    depth_max: metres: farther depth counts as no measurement (the command line's ``dataset.depth_max``);
        None or 0 keeps every range.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InputError(None, f"depth must be an H×W array, got shape {depth.shape}")
    if (depth.shape[1], depth.shape[0]) != (intrinsics.width, intrinsics.height):
        raise InputError(None, f"depth is {depth.shape[1]}x{depth.shape[0]}, the intrinsics are for "
                               f"{intrinsics.width}x{intrinsics.height}")
    if np.issubdtype(depth.dtype, np.integer) and depth_scale is None:
        raise InputError(None, f"depth of type {depth.dtype} needs depth_scale (units per metre, e.g. 1000 for "
                               "millimetres); float depth is taken as metres")
    if not np.issubdtype(depth.dtype, np.number) or np.issubdtype(depth.dtype, np.complexfloating):
        raise InputError(None, f"depth of type {depth.dtype}: expected numbers")
    if depth_scale is not None and not depth_scale > 0:
        raise InputError(None, f"depth_scale {depth_scale}: must be a positive number of units per metre")
    metres = depth.astype(np.float32) / np.float32(depth_scale) if depth_scale is not None \
        else depth.astype(np.float32, copy=True)
    bad = ~np.isfinite(metres) | (metres <= 0)
    if depth_max:
        bad |= metres > depth_max
    metres[bad] = 0.0
    rgb = _rgb(color, depth.shape)
    if not intrinsics.pinhole:  # skew or lens distortion: the kernels take pinhole images
        from ti_fusion.io.datasets.undistort import undistort

        metres, rgb, intrinsics = undistort(metres, rgb, intrinsics)
    return Frame(index=int(index), timestamp=float(index if timestamp is None else timestamp), depth=metres,
                 intrinsics=intrinsics, color=rgb, gt_pose=None if gt_pose is None else _pose(gt_pose),
                 color_registered=rgb is not None and bool(color_registered))


def _rgb(color, shape: tuple[int, int]) -> np.ndarray | None:
    if color is None:
        return None
    color = np.asarray(color)
    if color.dtype != np.uint8:
        raise InputError(None, f"colour of type {color.dtype}: expected uint8 RGB")
    if color.ndim == 2:
        color = cv2.cvtColor(color, cv2.COLOR_GRAY2RGB)
    if color.ndim != 3 or color.shape[2] != 3 or color.shape[:2] != shape:
        raise InputError(None, f"colour of shape {color.shape}: expected {shape[0]}×{shape[1]}×3 RGB, the depth "
                               "image's size (registered to it)")
    return np.array(color, order="C", copy=True)  # the caller may reuse its buffer for the next frame


def _pose(T) -> np.ndarray:
    from ti_fusion.geometry import rigidity_error

    T = np.asarray(T, dtype=np.float64)
    problem = rigidity_error(T) if T.shape == (4, 4) else f"shape {T.shape}, expected 4×4"
    if problem:
        raise InputError(None, f"gt_pose is not a rigid transform: {problem}")
    return T.copy()


class FrameList(Dataset):
    """Frames of one's own as a ``Dataset``: a list of ``Frame`` (``rgbd_frame``), or any sequence that
    makes them on demand (``__len__`` and ``__getitem__``). Every frame must have the first one's
    intrinsics. Selection and downsampling apply as to any dataset; the frames given are not changed."""

    format = "arrays"

    def __init__(self, frames: Sequence[Frame], name: str = "frames", downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(Path(name), downsample=downsample, start=start, stop=stop, stride=stride)
        if len(frames) == 0:
            raise InputError(None, "FrameList: no frames")
        self.frames = frames
        self.name = name
        self.format_from = "frames given in Python"
        self.intrinsics_source = "the frames' own"
        self._intrinsics = frames[0].intrinsics
        self.color_registered = bool(frames[0].color_registered)  # rgbd_frame's color_registered

    @property
    def raw_intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def has_ground_truth(self) -> bool:
        return any(self.frames[i].gt_pose is not None for i in self.indices)

    def _num_raw_frames(self) -> int:
        return len(self.frames)

    def _load_raw(self, raw_index: int) -> Frame:
        frame = self.frames[raw_index]
        if frame.intrinsics != self._intrinsics:
            raise InputError(None, f"frame {raw_index} has intrinsics {frame.intrinsics}, the first "
                                   f"{self._intrinsics}: one camera per FrameList")
        return dataclasses.replace(frame)  # downsampling replaces the copy's arrays, not the caller's
