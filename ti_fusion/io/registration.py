"""Colour registered to depth in the run loop's thread (Taichi kernels are launched from one thread only):
a frame whose colour comes from a separate camera carries ``meta["color_camera"]`` = (that camera's
``Intrinsics`` at full resolution, T_color_depth), set by the loader that knows them (a RealSense
recording, a bag with ``--color-extrinsics``); ``ColorRegistrar`` replaces its colour by the colour
reprojected into the depth camera (``kernels/registration.py``), marks it registered, and puts the pixels
the colour camera did not see in ``meta["color_valid"]`` (False: no colour; the photometric term skips them).
"""

from __future__ import annotations

from dataclasses import replace

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Frame


def resized(K: Intrinsics, w: int, h: int, index: int) -> Intrinsics:
    """The colour camera of an image that was subsampled (``--downsample``: ``img[::f, ::f]``) or resized
    (a loader that fits colour to the depth's size: pixel edges scale, so centres move by half a pixel)."""
    f = round(K.width / w)
    if f >= 1 and K.downsampled(f).width == w and K.downsampled(f).height == h:
        return K.downsampled(f)
    sx, sy = w / K.width, h / K.height
    if not (0.1 < sx < 10 and 0.1 < sy < 10):
        raise InputError(None, f"frame {index}: colour image of {w}x{h}, its camera is {K.width}x{K.height}")
    return replace(K, fx=K.fx * sx, fy=K.fy * sy, cx=(K.cx + 0.5) * sx - 0.5, cy=(K.cy + 0.5) * sy - 0.5,
                   skew=K.skew * sx, width=w, height=h)


class ColorRegistrar:
    """Registers frames' colour, keeping one kernel object (its fields) per pair of image sizes.
    ``camera``: the dataset's colour camera (``Dataset.color_camera``: a folder or 7-Scenes run with
    ``--color-extrinsics``) for frames that carry none of their own."""

    def __init__(self, camera=None):
        self._kernels = {}
        self._camera = camera

    def __call__(self, frame: Frame) -> Frame:
        camera = frame.meta.get("color_camera", self._camera)
        if camera is None or frame.color is None:
            return frame
        from ti_fusion.backend import current_backend
        from ti_fusion.kernels.registration import ColorRegistration

        current_backend()  # commands without Taichi of their own (vo) start it on the CPU here

        K_color, T = camera
        h, w = frame.color.shape[:2]
        if (K_color.width, K_color.height) != (w, h):
            K_color = resized(K_color, w, h, frame.index)
        key = (frame.depth.shape, (h, w))
        if key not in self._kernels:
            self._kernels[key] = ColorRegistration(frame.depth.shape, (h, w))
        frame.color, valid = self._kernels[key].register(frame.depth, frame.color, frame.intrinsics, K_color, T)
        frame.meta["color_valid"] = valid
        frame.meta.pop("color_camera", None)
        frame.color_registered = True
        return frame
