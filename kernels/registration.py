"""Colour registered to depth: each depth pixel's point moved into the colour camera through the
extrinsics and its colour read there, so that pixel (u, v) of the output sees the point of depth (u, v).

For a depth pixel (u, v) with depth z: p = z K_d⁻¹ (u, v, 1), q = T_color_depth p, and the colour at
K_c q / q_z, read by bilinear interpolation. A point the colour camera does not see (outside its image,
behind it, or hidden behind a nearer point from the colour camera's side: the two cameras are a few
centimetres apart, so the edge of a near object hides a strip of the background) gets no colour (valid 0):
a z-buffer of the depth points' colour-camera depths (nearest per colour pixel, as int32 bit patterns
with 32-bit atomics so that Vulkan runs it) is filled first, and a point more than ``margin`` (relative)
behind the nearest one at its colour pixel is hidden. Each point is splatted over the colour pixels its
depth pixel covers (a square of side ⌈f_c / f_d · z / q_z⌉, at most 7), so that a colour camera with more
pixels per degree than the depth camera leaves no gaps in the near surface for far points to show through.

``ColorRegistration`` owns the fields for one pair of image sizes; ``register(depth, colour, K_d, K_c, T)``
returns (colour uint8 H×W×3, valid bool H×W).
"""

import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics
from ti_fusion.kernels.common import (INT_MAX, Rigid, Vec3, bits_depth, data_oriented, depth_bits, rigid,
                                      rigid_arg)

Vec4 = ti.types.vector(4, ti.f32)
MAX_SPLAT = 7  # colour pixels per side of a point's footprint in the z-buffer at most
OCCLUSION_MARGIN = 0.05  # relative: a point 5 % farther than the nearest at its colour pixel is hidden
# pixels: a point this far outside the colour image still reads its edge (float32 rounding of a point on
# the last column, e.g. 79.00001 for 79, must not lose it)
EDGE = 0.01


@ti.func
def _to_color(depth: ti.template(), v, u, kd, T: ti.template()):
    """(q in the colour camera, z) of depth pixel (v, u); z = 0 where no depth."""
    R, t = rigid(T)
    z = depth[v, u]
    q = Vec3(0.0, 0.0, 0.0)
    if z > 0:
        p = Vec3((ti.cast(u, ti.f32) - kd[2]) / kd[0] * z, (ti.cast(v, ti.f32) - kd[3]) / kd[1] * z, z)
        q = R @ p + t
    return q, z


@ti.kernel
def clear_zbuffer(zbuf: ti.template(), hc: ti.i32, wc: ti.i32):
    for v, u in ti.ndrange(hc, wc):
        zbuf[v, u] = INT_MAX


@ti.kernel
def splat_depth(depth: ti.template(), h: ti.i32, w: ti.i32, kd: Vec4, kc: Vec4, T: Rigid, zbuf: ti.template(),
                hc: ti.i32, wc: ti.i32):
    """zbuf[colour pixel] = the nearest colour-camera depth of the points whose footprint covers it."""
    for v, u in ti.ndrange(h, w):
        q, z = _to_color(depth, v, u, kd, T)
        if z > 0 and q[2] > 0:
            uc = kc[0] * q[0] / q[2] + kc[2]
            vc = kc[1] * q[1] / q[2] + kc[3]
            side = ti.min(ti.ceil(kc[0] / kd[0] * z / q[2] - 0.01), MAX_SPLAT)  # 1.0000001 is one pixel
            r = ti.cast(side, ti.i32) // 2
            iu = ti.cast(ti.round(uc), ti.i32)
            iv = ti.cast(ti.round(vc), ti.i32)
            key = depth_bits(q[2])
            for dv, du in ti.ndrange((-r, r + 1), (-r, r + 1)):
                x, y = iu + du, iv + dv
                if 0 <= x < wc and 0 <= y < hc:
                    ti.atomic_min(zbuf[y, x], key)


