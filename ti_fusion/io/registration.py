"""Colour registered to depth in the run loop's thread (Taichi kernels are launched from one thread only):
a frame whose colour comes from a separate camera carries ``meta["color_camera"]`` = (that camera's
``Intrinsics`` at full resolution, T_color_depth), set by the loader that knows them (a RealSense
recording, a bag with ``--color-extrinsics``); ``ColourRegistrar`` replaces its colour by the colour
reprojected into the depth camera (``kernels/registration.py``), marks it registered, and puts the pixels
the colour camera did not see in ``meta["color_valid"]`` (False: no colour; the photometric term skips them).
"""

from __future__ import annotations

from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Frame


class ColourRegistrar:
    """Registers frames' colour, keeping one kernel object (its fields) per pair of image sizes."""

    def __init__(self):
        self._kernels = {}

    def __call__(self, frame: Frame) -> Frame:
        camera = frame.meta.get("color_camera")
        if camera is None or frame.color is None:
            return frame
        from ti_fusion.backend import current_backend
        from ti_fusion.kernels.registration import ColorRegistration

        current_backend()  # commands without Taichi of their own (vo) start it on the CPU here

        K_colour, T = camera
        h, w = frame.color.shape[:2]
        if (K_colour.width, K_colour.height) != (w, h):  # downsampled with the frame (--downsample)
            f = round(K_colour.width / w)
            if f < 1 or K_colour.downsampled(f).width != w:
                raise InputError(None, f"frame {frame.index}: colour image of {w}x{h}, its camera is "
                                       f"{K_colour.width}x{K_colour.height}")
            K_colour = K_colour.downsampled(f)
        key = (frame.depth.shape, (h, w))
        if key not in self._kernels:
            self._kernels[key] = ColorRegistration(frame.depth.shape, (h, w))
        frame.color, valid = self._kernels[key].register(frame.depth, frame.color, frame.intrinsics, K_colour, T)
        frame.meta["color_valid"] = valid
        frame.meta.pop("color_camera")
        frame.color_registered = True
        return frame
