"""Pinhole camera intrinsics."""

from __future__ import annotations

import numbers
from dataclasses import dataclass, replace

import numpy as np

# The field of view (degrees, the wider of horizontal and vertical) that intrinsics must give their image.
MIN_FOV_DEG, MAX_FOV_DEG = 20.0, 170.0
# Lens distortion models a calibration may state (ROS camera_info names; OpenCV's standard model reads
# 4, 5, 8, 12 or 14 coefficients, its fisheye model 4).
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")


# (intrinsics, factor, the types of both's numbers) → Intrinsics.downsampled's answer
_DOWNSAMPLED: dict = {}


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image of ``width`` × ``height`` pixels.

    A pixel (u, v) with depth z back-projects to ((u - cx) z / fx, (v - cy) z / fy, z):
    x right, y down, z forward (the OpenCV / TUM camera frame).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    # What a calibration may add to the pinhole model. The kernels take only a pinhole camera: a dataset
    # whose calibration has these undistorts its images once per frame (``ti_fusion.io.datasets.undistort``)
    # and hands out frames with ``undistorted()`` intrinsics.
    skew: float = 0.0                       # K[0,1] (pixels), 0 for almost every camera
    distortion: tuple[float, ...] = ()      # lens distortion coefficients in OpenCV's order; () = none
    distortion_model: str = ""              # DISTORTION_MODELS: how to read ``distortion``

    def __post_init__(self):
        # Values of the wrong type (a calibration read as text) would fail far from here as a TypeError.
        from ti_fusion.errors import InputError

        for name in ("fx", "fy", "cx", "cy", "skew"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise InputError(None, f"Intrinsics {name}={value!r}: expected a number of pixels, got "
                                       f"{type(value).__name__}")
        for name in ("width", "height"):
            value = getattr(self, name)
            whole = isinstance(value, numbers.Integral) or (isinstance(value, numbers.Real) and float(value).is_integer())
            if isinstance(value, bool) or not whole:
                raise InputError(None, f"Intrinsics {name}={value!r}: expected a whole number of pixels, got "
                                       f"{type(value).__name__}")
            if not isinstance(value, int):
                object.__setattr__(self, name, int(value))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def pinhole(self) -> bool:
        """No skew and no lens distortion: what the kernels take as it is."""
        return self.skew == 0.0 and not any(self.distortion)

    def undistorted(self) -> "Intrinsics":
        """The pinhole camera that undistorted images are for: the same fx, fy, cx, cy, no skew or distortion."""
        return self if self.pinhole else replace(self, skew=0.0, distortion=(), distortion_model="")

    def downsampled(self, factor: int) -> "Intrinsics":
        """Intrinsics of the image subsampled as ``img[::factor, ::factor]`` (pixel u' is pixel factor·u')."""
        if factor == 1:
            return self
        # a frame's pyramid asks for the same few every frame, each a dataclass made and checked anew
        try:
            key = (self, factor, type(factor), type(self.fx), type(self.fy), type(self.cx), type(self.cy),
                   type(self.skew))
            known = _DOWNSAMPLED.get(key)
        except TypeError:  # a value that cannot be a key (a list of distortion coefficients)
            return self._downsampled(factor)
        if known is None:
            if len(_DOWNSAMPLED) >= 64:
                _DOWNSAMPLED.clear()
            known = _DOWNSAMPLED[key] = self._downsampled(factor)
        return known

    def _downsampled(self, factor) -> "Intrinsics":
        return replace(
            self,
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=self.cx / factor,
            cy=self.cy / factor,
            skew=self.skew / factor,  # distortion acts on normalised coordinates: unchanged
            width=(self.width + factor - 1) // factor,
            height=(self.height + factor - 1) // factor,
        )

    def fields_of_view(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view in degrees, from the principal point to both image edges."""
        def fov(f: float, c: float, size: int) -> float:
            return float(np.degrees(np.arctan2(c + 0.5, f) + np.arctan2(size - 0.5 - c, f)))

        return fov(self.fx, self.cx, self.width), fov(self.fy, self.cy, self.height)

    def implausibility(self) -> str | None:
        """Why these intrinsics cannot be this image's camera (None: they can): the principal point outside
        the image, or a field of view no RGB-D camera has (wider than fisheye-wide, narrower than a telephoto
        that sees a few centimetres of a wall at a metre)."""
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(values)):
            return f"intrinsics {self._text()} contain NaN or infinite values"
        if self.fx <= 0 or self.fy <= 0:
            return f"focal lengths must be positive (fx={self.fx:g}, fy={self.fy:g})"
        if not (-0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5):
            return (f"principal point ({self.cx:g}, {self.cy:g}) is outside the {self.width}x{self.height} image "
                    f"(cx in [0, {self.width - 1}], cy in [0, {self.height - 1}]; the image's centre is "
                    f"({(self.width - 1) / 2:g}, {(self.height - 1) / 2:g}))")
        h, v = self.fields_of_view()
        widest = max(h, v)
        if not MIN_FOV_DEG <= widest <= MAX_FOV_DEG:
            # the focal length that gives a 60° horizontal view, as most RGB-D cameras have
            typical = self.width / 2 / np.tan(np.radians(30))
            return (f"fx {self.fx:g}, fy {self.fy:g} give a {h:.3g}° x {v:.3g}° field of view at {self.width}x"
                    f"{self.height}: outside {MIN_FOV_DEG:g}° to {MAX_FOV_DEG:g}°, so not this image's camera (a "
                    f"60° view needs fx about {typical:.0f}; focal lengths are in pixels of these images)")
        return None

    def _text(self) -> str:
        return f"fx {self.fx:g} fy {self.fy:g} cx {self.cx:g} cy {self.cy:g}"

    def as_tuple(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy): the form the kernels take."""
        return (float(self.fx), float(self.fy), float(self.cx), float(self.cy))
