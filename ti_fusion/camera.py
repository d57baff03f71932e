"""Pinhole camera intrinsics."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


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

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def downsampled(self, factor: int) -> "Intrinsics":
        """Intrinsics of the image subsampled as ``img[::factor, ::factor]`` (pixel u' is pixel factor·u')."""
        if factor == 1:
            return self
        return replace(
            self,
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=self.cx / factor,
            cy=self.cy / factor,
            width=(self.width + factor - 1) // factor,
            height=(self.height + factor - 1) // factor,
        )

    def as_tuple(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy): the form the kernels take."""
        return (float(self.fx), float(self.fy), float(self.cx), float(self.cy))
