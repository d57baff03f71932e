"""Undistortion of a calibrated camera's frames (``ti_fusion/io/datasets/undistort.py``): the OpenCV maps
against a NumPy float64 reference of each distortion model (skew included), depth read at the nearest pixel
and colour bilinearly, pixels outside the input left without depth, and a folder whose camera.yaml has
distortion handing out undistorted frames with the pinhole intrinsics."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.datasets.undistort import undistort, undistortion_maps

W, H = 64, 48
PINHOLE = Intrinsics(fx=58.0, fy=57.0, cx=31.2, cy=23.7, width=W, height=H)


def reference_maps(K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """float64: for each output pixel of ``K.undistorted()``, the input pixel of the calibrated camera."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    d = list(K.distortion)
    if K.distortion_model == "equidistant":
        k1, k2, k3, k4 = d
        r = np.hypot(x, y)
        theta = np.arctan(r)
        theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
        scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1), 1.0)
        xd, yd = x * scale, y * scale
    else:
        k1, k2, p1, p2, k3, k4, k5, k6 = (d + [0.0] * 8)[:8]
        r2 = x * x + y * y
        radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return K.fx * xd + K.skew * yd + K.cx, K.fy * yd + K.cy


CAMERAS = {
    "plumb_bob with skew": dataclasses.replace(PINHOLE, skew=4.0, distortion=(0.25, -0.8, 0.001, 0.002, 0.9),
                                               distortion_model="plumb_bob"),
    "rational_polynomial": dataclasses.replace(PINHOLE, distortion=(0.3, -0.1, 0.002, -0.001, 0.05, 0.2, 0.01, 0.02),
                                               distortion_model="rational_polynomial"),
    "equidistant": dataclasses.replace(PINHOLE, distortion=(0.1, -0.05, 0.01, -0.002), distortion_model="equidistant"),
    "skew only": dataclasses.replace(PINHOLE, skew=-6.0),
}


@pytest.mark.parametrize("name", CAMERAS)
def test_the_maps_match_the_numpy_reference(name):
    K = CAMERAS[name]
    map_x, map_y = undistortion_maps(K)
    ref_x, ref_y = reference_maps(K)
    assert map_x.shape == (H, W) and map_x.dtype == np.float32
    np.testing.assert_allclose(map_x, ref_x, atol=2e-3)
    np.testing.assert_allclose(map_y, ref_y, atol=2e-3)
    assert undistortion_maps(K) is undistortion_maps(K)  # computed once per calibration


def test_depth_is_read_at_the_nearest_pixel_and_color_bilinearly(rng):
    K = CAMERAS["plumb_bob with skew"]
    depth = rng.uniform(0.5, 3.0, (H, W)).astype(np.float32)
    depth[rng.random((H, W)) < 0.1] = 0.0  # invalid pixels stay invalid, never averaged into their neighbours
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    out_depth, out_color, out_K = undistort(depth, color, K)
    assert out_K == PINHOLE and out_K.pinhole
    ref_x, ref_y = reference_maps(K)
    inside = (ref_x >= 0) & (ref_x <= W - 1) & (ref_y >= 0) & (ref_y <= H - 1)
    # away from the exact middle between two pixels (where rounding may go either way), the nearest pixel's depth
    clear = inside & (np.abs(ref_x % 1 - 0.5) > 0.01) & (np.abs(ref_y % 1 - 0.5) > 0.01)
    iy, ix = np.floor(ref_y + 0.5).astype(int), np.floor(ref_x + 0.5).astype(int)
    np.testing.assert_array_equal(out_depth[clear], depth[iy[clear], ix[clear]])
    assert np.isin(out_depth, np.append(depth.ravel(), 0.0)).all()
    # colour: bilinear between the four neighbours (OpenCV's 5-bit interpolation weights: within 2 levels)
    x0, y0 = np.floor(ref_x).astype(int), np.floor(ref_y).astype(int)
    ok = inside & (x0 < W - 1) & (y0 < H - 1)
    fx, fy = (ref_x - x0)[ok][:, None], (ref_y - y0)[ok][:, None]
    c = color.astype(np.float64)
    a, b, yy, xx = c[y0[ok], x0[ok]], c[y0[ok], x0[ok] + 1], y0[ok], x0[ok]
    bilinear = (1 - fy) * ((1 - fx) * a + fx * b) + fy * ((1 - fx) * c[yy + 1, xx] + fx * c[yy + 1, xx + 1])
    assert np.abs(out_color[ok].astype(np.float64) - bilinear).max() <= 2.0
    # output pixels whose ray falls outside the input image have no depth and black colour
    outside = (ref_x < -1) | (ref_x > W) | (ref_y < -1) | (ref_y > H)
    assert outside.any() and (out_depth[outside] == 0).all() and (out_color[outside] == 0).all()


def test_a_pinhole_frame_is_returned_as_it_is(rng):
    depth = rng.uniform(0.5, 3.0, (H, W)).astype(np.float32)
    out_depth, out_color, out_K = undistort(depth, None, PINHOLE)
    assert out_depth is depth and out_color is None and out_K is PINHOLE


def test_a_folder_with_distortion_hands_out_undistorted_frames(tmp_path, rng):
    root = tmp_path / "cam"
    (root / "depth").mkdir(parents=True)
    raw = (rng.uniform(0.5, 3.0, (H, W)) * 1000).astype(np.uint16)
    assert cv2.imwrite(str(root / "depth" / "0.png"), raw)
    K = CAMERAS["plumb_bob with skew"]
    (root / "intrinsics.txt").write_text(f"{K.fx} {K.skew} {K.cx}\n0 {K.fy} {K.cy}\n0 0 1\n")
    (root / "camera.yaml").write_text(
        f"width: {W}\nheight: {H}\ndistortion_model: plumb_bob\nd: {list(K.distortion)}\n"
        f"k: [{K.fx}, {K.skew}, {K.cx}, 0, {K.fy}, {K.cy}, 0, 0, 1]\n")
    ds = open_dataset(DatasetConfig(path=str(root), format="folder", depth_scale=1000.0, downsample=2))
    assert ds.raw_intrinsics == K and ds.intrinsics == PINHOLE.downsampled(2)
    frame = ds[0]
    expected, _, _ = undistort(raw.astype(np.float32) / 1000, None, K)
    assert frame.intrinsics == PINHOLE.downsampled(2)
    np.testing.assert_array_equal(frame.depth, expected[::2, ::2])  # undistorted first, then downsampled
    assert "skew 4 and plumb_bob distortion [0.25, -0.8, 0.001, 0.002, 0.9]" in ds.describe_format()
