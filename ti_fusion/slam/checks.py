"""What a run checks of the frames it is given, before they can do harm: one ``InputError`` naming the frame
and the problem, never a silent wrong result or a failure at the end of the run.

- ``check_frame(slam, frame)``: called first by ``DenseSLAM.register_frame`` (the Python API), every frame:
  the frame's type, image size and intrinsics against the ``DenseSLAM``'s (one camera per map), finite and
  strictly increasing timestamps, finite non-negative depth, colour of the depth's size, and on the first
  frames with depth, depth in metres (not millimetres, not metres divided by 1000).
- ``check_first_frames(dataset, config)``: called by the pipeline before its first frame: the first frames'
  depth statistics against the stated depth scale and ``dataset.depth_max`` (all depth a few millimetres, or
  all beyond the range), with the scale that would make them plausible.
"""

from __future__ import annotations

import math

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError

# Depth nearer than this (metres) is no RGB-D camera's measurement (the nearest range of structured light,
# time of flight and stereo cameras is 0.1 to 0.5 m): depth whose 95th percentile is under it has wrong units.
NEAREST_PLAUSIBLE_M = 0.05
# The first frames with depth whose statistics are checked (a later frame of the same sensor has the same units).
DEPTH_CHECK_FRAMES = 3
# Frames the pipeline reads ahead of the run to check the depth's units.
PRECHECK_FRAMES = 3
# The typical depth (metres) the suggested scale aims the median at: a room seen by an RGB-D camera.
TYPICAL_DEPTH_M = 1.5


