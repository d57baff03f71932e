"""Images of a camera with lens distortion or skew turned into the pinhole images the kernels take.

    depth, color, K = undistort(depth, color, intrinsics)   # K = intrinsics.undistorted()

The output pixel (u, v) of the pinhole camera ``intrinsics.undistorted()`` (same fx, fy, cx, cy; no skew,
no distortion) is read at the input pixel where the calibrated camera sees the same ray: OpenCV's
``initUndistortRectifyMap`` (``cv2.fisheye``'s for the equidistant model) gives that pixel for every output
pixel once per calibration, and the skew (which they ignore) is added to it; each frame is then one
``cv2.remap``. Depth is read at the nearest pixel (an
average across an edge would invent a surface between the two), colour bilinearly. Output pixels whose ray
falls outside the input image have no depth (0) and black colour.

Depth stays the input pixel's z: distortion moves where a point appears in the image, not its distance
along the optical axis, so the value read at the source pixel is the z of the ray that the output pixel
now stands for.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics


@functools.lru_cache(maxsize=8)
def undistortion_maps(intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y): float32 H×W, the input pixel each output pixel of ``intrinsics.undistorted()`` reads.
    Computed once per calibration (the intrinsics are hashable and frozen)."""
    K = new_K = intrinsics.undistorted().K  # OpenCV's models read fx, fy, cx, cy only: skew is added below
    size = (intrinsics.width, intrinsics.height)
    D = np.asarray(intrinsics.distortion, dtype=np.float64)
    if intrinsics.distortion_model == "equidistant":
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, D.reshape(4, 1), np.eye(3), new_K, size, cv2.CV_32FC1)
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K, D if D.size else None, np.eye(3), new_K, size, cv2.CV_32FC1)
    if intrinsics.skew:  # u = fx x_d + skew y_d + cx, and y_d = (v - cy) / fy
        map_x = (map_x + np.float32(intrinsics.skew / intrinsics.fy) * (map_y - np.float32(intrinsics.cy))).astype(
            np.float32)
    return map_x, map_y


def undistort(depth: np.ndarray, color: np.ndarray | None,
              intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray | None, Intrinsics]:
    """(depth, colour, pinhole intrinsics) of one frame; frames of a pinhole camera are returned as they are."""
    if intrinsics.pinhole:
        return depth, color, intrinsics
    map_x, map_y = undistortion_maps(intrinsics)
    depth = cv2.remap(np.ascontiguousarray(depth, dtype=np.float32), map_x, map_y, cv2.INTER_NEAREST,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    if color is not None:
        color = cv2.remap(np.ascontiguousarray(color), map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return depth, color, intrinsics.undistorted()