@ti.kernel
def sample_color(depth: ti.template(), h: ti.i32, w: ti.i32, kd: Vec4, kc: Vec4, T: Rigid, zbuf: ti.template(),
                 color: ti.template(), hc: ti.i32, wc: ti.i32, margin: ti.f32, out: ti.template(),
                 valid: ti.template()):
    """out[v, u] = the colour at depth pixel (v, u)'s point in the colour image (bilinear), valid 1; else
    (0, 0, 0) and valid 0."""
    for v, u in ti.ndrange(h, w):
        q, z = _to_color(depth, v, u, kd, T)
        c = Vec3(0.0, 0.0, 0.0)
        ok = 0
        if z > 0 and q[2] > 0:
            uc = kc[0] * q[0] / q[2] + kc[2]
            vc = kc[1] * q[1] / q[2] + kc[3]
            if uc >= -EDGE and uc <= wc - 1.0 + EDGE and vc >= -EDGE and vc <= hc - 1.0 + EDGE:
                nearest = bits_depth(zbuf[ti.cast(ti.round(vc), ti.i32), ti.cast(ti.round(uc), ti.i32)])
                if q[2] <= nearest * (1.0 + margin):
                    u0 = ti.min(ti.cast(ti.floor(uc), ti.i32), wc - 2)
                    v0 = ti.min(ti.cast(ti.floor(vc), ti.i32), hc - 2)
                    u0 = ti.max(u0, 0)
                    v0 = ti.max(v0, 0)
                    a = ti.min(ti.max(uc - u0, 0.0), 1.0)
                    b = ti.min(ti.max(vc - v0, 0.0), 1.0)
                    c = (1 - a) * (1 - b) * color[v0, u0] + a * (1 - b) * color[v0, u0 + 1] \
                        + (1 - a) * b * color[v0 + 1, u0] + a * b * color[v0 + 1, u0 + 1]
                    ok = 1
        out[v, u] = c
        valid[v, u] = ok


def _vec(K: Intrinsics) -> np.ndarray:
    return np.array([K.fx, K.fy, K.cx, K.cy], dtype=np.float32)


@data_oriented
class ColorRegistration:
    """The fields of one depth size (h, w) and colour size (hc, wc), and the three kernels' launches."""

    def __init__(self, depth_shape: tuple[int, int], color_shape: tuple[int, int]):
        (h, w), (hc, wc) = depth_shape, color_shape
        self.depth_shape, self.color_shape = (h, w), (hc, wc)
        self.depth = ti.field(ti.f32, shape=(h, w))
        self.color = ti.Vector.field(3, ti.f32, shape=(hc, wc))
        self.zbuf = ti.field(ti.i32, shape=(hc, wc))
        self.out = ti.Vector.field(3, ti.f32, shape=(h, w))
        self.valid = ti.field(ti.i32, shape=(h, w))

    def register(self, depth: np.ndarray, color: np.ndarray, K_depth: Intrinsics, K_color: Intrinsics,
                 T_color_depth: np.ndarray, margin: float = OCCLUSION_MARGIN) -> tuple[np.ndarray, np.ndarray]:
        """(colour uint8 h×w×3 in the depth camera, valid bool h×w) of ``color`` (uint8 hc×wc×3)."""
        if depth.shape != self.depth_shape or color.shape[:2] != self.color_shape:
            raise ValueError(f"depth {depth.shape} and colour {color.shape} given to a registration of "
                             f"{self.depth_shape} and {self.color_shape}")
        (h, w), (hc, wc) = self.depth_shape, self.color_shape
        self.depth.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
        self.color.from_numpy(np.ascontiguousarray(color, dtype=np.float32))
        kd, kc, T = _vec(K_depth), _vec(K_color), rigid_arg(T_color_depth)
        clear_zbuffer(self.zbuf, hc, wc)
        splat_depth(self.depth, h, w, kd, kc, T, self.zbuf, hc, wc)
        sample_color(self.depth, h, w, kd, kc, T, self.zbuf, self.color, hc, wc, margin, self.out, self.valid)
        out = np.clip(np.rint(self.out.to_numpy()), 0, 255).astype(np.uint8)
        return out, self.valid.to_numpy().astype(bool)