class FrameChecks:
    """The state ``check_frame`` keeps between frames of one ``DenseSLAM``."""

    def __init__(self, intrinsics: Intrinsics):
        problem = _camera_problem(intrinsics)
        if problem:
            raise InputError(None, f"DenseSLAM intrinsics: {problem}")
        self.intrinsics = intrinsics
        self.last: tuple[int, float] | None = None  # (index, timestamp) of the last frame accepted
        self.depth_frames_checked = 0

    def check(self, frame) -> None:
        from ti_fusion.frame import Frame

        if not isinstance(frame, Frame):
            raise InputError(None, f"register_frame takes a Frame (ti_fusion.io.datasets.rgbd_frame makes one from "
                                   f"arrays), got {type(frame).__name__}")
        name = f"frame {frame.index}"
        self._check_camera(frame, name)
        self._check_images(frame, name)
        self._check_timestamp(frame, name)
        self.last = (frame.index, float(frame.timestamp))

    def _check_camera(self, frame, name: str) -> None:
        K, mine = frame.intrinsics, self.intrinsics
        if not isinstance(K, Intrinsics):
            raise InputError(None, f"{name}: intrinsics of type {type(K).__name__}, expected ti_fusion.camera.Intrinsics")
        if not K.pinhole:
            raise InputError(None, f"{name}: intrinsics with skew or lens distortion: undistort the images first "
                                   "(rgbd_frame does, given those intrinsics)")
        if (K.width, K.height) != (mine.width, mine.height):
            raise InputError(None, f"{name}: {K.width}x{K.height} images, the DenseSLAM's intrinsics are for "
                                   f"{mine.width}x{mine.height}: one image size and camera per DenseSLAM")
        same = all(math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9) for a, b in
                   zip(K.as_tuple(), mine.as_tuple()))
        if not same:
            raise InputError(None, f"{name}: intrinsics {_k(K)} differ from the DenseSLAM's {_k(mine)}: one camera "
                                   "per DenseSLAM (its map and prediction use its own; make another DenseSLAM for "
                                   "another camera)")

    def _check_images(self, frame, name: str) -> None:
        depth, K = frame.depth, frame.intrinsics
        if not isinstance(depth, np.ndarray) or depth.ndim != 2:
            shape = getattr(depth, "shape", None)
            raise InputError(None, f"{name}: depth must be an H×W NumPy array, got "
                                   f"{type(depth).__name__}{'' if shape is None else f' of shape {shape}'}")
        if depth.shape != (K.height, K.width):
            raise InputError(None, f"{name}: depth is {depth.shape[1]}x{depth.shape[0]}, its intrinsics are for "
                                   f"{K.width}x{K.height}")
        if not np.issubdtype(depth.dtype, np.floating):
            raise InputError(None, f"{name}: depth of type {depth.dtype}: a Frame's depth is float metres "
                                   "(rgbd_frame(depth, K, depth_scale=1000) converts millimetres)")
        # two reductions without temporaries: NaN fails "min >= 0", +inf fails "max < inf"
        if depth.size and not (depth.min() >= 0 and depth.max() < np.inf):
            bad = int(np.count_nonzero(~(np.isfinite(depth) & (depth >= 0))))
            raise InputError(None, f"{name}: depth has {bad} NaN, infinite or negative values: 0 marks a pixel "
                                   "without measurement (rgbd_frame turns them into 0)")
        color = frame.color
        if color is not None:
            if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.shape != (*depth.shape, 3):
                what = f"{color.dtype} of shape {color.shape}" if isinstance(color, np.ndarray) else type(color).__name__
                raise InputError(None, f"{name}: colour {what}: expected uint8 {depth.shape[0]}×{depth.shape[1]}×3 "
                                       "RGB, the depth image's size")
        if self.depth_frames_checked < DEPTH_CHECK_FRAMES:
            valid = depth[::2, ::2][depth[::2, ::2] > 0]
            if valid.size:
                self.depth_frames_checked += 1
                problem = near_depth_problem(valid)
                if problem:
                    raise InputError(None, f"{name}: {problem}, so the depth is not in metres: Frame.depth is "
                                           "metres (rgbd_frame's depth_scale is the raw units per metre: 1000 for "
                                           "millimetres, none for float metres)")

    def _check_timestamp(self, frame, name: str) -> None:
        t = frame.timestamp
        if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not math.isfinite(t):
            raise InputError(None, f"{name}: timestamp {t!r} is not a finite number of seconds")
        if self.last is not None and frame.index == self.last[0]:  # rgbd_frame's default index on every frame
            raise InputError(None, f"{name}: the same index as the frame before it (the trajectory and loop closure "
                                   "know frames by index): give each frame its own, e.g. rgbd_frame(..., index=i, "
                                   "timestamp=seconds) (without them every frame is index 0 at 0 s)")
        if self.last is not None and not t > self.last[1]:
            index, previous = self.last
            raise InputError(None, f"{name}: timestamp {float(t):.6f} is not after frame {index}'s {previous:.6f}: "
                                   "timestamps must increase (trajectory.tum and the evaluation pair poses by time)")


def check_frame(slam, frame) -> None:
    """InputError when ``frame`` cannot be ``slam``'s next frame (see the module docstring); the checks'
    state lives on the ``DenseSLAM`` itself."""
    checks = slam.__dict__.get("_frame_checks")
    if checks is None:
        checks = slam._frame_checks = FrameChecks(slam.intrinsics)
    checks.check(frame)


def _camera_problem(K) -> str | None:
    if not isinstance(K, Intrinsics):
        return f"of type {type(K).__name__}, expected ti_fusion.camera.Intrinsics"
    return K.implausibility()


def _k(K: Intrinsics) -> str:
    return f"fx {K.fx:g} fy {K.fy:g} cx {K.cx:g} cy {K.cy:g}"


def _metres(x: float) -> str:
    return f"{x * 1e3:.2g} mm" if x < 0.01 else f"{x * 100:.3g} cm" if x < 1 else f"{x:.3g} m"


def near_depth_problem(valid: np.ndarray) -> str | None:
    """The line saying that valid depths (metres, > 0) are nearer than any RGB-D camera measures, or None."""
    high = float(np.percentile(valid, 95))
    if high >= NEAREST_PLAUSIBLE_M:
        return None
    return (f"95 % of its depth is under {_metres(NEAREST_PLAUSIBLE_M)} ({_metres(float(valid.min()))} to "
            f"{_metres(float(valid.max()))}, median {_metres(float(np.median(valid)))}), nearer than any RGB-D camera "
            "measures")


def _scale_factor(median: float) -> float:
    """The power of ten that brings ``median`` metres nearest a room's depth."""
    return 10.0 ** round(math.log10(TYPICAL_DEPTH_M / median))


def check_first_frames(dataset, config) -> None:
    """InputError before the run when the first frames' depth, read without the range cut, is all nearer
    than a camera measures or all beyond ``dataset.depth_max``: the depth scale is wrong, and the line says
    which one would make it plausible. The synthetic sequence and frames from Python are not read ahead."""
    if dataset.format == "arrays":
        _check_frame_list(dataset)
        return
    ds_config = getattr(dataset, "config", None)
    if getattr(dataset, "renders_on_taichi", False) or dataset.format == "synthetic" \
            or ds_config is None or not hasattr(ds_config, "depth_max"):
        return
    depth_max = ds_config.depth_max
    saved = depth_max
    ds_config.depth_max = 0.0  # read the depth as it is: the cut is what is checked
    try:
        samples = [dataset[i].depth[::2, ::2] for i in range(min(PRECHECK_FRAMES, len(dataset)))]
    finally:
        ds_config.depth_max = saved
    valid = np.concatenate([d[d > 0] for d in samples]) if samples else np.zeros(0)
    if not valid.size:
        return  # blank first frames: the map starts later, or the run ends saying that nothing had depth
    scale = dataset.depth_scale or 1.0
    stated = f"with depth scale {scale:g} units per metre ({_scale_source(dataset)})"
    median = float(np.median(valid))
    near = near_depth_problem(valid)
    if near:
        factor = _scale_factor(median)
        raise InputError(dataset.root, f"the first frames' depth {stated}: {near}; --depth-scale "
                                       f"{scale / factor:g} would make its median {_metres(median * factor)}")
    if depth_max and depth_max > 0:
        beyond = float(np.count_nonzero(valid > depth_max)) / valid.size
        if beyond >= 0.95:
            factor = _scale_factor(median)
            raise InputError(dataset.root, f"the first frames' depth {stated} is {_metres(float(valid.min()))} to "
                                           f"{_metres(float(valid.max()))} (median {_metres(median)}): "
                                           f"{beyond:.0%} of it beyond dataset.depth_max = {depth_max:g} m, so "
                                           f"nothing would be left; --depth-scale {scale / factor:g} would make its "
                                           f"median {_metres(median * factor)} (or raise dataset.depth_max if the "
                                           "scene is that far)")


def _check_frame_list(dataset) -> None:
    """Frames held in a list (``FrameList``): their timestamps and cameras checked before the first frame,
    as ``check_frame`` would check them one by one (a lazy sequence is left to ``check_frame``)."""
    frames = dataset.frames
    if not isinstance(frames, (list, tuple)):
        return
    checks = FrameChecks(dataset.intrinsics)
    for i in dataset.indices:
        frame = frames[i]
        name = f"frame {getattr(frame, 'index', i)}"
        checks._check_timestamp(frame, name)
        if frame.intrinsics != frames[dataset.indices[0]].intrinsics:
            checks._check_camera(frame, name)  # says how it differs
        checks.last = (frame.index, float(frame.timestamp))


def _scale_source(dataset) -> str:
    source = getattr(dataset, "depth_scale_source", None)  # where a loader says where it took the scale from
    if source:
        return str(source)
    given = getattr(dataset, "config", None) is not None and getattr(dataset.config, "depth_scale", 0)
    return "--depth-scale / dataset.depth_scale" if given else f"the {dataset.format} format's own"
