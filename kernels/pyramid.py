"""Per-frame maps on the Taichi side: depth pyramid, vertex maps and normal maps.

Level 0 is the input resolution (optionally smoothed, see below), or with ``input_level`` L the input
averaged down L times by the same pyramid step; level l is subsampled by 2**l from level 0. The
coarse depth at (u', v') is the average of the 3×3 fine neighbourhood centred on (2u', 2v') over the
pixels within a range of the centre depth, so the average never mixes the two sides of a depth edge, and
pixel u' stays exactly at fine pixel 2u' (intrinsics of level l are ``Intrinsics.downsampled(2**l)``).
On the image border the window is the symmetric part that fits (a one-sided window would bend slanted
surfaces there, and that bend, fixed to the image, would hold ICP back from sliding along a plane).

Smoothing (``pyramid.depth_smooth_radius`` > 0, the role of KinectFusion's bilateral filter): the level-0 depth is
replaced by the mean of the (2r+1)×(2r+1) neighbours within the same range of the centre depth, computed
separably (a row pass, then a column pass, each range-checked against its own centre). Normals from
central differences of raw Kinect-like depth are noisy enough at full resolution that most of them fail
ICP's normal-angle test; r = 2 cuts the normal noise several-fold (its cost: docs/KERNELS.md, pyramid.py).

Speed: Taichi's CPU backend does not vectorise a loop over pixels (the field's root pointer is reloaded
in every iteration, which stops LLVM's loop vectoriser; checked in the generated IR), but LLVM's SLP
vectoriser does turn the same operation on the components of a small vector into SIMD. So the smoothing
passes, the pyramid and the vertex/normal maps take eight pixels of a row per iteration as an 8-vector
(``LANES``, ``Pack``), several times faster than one pixel at a time (docs/KERNELS.md); the packs on the
image border, where a window or a neighbour would fall outside, take a pixel-at-a-time path, written as a
loop rather than unrolled eight times (unrolled, it was most of the compile time). Loops over images smaller than ``SERIAL_BELOW`` pixels run on the calling thread.

Intensity (the photometric tracking term, ``icp.color_weight`` > 0; allocated on first use): per level an
intensity image in [0, 1] (−1 = none) and, for the live frame, (I, ∂I/∂x, ∂I/∂y) with Sobel / 8 (per pixel;
I = −1 on the border and next to a missing intensity). The live frame's grey image (ITU-R 601 weights) is
averaged down like the depth: coarse pixel (u, v) is the [1 2 1] ⊗ [1 2 1] weighted mean of the valid fine
intensities of the 3×3 window centred on (2u, 2v), so it stays aligned with the depth pyramid; the model's
level 0 is the colour of the surfel seen at each pixel (``surfel_intensity_loop``, from the prediction's
``view_index``).

Storage and compilation: Taichi compiles a kernel once per set of fields it is given (a ``ti.template()``
argument is keyed by the field itself), so each pyramid's levels are stacked top to bottom in one field
per quantity (depth, vertex, normal, intensity: level l at rows ``row0[l]`` .. ``row0[l] + H_l``, columns
0 .. W_l) and the kernels take the level's first row and size as runtime arguments: one instance of
``pyramid_down``, ``vertex_normal_maps`` and ICP's passes serves every level of a pyramid, where per-level
fields needed one per level. ``FramePyramid.depth[l]`` (likewise ``vertex``, ``normal``, ``intensity``,
``intensity_grad``) is a ``Level``, a view that reads and writes like an H_l × W_l field inside other
kernels and has ``to_numpy`` / ``from_numpy``. Runtime offsets were chosen over ``ti.types.ndarray``
arguments (one instance per dtype for every pyramid) because an ndarray argument costs more per launch than
a field, and ICP passes four images per launch (docs/KERNELS.md). Allocate FramePyramid
once and reuse them: a new one compiles (or loads) its own instances.
"""


import weakref
from dataclasses import astuple

import numpy as np
import taichi as ti
from taichi.lang import impl as ti_impl
from taichi.lang.util import in_taichi_scope

from ti_fusion.backend import on_cpu, serial_for
from ti_fusion.kernels.common import INT_MAX, LANES, Pack, data_oriented, given
from ti_fusion.kernels.fusion import pack_color, pack_color_loop, pack_color_pixel
from ti_fusion.kernels.surfels import Pool
from ti_fusion.camera import Intrinsics
from ti_fusion.config import PyramidConfig
from ti_fusion.errors import InputError


@data_oriented
class Level:
    """One level of a pyramid stacked in one field: rows ``row0`` .. ``row0`` + H and columns 0 .. W of
    ``field`` (see the module docstring). Inside a kernel it reads and writes like an H × W field
    (``level[v, u]``, ``level.shape``; no struct-for: loop over ``ti.ndrange(*level.shape)``); in Python
    it has ``to_numpy``, ``from_numpy`` and ``fill`` for its own pixels. A plain field is a level at row 0
    of itself (``as_level``)."""

    def __init__(self, field, row0: int, shape):
        self.field = field
        self.row0 = int(row0)
        self.shape = (int(shape[0]), int(shape[1]))

    def __getitem__(self, index):
        v, u = index
        if in_taichi_scope():  # (a field's own ``[]`` is for Python scope only)
            return ti_impl.subscript(None, self.field, v + self.row0, u)
        return self.field[v + self.row0, u]

    @property
    def dtype(self):
        return self.field.dtype

    def to_numpy(self) -> np.ndarray:
        H, W = self.shape
        return np.ascontiguousarray(self.field.to_numpy()[self.row0:self.row0 + H, :W])

    def from_numpy(self, array: np.ndarray) -> None:
        """Set this level's pixels (the rest of the stack is kept: a copy of the whole field, so for
        occasional uploads, not per frame)."""
        array = np.asarray(array)
        if array.shape[:2] != self.shape:
            raise ValueError(f"array of shape {array.shape} given to a level of shape {self.shape}")
        whole = self.field.to_numpy()
        H, W = self.shape
        whole[self.row0:self.row0 + H, :W] = array
        self.field.from_numpy(whole)

    def fill(self, value) -> None:
        whole = self.field.to_numpy()
        H, W = self.shape
        whole[self.row0:self.row0 + H, :W] = value
        self.field.from_numpy(whole)


def as_level(x) -> Level:
    """``x`` itself if it is a ``Level``, else the plain 2-D field ``x`` as the level at its row 0."""
    return x if isinstance(x, Level) else Level(x, 0, x.shape)


@ti.kernel
def copy_rows(src: ti.template(), s0: ti.i32, dst: ti.template(), d0: ti.i32, rows: ti.i32):
    """Rows ``s0`` .. ``s0`` + ``rows`` of ``src`` into rows ``d0`` .. ``d0`` + ``rows`` of ``dst``, every column of
    ``dst`` (stacked fields of the same width, see ``Level``): on the device, where a NumPy round trip would carry
    both whole fields to the host and back."""
    for v, u in ti.ndrange(rows, dst.shape[1]):
        dst[d0 + v, u] = src[s0 + v, u]


def stacked_rows(shapes) -> tuple[list[int], int, int]:
    """(first row of each level, total rows, width) of levels of ``shapes`` stacked top to bottom."""
    row0, rows = [], 0
    for h, _ in shapes:
        row0.append(rows)
        rows += h
    return row0, rows, max(w for _, w in shapes)


@ti.func
def pyramid_pixel(fine: ti.template(), f0, H, W, v, u, max_diff):
    """Coarse pixel (v, u) of ``pyramid_down``, one at a time (the path for the image border); the fine
    image is H × W at row ``f0`` of ``fine``."""
    y0 = 2 * v
    x0 = 2 * u
    c = fine[f0 + y0, x0]
    out = 0.0
    if c > 0:
        # On the image border the window shrinks to the symmetric part that fits (only the centre row
        # or column), so that a slanted surface is not bent towards the edge.
        ry = ti.min(1, ti.min(y0, H - 1 - y0))
        rx = ti.min(1, ti.min(x0, W - 1 - x0))
        # one (sum, count) pair per window row: three short add chains instead of one long one
        total = ti.Vector([0.0, 0.0, 0.0])
        count = ti.Vector([0.0, 0.0, 0.0])
        for dv, du in ti.static(ti.ndrange((-1, 2), (-1, 2))):
            d = fine[f0 + y0 + dv * ry, x0 + du * rx]  # outside the window: re-reads a row/column inside
            ok = (ti.abs(dv) <= ry) & (ti.abs(du) <= rx) & (d > 0) & (ti.abs(d - c) < max_diff)
            total[dv + 1] += ti.select(ok, d, 0.0)
            count[dv + 1] += ti.select(ok, 1.0, 0.0)
        out = total.sum() / count.sum()  # the centre always counts
    return out


@ti.kernel
def pyramid_down(fine: ti.template(), f0: ti.i32, H: ti.i32, W: ti.i32, coarse: ti.template(), c0: ti.i32,
                 max_diff: ti.f32, packed: ti.template(), serial: ti.template()):
    """One level of ``pyramid_loop`` in one launch."""
    pyramid_loop(fine, f0, H, W, coarse, c0, max_diff, packed, serial, None, None, 0)


@ti.func
def pyramid_loop(fine: ti.template(), f0, H, W, coarse: ti.template(), c0, max_diff, packed: ti.template(),
                 serial: ti.template(), color: ti.template(), rgb: ti.template(), color_step):
    """coarse = fine averaged down one level (see the module docstring): the H × W image at row ``f0`` of
    ``fine`` into the one at row ``c0`` of ``coarse`` (levels of stacked fields, see ``Level``); ``packed``:
    coarse is a packed image (``LANES`` pixels per element, see ``smooth_rows``) rather than a plain one.

    Eight coarse pixels of a row per iteration, as 8-vectors (SLP-vectorised, see ``LANES``): each of the
    three fine rows is read once as the 17 pixels the eight 3×3 windows span, and every tap is a fixed
    selection of them. Packs on the image border take the pixel-at-a-time path (``pyramid_pixel``). A
    function with one loop: called at a kernel's top level, that loop is one of the kernel's parallel loops
    (``pyramid_down``). With ``color`` (a field of the coarse image's size, else None) the uint8 RGB image
    ``rgb`` is packed into it in the same loop (``fusion.pack_color_loop``'s pixels, at every ``color_step``-th
    pixel of ``rgb``): a parallel loop fewer (``input_images``)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    Wc = (W + 1) // 2
    for v, b in ti.ndrange((H + 1) // 2, (Wc + LANES - 1) // LANES):
        u0 = b * LANES
        y0 = 2 * v
        if 0 < y0 < H - 1 and 0 < u0 and 2 * (u0 + LANES - 1) + 1 <= W - 1:  # every window is whole
            c = Pack([fine[f0 + y0, 2 * (u0 + l)] for l in ti.static(range(LANES))])
            total = Pack(0.0)
            count = Pack(0.0)
            for dv in ti.static(range(-1, 2)):
                row = ti.Vector([fine[f0 + y0 + dv, 2 * u0 - 1 + k] for k in ti.static(range(2 * LANES + 1))])
                row_total = Pack(0.0)  # per window row, as pyramid_pixel adds them
                row_count = Pack(0.0)
                for du in ti.static(range(-1, 2)):
                    value, counted = range_tap(Pack([row[2 * l + 1 + du] for l in ti.static(range(LANES))]), c,
                                               max_diff)
                    row_total += value
                    row_count += counted
                total += row_total
                count += row_count
            out = ti.select(c > 0, total / ti.max(count, 1.0), 0.0)
            if ti.static(packed):
                coarse[c0 + v, b] = out
            else:
                for l in ti.static(range(LANES)):
                    coarse[c0 + v, u0 + l] = out[l]
        else:
            for l in range(LANES):  # a loop, not unrolled: one copy of the slow path to compile
                u = u0 + l
                if u < Wc:
                    if ti.static(packed):
                        coarse[c0 + v, b][l] = pyramid_pixel(fine, f0, H, W, v, u, max_diff)
                    else:
                        coarse[c0 + v, u] = pyramid_pixel(fine, f0, H, W, v, u, max_diff)
        if ti.static(given(color)):
            for l in range(LANES):
                if u0 + l < Wc:
                    pack_color_pixel(color, rgb, color_step, v, u0 + l)


@ti.func
def range_tap(d, c, max_diff):
    """(value, count) of the taps ``d`` in a range-checked mean about the centres ``c`` (scalars or Packs):
    a tap counts when it is valid and within ``max_diff`` of its centre."""
    ok = (d > 0) & (ti.abs(d - c) < max_diff)
    return ti.select(ok, d, 0.0), ti.select(ok, 1.0, 0.0)


@ti.func
def packed_pixel(src: ti.template(), v, u):
    """Depth of pixel (v, u) of a packed image."""
    return src[v, u // LANES][u % LANES]


@ti.func
def range_mean_at(src: ti.template(), v, u, radius, n, along_rows: ti.template(), max_diff):
    """Range-checked mean of one pixel of a packed image with the symmetric window that fits in the image
    (n pixels along the pass). The slow path of the smoothing passes, for the packs on the image border."""
    c = packed_pixel(src, v, u)
    out = 0.0
    if c > 0:
        i = u if ti.static(along_rows) else v  # position along the pass
        fit = ti.min(radius, i, n - 1 - i)
        total = 0.0
        count = 0.0
        for k in range(-fit, fit + 1):
            value, counted = range_tap(
                packed_pixel(src, v, u + k) if ti.static(along_rows) else packed_pixel(src, v + k, u), c, max_diff)
            total += value
            count += counted
        out = total / count  # the centre always counts
    return out


@ti.kernel
def smooth_rows(src: ti.template(), dst: ti.template(), width: ti.i32, radius: ti.template(), max_diff: ti.f32):
    """``smooth_rows_loop`` in one launch."""
    smooth_rows_loop(src, dst, width, radius, max_diff)


@ti.func
def smooth_rows_loop(src: ti.template(), dst: ti.template(), width, radius: ti.template(), max_diff):
    """The row pass of the range-checked mean on packed images (H × ⌈W/8⌉ packs of 8 pixels): dst = the mean
    of the 2r+1 neighbours along the row that are valid and within ``max_diff`` of the centre; invalid
    stays invalid. Near the image border the window is the symmetric radius that fits (a one-sided window
    would bend a slanted surface towards the image edge)."""
    halo = ti.static((radius + LANES - 1) // LANES)  # packs needed on each side
    for v, b in src:
        u0 = b * LANES
        if u0 >= radius and u0 + LANES - 1 + radius <= width - 1:  # every lane has its whole window
            window = ti.Vector([0.0] * (LANES * (2 * halo + 1)))
            for j in ti.static(range(2 * halo + 1)):
                p = src[v, b - halo + j]
                for l in ti.static(range(LANES)):
                    window[j * LANES + l] = p[l]
            c = src[v, b]
            total = Pack(0.0)
            count = Pack(0.0)
            for k in ti.static(range(-radius, radius + 1)):
                value, counted = range_tap(Pack([window[halo * LANES + l + k] for l in ti.static(range(LANES))]),
                                           c, max_diff)
                total += value
                count += counted
            dst[v, b] = ti.select(c > 0, total / ti.max(count, 1.0), 0.0)
        else:
            for l in range(LANES):  # a loop, not unrolled: one copy of the slow path to compile
                out = 0.0
                if u0 + l < width:
                    out = range_mean_at(src, v, u0 + l, radius, width, True, max_diff)
                dst[v, b][l] = out


@ti.kernel
def smooth_columns(src: ti.template(), dst: ti.template(), radius: ti.template(), max_diff: ti.f32):
    """``smooth_columns_loop`` in one launch."""
    smooth_columns_loop(src, dst, radius, max_diff)


@ti.func
def smooth_columns_loop(src: ti.template(), dst: ti.template(), radius: ti.template(), max_diff):
    """The column pass of the range-checked mean (as ``smooth_rows``, along columns) from a packed H × ⌈W/8⌉
    image into the H × W image at row 0 of ``dst`` (W its width: level 0 of a stack). The 8 lanes of a
    pack share their window, border rows included."""
    H = src.shape[0]
    W = dst.shape[1]
    for v, b in src:
        c = src[v, b]
        total = Pack(0.0)
        count = Pack(0.0)
        if radius <= v < H - radius:  # the whole window: unrolled
            for k in ti.static(range(-radius, radius + 1)):
                value, counted = range_tap(src[v + k, b], c, max_diff)
                total += value
                count += counted
        else:
            fit = ti.min(v, H - 1 - v)
            for k in range(-fit, fit + 1):
                value, counted = range_tap(src[v + k, b], c, max_diff)
                total += value
                count += counted
        out = ti.select(c > 0, total / ti.max(count, 1.0), 0.0)
        for l in ti.static(range(LANES)):
            if b * LANES + l < W:
                dst[v, b * LANES + l] = out[l]


@ti.func
def backproject_pixel(depth: ti.template(), r0, v, u, ifx, ify, cx, cy):
    z = depth[r0 + v, u]
    z = ti.select(z > 0, z, 0.0)  # branch-free: the zero vector falls out of z = 0 (NaN is invalid too)
    return ti.Vector([(u - cx) * ifx * z, (v - cy) * ify * z, z])


@ti.func
def normal_at(depth: ti.template(), r0, H, W, v, u, c, ifx, ify, cx, cy, max_depth_jump):
    """The normal of pixel (v, u) with vertex c: see ``vertex_normal_maps``; one pixel at a time."""
    n = ti.Vector([0.0, 0.0, 0.0])
    if 0 < u < W - 1 and 0 < v < H - 1:
        if c.z > 0:  # holes are common: skip the four neighbours
            l = backproject_pixel(depth, r0, v, u - 1, ifx, ify, cx, cy)
            r = backproject_pixel(depth, r0, v, u + 1, ifx, ify, cx, cy)
            t = backproject_pixel(depth, r0, v - 1, u, ifx, ify, cx, cy)
            b = backproject_pixel(depth, r0, v + 1, u, ifx, ify, cx, cy)
            lo = ti.min(ti.min(l.z, r.z), ti.min(t.z, b.z))
            hi = ti.max(ti.max(l.z, r.z), ti.max(t.z, b.z))
            # all neighbours valid, and max |z_neighbour - z_centre| <= max_depth_jump
            if lo > 0 and hi - c.z <= max_depth_jump and c.z - lo <= max_depth_jump:
                m = (r - l).cross(b - t)
                len2 = m.dot(m)
                if len2 > 0:
                    s = ti.rsqrt(len2)
                    n = m * ti.select(m.dot(c) > 0, -s, s)  # face the camera
    return n


@ti.func
def row_pack(depth: ti.template(), v, u0):
    """Depths of pixels u0 .. u0 + 7 of row v (of the stack), invalid (≤ 0 or NaN) as 0."""
    z = Pack([depth[v, u0 + l] for l in ti.static(range(LANES))])
    return ti.select(z > 0, z, 0.0)


@ti.kernel
def vertex_normal_maps(depth: ti.template(), vertex: ti.template(), normal: ti.template(), r0: ti.i32, H: ti.i32,
                       W: ti.i32, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32, max_depth_jump: ti.f32,
                       serial: ti.template()):
    """One level of ``vertex_normal_loop`` in one launch."""
    vertex_normal_loop(depth, vertex, normal, r0, H, W, fx, fy, cx, cy, max_depth_jump, serial)


@ti.func
def vertex_normal_loop(depth: ti.template(), vertex: ti.template(), normal: ti.template(), r0, H, W, fx, fy, cx,
                       cy, max_depth_jump, serial: ti.template()):
    """vertex[v, u] = ((u - cx) z / fx, (v - cy) z / fy, z), zero where the depth is invalid (≤ 0 or NaN);
    normal[v, u] = the cross product of central differences of the vertices, facing the camera, zero where
    undefined: on the image border, where the pixel or one of its four neighbours is invalid, or where a
    neighbour's depth differs from the centre's by more than ``max_depth_jump`` (a depth edge).

    One pass: the neighbours' vertices are back-projected again where they are needed rather than read
    back from the vertex map, so the two maps cost one loop (and one thread-pool dispatch) instead of two.
    Eight pixels of a row per iteration, as 8-vectors (see ``LANES``): LLVM's SLP vectoriser turns their
    arithmetic into SIMD. Packs on the image border, where a neighbour would fall outside, take the pixel-at-a-time
    path. The three images are the H × W level at row ``r0`` of their stacked fields (see ``Level``). A
    function with one loop, as ``pyramid_loop``.
    """
    ifx = 1.0 / fx
    if ti.static(serial):
        ti.loop_config(serialize=True)  # one division per launch, not two per pixel
    ify = 1.0 / fy
    for v, b in ti.ndrange(H, (W + LANES - 1) // LANES):  # a range-for: ``serialize`` skips a struct-for
        vertex_normal_pack(depth, vertex, normal, r0, H, W, v, b, ifx, ify, cx, cy, max_depth_jump)


@ti.func
def vertex_normal_pack(depth: ti.template(), vertex: ti.template(), normal: ti.template(), r0, H, W, v, b, ifx, ify,
                       cx, cy, max_depth_jump):
    """Pixels 8b .. 8b + 7 of row v of ``vertex_normal_loop`` (``ifx``, ``ify``: 1 / fx, 1 / fy)."""
    u0 = b * LANES
    if 0 < v < H - 1 and 0 < u0 and u0 + LANES < W:  # every lane has its four neighbours
        xs = Pack([(u0 + l - cx) * ifx for l in ti.static(range(LANES))])
        y = (v - cy) * ify
        zc = row_pack(depth, r0 + v, u0)
        for l in ti.static(range(LANES)):
            vertex[r0 + v, u0 + l] = ti.Vector([xs[l] * zc[l], y * zc[l], zc[l]])
        # left and right neighbours: the row pack shifted by one pixel
        row = ti.Vector([0.0] * (LANES + 2))
        row[0] = ti.select(depth[r0 + v, u0 - 1] > 0, depth[r0 + v, u0 - 1], 0.0)
        row[LANES + 1] = ti.select(depth[r0 + v, u0 + LANES] > 0, depth[r0 + v, u0 + LANES], 0.0)
        for l in ti.static(range(LANES)):
            row[l + 1] = zc[l]
        zl = Pack([row[l] for l in ti.static(range(LANES))])
        zr = Pack([row[l + 2] for l in ti.static(range(LANES))])
        zt = row_pack(depth, r0 + v - 1, u0)
        zb = row_pack(depth, r0 + v + 1, u0)
        xl = Pack([(u0 + l - 1 - cx) * ifx for l in ti.static(range(LANES))])
        xr = Pack([(u0 + l + 1 - cx) * ifx for l in ti.static(range(LANES))])
        yt = (v - 1 - cy) * ify
        yb = (v + 1 - cy) * ify
        # m = (r − l) × (b − t), with r − l and b − t from the back-projected neighbours
        ax = xr * zr - xl * zl
        ay = y * zr - y * zl
        az = zr - zl
        bx = xs * zb - xs * zt
        by = yb * zb - yt * zt
        bz = zb - zt
        mx = ay * bz - az * by
        my = az * bx - ax * bz
        mz = ax * by - ay * bx
        lo = ti.min(ti.min(zl, zr), ti.min(zt, zb))
        hi = ti.max(ti.max(zl, zr), ti.max(zt, zb))
        len2 = mx * mx + my * my + mz * mz
        ok = (zc > 0) & (lo > 0) & (hi - zc <= max_depth_jump) & (zc - lo <= max_depth_jump) & (len2 > 0)
        s = ti.rsqrt(ti.select(ok, len2, 1.0))
        s = ti.select(mx * xs * zc + my * y * zc + mz * zc > 0, -s, s)  # face the camera
        nx = ti.select(ok, mx * s, 0.0)
        ny = ti.select(ok, my * s, 0.0)
        nz = ti.select(ok, mz * s, 0.0)
        for l in ti.static(range(LANES)):
            normal[r0 + v, u0 + l] = ti.Vector([nx[l], ny[l], nz[l]])
    else:
        for l in range(LANES):  # a loop, not unrolled: one copy of the slow path to compile
            u = u0 + l
            if u < W:
                c = backproject_pixel(depth, r0, v, u, ifx, ify, cx, cy)
                vertex[r0 + v, u] = c
                normal[r0 + v, u] = normal_at(depth, r0, H, W, v, u, c, ifx, ify, cx, cy, max_depth_jump)


# ``maps_levels``' per-level settings, one row per level: first row in the stack,
# height, width, fx, fy, cx, cy, the depth-jump threshold of the normals
G_ROW0, G_H, G_W, G_FX, G_FY, G_CX, G_CY, G_JUMP, N_GEOMETRY = range(9)


@ti.kernel
def maps_levels(depth: ti.template(), vertex: ti.template(), normal: ti.template(), geometry: ti.template(),
                levels: ti.template(), first_maps: ti.i32, serial: ti.template(), shift: ti.i32):
    """``maps_levels_loops`` in one launch."""
    maps_levels_loops(depth, vertex, normal, geometry, levels, first_maps, serial, shift)


@ti.kernel
def input_images(fine: ti.types.ndarray(dtype=ti.f32, ndim=2), raw: ti.template(), max_diff: ti.f32,
                 serial_input: ti.template(), grey: ti.types.ndarray(dtype=ti.f32, ndim=2), intensity: ti.template(),
                 with_grey: ti.template(), rgb: ti.types.ndarray(dtype=ti.u8, ndim=3), color: ti.template(),
                 color_step: ti.i32, with_color: ti.template(), color_in_pyramid: ti.template()):
    """Every loop of a frame's maps that reads the caller's arrays, for an input averaged down once and
    smoothed (the default at 640×480): ``pyramid_loop`` from the input image ``fine`` (not copied first)
    into the packed ``raw``; with ``with_grey``, the grey image ``grey`` averaged down into level 0 of
    ``intensity``; with ``with_color``, the uint8 RGB image ``rgb`` packed into ``color``
    (``pack_color_loop``; with ``color_in_pyramid``, where ``color`` is of ``raw``'s size, inside the
    pyramid's loop: a parallel loop fewer). Off the CPU each array argument is copied back after the launch, a wait, so
    depth, grey and colour cross together; the rest of the maps are launches of their own
    (``FramePyramid._input_launches``)."""
    H, W = fine.shape
    if ti.static(with_color and color_in_pyramid):
        pyramid_loop(fine, 0, H, W, raw, 0, max_diff, True, serial_input, color, rgb, color_step)
    else:
        pyramid_loop(fine, 0, H, W, raw, 0, max_diff, True, serial_input, None, None, 0)
    if ti.static(with_grey):
        intensity_down_loop(grey, 0, H, W, intensity, 0, serial_input)
    if ti.static(with_color and not color_in_pyramid):
        pack_color_loop(color, rgb, color_step)


@ti.kernel
def smooth_depth(raw: ti.template(), rows: ti.template(), depth: ti.template(), width: ti.i32,
                 radius: ti.template(), max_diff: ti.f32):
    """The smoothing's row and column passes (``smooth_rows_loop``, ``smooth_columns_loop``) in one launch:
    the packed level-0 depth ``raw`` into level 0 of ``depth``."""
    smooth_rows_loop(raw, rows, width, radius, max_diff)
    smooth_columns_loop(rows, depth, radius, max_diff)


@ti.func
def maps_levels_loops(depth: ti.template(), vertex: ti.template(), normal: ti.template(), geometry: ti.template(),
                      levels: ti.template(), first_maps, serial: ti.template(), shift):
    """The vertex and normal maps of levels ``first_maps`` .. levels − 1 of a stack (``vertex_normal_loop``'s
    packs) in one loop over the packs of every level, each pack with its level's row, size and intrinsics
    from ``geometry``: one copy of the per-pack code for every level (one loop per level compiled several times
    as long: docs/PERFORMANCE.md, "The frame's maps as five kernels"). ``first_maps`` is a runtime value (the
    levels before it have no packs in the loop), so that one instance serves a rendered model, whose level 0
    maps come from the renderer, and depth uploaded into the same maps (loop verification's keyframes). The rows
    in ``geometry`` are the stack's own, and its levels lie ``shift`` rows further down the fields (a stack in the
    fields of another, ``FramePyramid.pair``: the same geometry and the same instance for both).

    The loop runs over the packs of those levels only, numbered level by level (a level's H × ⌈W/8⌉ packs row by
    row): a loop over every row of the stack and the widest level's packs spent most of its iterations on
    skipping (three quarters of them for a rendered model's levels 1 and 2)."""
    start = ti.Vector([0] * levels)  # the first pack of each level in the loop's numbering
    total = 0
    for l in ti.static(range(levels)):
        start[l] = total
        if l >= first_maps:
            total += ti.cast(geometry[l, G_H], ti.i32) * ((ti.cast(geometry[l, G_W], ti.i32) + LANES - 1) // LANES)
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for k in range(total):
        l = 0  # the levels before first_maps have no packs: their starts are 0, below every k
        first = 0  # the first pack of level l (static indices only: no dynamic index into a local vector)
        for m in ti.static(range(1, levels)):
            l += ti.select(k >= start[m], 1, 0)
            first = ti.select(k >= start[m], start[m], first)
        W = ti.cast(geometry[l, G_W], ti.i32)
        packs = (W + LANES - 1) // LANES
        r = k - first
        vertex_normal_pack(depth, vertex, normal, ti.cast(geometry[l, G_ROW0], ti.i32) + shift,
                           ti.cast(geometry[l, G_H], ti.i32), W, r // packs, r % packs, 1.0 / geometry[l, G_FX],
                           1.0 / geometry[l, G_FY], geometry[l, G_CX], geometry[l, G_CY], geometry[l, G_JUMP])


GREY = (0.299, 0.587, 0.114)  # ITU-R BT.601 luma weights of R, G, B
_NO_GREY = np.zeros((1, 1), np.float32)  # input_images' grey argument when it has none
_NO_RGB = np.zeros((1, 1, 3), np.uint8)  # and its colour argument


@ti.kernel
def intensity_down(fine: ti.template(), f0: ti.i32, H: ti.i32, W: ti.i32, coarse: ti.template(), c0: ti.i32,
                   serial: ti.template()):
    """One level of ``intensity_down_loop`` in one launch."""
    intensity_down_loop(fine, f0, H, W, coarse, c0, serial)


@ti.func
def intensity_down_loop(fine: ti.template(), f0, H, W, coarse: ti.template(), c0, serial: ti.template()):
    """coarse = fine averaged down one level: the [1 2 1] ⊗ [1 2 1] weighted mean of the valid (≥ 0) fine
    intensities in the 3×3 window centred on (2v, 2u) that lie inside the image; −1 where none is valid.
    The H × W image at row ``f0`` of ``fine`` into the ⌈H/2⌉ × ⌈W/2⌉ one at row ``c0`` of ``coarse``."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for v, u in ti.ndrange((H + 1) // 2, (W + 1) // 2):
        total = 0.0
        weight = 0.0
        for dv, du in ti.static(ti.ndrange((-1, 2), (-1, 2))):
            y = 2 * v + dv
            x = 2 * u + du
            if 0 <= y < H and 0 <= x < W:
                i = fine[f0 + y, x]
                if i >= 0:
                    w = ti.static(float((2 - abs(dv)) * (2 - abs(du))))
                    total += w * i
                    weight += w
        coarse[c0 + v, u] = ti.select(weight > 0, total / ti.max(weight, 1.0), -1.0)


@ti.func
def intensity_levels_loops(stack: ti.template(), rows: ti.template(), serial: ti.template()):
    """Each level of ``stack`` after the first averaged down from the one above (``intensity_down_loop``),
    one loop per level in order; ``rows``: the levels' (first row, height, width)."""
    for l in ti.static(range(1, len(rows))):
        intensity_down_loop(stack, rows[l - 1][0], rows[l - 1][1], rows[l - 1][2], stack, rows[l][0], serial)


@ti.func
def intensity_gradient_loop(image: ti.template(), out: ti.template(), r0, H, W, serial: ti.template()):
    """out[v, u] = (I, ∂I/∂x, ∂I/∂y), the derivatives by Sobel / 8 (intensity per pixel); (−1, 0, 0) on the
    image border and where any of the 3×3 window has no intensity. Both the H × W level at row ``r0``."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for v, u in ti.ndrange(H, W):
        res = ti.Vector([-1.0, 0.0, 0.0])
        if 0 < v < H - 1 and 0 < u < W - 1:
            a = ti.Matrix([[image[r0 + v + dv, u + du] for du in ti.static(range(-1, 2))]
                           for dv in ti.static(range(-1, 2))])
            lo = a.min()
            if lo >= 0:
                gx = ((a[0, 2] + 2.0 * a[1, 2] + a[2, 2]) - (a[0, 0] + 2.0 * a[1, 0] + a[2, 0])) / 8.0
                gy = ((a[2, 0] + 2.0 * a[2, 1] + a[2, 2]) - (a[0, 0] + 2.0 * a[0, 1] + a[0, 2])) / 8.0
                res = ti.Vector([a[1, 1], gx, gy])
        out[r0 + v, u] = res


@ti.kernel
def intensity_maps(fine: ti.template(), stack: ti.template(), grad: ti.template(), rows: ti.template(),
                   from_fine: ti.template(), serial_input: ti.template(), serial: ti.template()):
    """A live frame's intensity pyramid and gradients in one launch (``intensity_maps_loops``)."""
    intensity_maps_loops(fine, stack, grad, rows, from_fine, serial_input, serial)


@ti.kernel
def intensity_input_maps(fine: ti.types.ndarray(dtype=ti.f32, ndim=2), stack: ti.template(), grad: ti.template(),
                         rows: ti.template(), serial_input: ti.template(), serial: ti.template()):
    """``intensity_maps`` from the caller's grey image averaged down once (no copy into a field first)."""
    intensity_maps_loops(fine, stack, grad, rows, True, serial_input, serial)


@ti.func
def intensity_maps_loops(fine: ti.template(), stack: ti.template(), grad: ti.template(), rows: ti.template(),
                         from_fine: ti.template(), serial_input: ti.template(), serial: ti.template()):
    """With ``from_fine``, the grey image ``fine`` averaged down into level 0 of ``stack`` first; then each
    level from the one above, then every level's gradients into ``grad`` (consecutive loops of one kernel,
    run in order). ``rows``: the levels' (first row, height, width), compile-time constants of the pyramid."""
    if ti.static(from_fine):
        H, W = fine.shape
        intensity_down_loop(fine, 0, H, W, stack, 0, serial_input)
    intensity_levels_loops(stack, rows, serial)
    for l in ti.static(range(len(rows))):
        intensity_gradient_loop(stack, grad, rows[l][0], rows[l][1], rows[l][2], serial)


@ti.func
def surfel_intensity_loop(view_index: ti.template(), color: ti.template(), out: ti.template(), serial: ti.template(),
                          r0: ti.template()):
    """out[r0 + v, u] = the grey level in [0, 1] of the surfel seen at the pixel (``color`` RGB in [0, 255]), −1
    where none is (``view_index`` INT_MAX); ``out`` level 0 of a stack (at row ``r0``), of ``view_index``'s size."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    H, W = view_index.shape
    for v, u in ti.ndrange(H, W):
        i = view_index[v, u]
        g = -1.0
        if i != INT_MAX:
            c = color[i]
            g = (GREY[0] * c[0] + GREY[1] * c[1] + GREY[2] * c[2]) / 255.0
        out[r0 + v, u] = g


@ti.kernel
def surfel_intensity_maps(view_index: ti.template(), color: ti.template(), stack: ti.template(),
                          rows: ti.template(), serial: ti.template()):
    """The model's intensity pyramid in one launch: ``surfel_intensity_loop`` into level 0 of ``stack``,
    then ``intensity_levels_loops`` (``rows`` as in ``intensity_maps``)."""
    surfel_intensity_loop(view_index, color, stack, serial, rows[0][0])
    intensity_levels_loops(stack, rows, serial)


def grey_image(color: np.ndarray) -> np.ndarray:
    """uint8 H×W×3 RGB → float32 H×W grey levels in [0, 1] (``GREY`` weights, OpenCV's, rounded to 1/255: a
    third of the time of the same in float32 NumPy)."""
    import cv2

    return cv2.cvtColor(np.ascontiguousarray(color, dtype=np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32) \
        * np.float32(1.0 / 255.0)


def jpeg_blockiness(grey: np.ndarray) -> float:
    """How strongly a grey image shows the block grid of JPEG compression: 1 for none, about 3-4 for the real
    TUM keyframes (re-encoded JPEG) and synthetic colour through JPEG at quality 75 (docs/PHOTOMETRIC.md).

    Along every few rows (and columns; about 60 of each), a step between neighbouring pixels that is larger
    than both its neighbouring steps is a peak; JPEG's 8×8 blocks put more peaks at one phase of the pixel
    index modulo 8 (4 in a frame subsampled by 2). The measure is the share of peaks at the phase with the most
    over the mean share at the others, the smaller of the rows' and columns' figures, the larger of periods 8
    and 4; 1 for an image too small (under 16 periods a side) or too flat to tell. Counting peaks rather than
    summing steps keeps a few strong edges at one phase from reading as a grid, and a peak count does not grow
    with the image's noise or contrast. Host NumPy on the grey image the frame's intensity is built from (no
    launch, no read-back)."""
    g = np.asarray(grey, dtype=np.float32)
    step = max(1, min(g.shape) // 60)
    profiles = []  # per axis: the share of the lines with a peak at each pixel index
    for lines in (g[::step], np.ascontiguousarray(g[:, ::step].T)):
        d = np.abs(lines[:, 1:] - lines[:, :-1])
        mid = d[:, 1:-1]
        peak = (mid > d[:, :-2]) & (mid > d[:, 2:])
        profiles.append(np.count_nonzero(peak, axis=0) / max(peak.shape[0], 1))
    found = []
    for period in (8, 4):
        ratios = []
        for profile in profiles:
            n = len(profile) // period * period
            if n < 16 * period:  # too few blocks: a smooth pattern's peaks can line up with a phase by chance
                break
            share = profile[:n].reshape(-1, period).mean(axis=0)
            top = int(np.argmax(share))
            ratios.append((share[top] + 1e-3) / (np.delete(share, top).mean() + 1e-3))  # a flat image: 1
        if len(ratios) == 2:
            found.append(min(ratios))
    return float(max(found)) if found else 1.0


def _level_shapes(height: int, width: int, levels: int = 3, input_level: int = 0) -> list[tuple[int, int]]:
    """The (height, width) of each level of ``FramePyramid(settings, height, width, levels, input_level)``."""
    for _ in range(input_level):
        height, width = (height + 1) // 2, (width + 1) // 2
    shapes = []
    for _ in range(levels):
        shapes.append((height, width))
        height, width = (height + 1) // 2, (width + 1) // 2
    return shapes


@data_oriented
class FramePyramid:
    """Depth, vertex and normal maps of one frame at every pyramid level (camera frame, metres).

        pyramid = FramePyramid(config.pyramid, height, width, levels, input_level)
        pyramid.compute(depth, intrinsics)

    ``depth[l]``, ``vertex[l]``, ``normal[l]`` (and ``intensity[l]``, ``intensity_grad[l]``) are ``Level``
    views of level l of one stacked field per quantity (module docstring).
    """

    def __init__(self, settings: PyramidConfig, height: int, width: int, levels: int = 3, input_level: int = 0,
                 _pair_room: bool = False, _stack_of: "FramePyramid | None" = None):
        """Maps of ``levels`` levels for depth images of ``height`` × ``width``, built with ``settings``
        (resolved here, once: the smoothing radius for this size, the range check of the depth means).
        With ``input_level`` L > 0 the input is first averaged down L times (``pyramid_down``) and level 0
        is that 2**L times smaller image: the fine resolution is never smoothed or back-projected, which is
        what makes it cheaper."""
        self.input_shape = (height, width)
        self.input_level = int(input_level)
        self._inputs = []  # input_level > 0: the input and the intermediate averaged images
        for _ in range(self.input_level):
            self._inputs.append(ti.field(ti.f32, shape=(height, width)))
            height, width = (height + 1) // 2, (width + 1) // 2
        self.height, self.width, self.levels = height, width, levels
        self.max_depth_jump = float(settings.normal_max_depth_jump)
        self.max_depth_diff = 3.0 * float(settings.depth_sigma)  # the range check of the depth means
        if not self.max_depth_diff > 0:  # every range check would reject even the centre pixel
            raise InputError(None, f"pyramid.depth_sigma must be positive, not {settings.depth_sigma}")
        self.smooth_radius = int(settings.smooth_radius(width))
        self.shapes = _level_shapes(height, width, levels)
        self.row0, rows, _ = stacked_rows(self.shapes)
        # ``pair``: the second pyramid's levels lie in the first's fields, ``_shift`` rows down (below the first's
        # levels and spare rows), so that both build their maps with the same kernel instances
        self._shift = 0 if _stack_of is None else _stack_of._pair_shift
        self._pair_shift = rows + height if _pair_room else 0
        self.row0 = [r + self._shift for r in self.row0]
        self._rows = tuple((r, h, w) for r, (h, w) in zip(self.row0, self.shapes))  # template argument
        self._stack_shape = (2 * rows + height if _pair_room or _stack_of is not None else rows, width)
        if _stack_of is None:
            # the depth's field has one level 0 more below the levels (``spare_depth``: the render's filled depth,
            # ``SurfelMapper.render_pyramid``), so that a level built from it shares the levels' compiled instance
            depth = ti.field(ti.f32, shape=(2 * (rows + height) if _pair_room else rows + height, width))
            vertex = ti.Vector.field(3, ti.f32, shape=self._stack_shape)
            normal = ti.Vector.field(3, ti.f32, shape=self._stack_shape)
        else:
            depth, vertex, normal = _stack_of.depth[0].field, _stack_of.vertex[0].field, _stack_of.normal[0].field
        self.depth = self._levels(depth)
        self.spare_depth = Level(depth, self._shift + rows, self.shapes[0])
        self.vertex = self._levels(vertex)
        self.normal = self._levels(normal)
        self.intrinsics: list[Intrinsics] = []
        # one choice for every level (a per-level one would compile an instance per choice): the loops run on
        # the calling thread when level 0 is small (tests), and the coarse levels of larger ones in parallel
        self._serial = serial_for(height * width)
        self._packed = None  # when smoothing: the level-0 depth before and after the row pass, packed
        # the photometric term's images (``compute_intensity``, ``intensity_from_surfels``), on first use
        self.intensity: list | None = None  # per level, f32 in [0, 1], −1 = none
        self.intensity_grad: list | None = None  # per level, (I, ∂I/∂x, ∂I/∂y) (live frames only)
        self.blockiness = float("nan")  # ``jpeg_blockiness`` of the last grey image given (live frames only)
        self._grey_inputs: list = []  # input_level > 0: the grey input and the intermediate averaged images
        # the levels' rows (the stack's own), sizes and intrinsics (G_* columns) for the maps' kernels, and the
        # intrinsics it holds: shared with a pyramid in the same fields (``pair``), which uploads its own when
        # they differ
        self._geo = _stack_of._geo if _stack_of is not None else {"field": None, "for": None}
        # the frame's colour packed for the fusion step (``compute(..., color=...)``): per level, on first use
        self._color: dict[int, object] = {}
        self._color_source = None  # (weak reference to the image, level) the last ``compute`` packed, else None

    @classmethod
    def lent_to(cls, owner, settings: PyramidConfig, height: int, width: int, levels: int = 3,
                input_level: int = 0) -> "FramePyramid":
        """``FramePyramid(settings, height, width, levels, input_level)`` for ``owner``'s lifetime, the
        same object a collected owner had for the same arguments where there is one (``Pool.lend``): its
        kernels are compiled already. Every map is rebuilt by ``compute``, so nothing of the last owner's
        frames is read; a reference to it kept after its owner is gone sees the next owner's frames."""
        key = (cls, astuple(settings), height, width, levels, input_level)
        return Pool.lend(owner, key, lambda: cls(settings, height, width, levels, input_level))

    @classmethod
    def pair(cls, settings: PyramidConfig, first: tuple, second: tuple) -> tuple["FramePyramid", "FramePyramid"]:
        """``FramePyramid(settings, *first)`` and ``FramePyramid(settings, *second)`` (each ``(height, width, levels,
        input_level)``); where their levels have the same sizes, the second's lie in the first's fields (below the
        first's rows), so that building either pyramid runs the same kernel instances (``pyramid_down``,
        ``maps_levels``), loaded in every process or compiled with an empty kernel cache once, not twice
        (docs/PERFORMANCE.md, "The warm run's fixed cost, again"). The second is then built from a render or a
        stored depth (``compute_from_field``), not ``compute``."""
        if _level_shapes(*first) != _level_shapes(*second):
            return cls(settings, *first), cls(settings, *second)
        one = cls(settings, *first, _pair_room=True)
        return one, cls(settings, *second, _stack_of=one)

    @classmethod
    def pair_lent_to(cls, owner, settings: PyramidConfig, first: tuple, second: tuple) -> tuple["FramePyramid",
                                                                                               "FramePyramid"]:
        """``pair(settings, first, second)`` for ``owner``'s lifetime, as ``lent_to`` lends one pyramid."""
        key = (cls, "pair", astuple(settings), tuple(first), tuple(second))
        return Pool.lend(owner, key, lambda: cls.pair(settings, first, second))

    def _levels(self, stack) -> list[Level]:
        return [Level(stack, r, s) for r, s in zip(self.row0, self.shapes)]

    def _upload_level0(self, stack, image: np.ndarray) -> None:
        """Level 0 of ``stack`` = ``image`` in one copy (the coarse levels' rows are zeroed: the pyramid is
        rebuilt from level 0 right after; a pair's other rows are kept)."""
        whole = stack.to_numpy() if self._pair_shift else np.zeros(tuple(stack.shape), dtype=np.float32)
        whole[:self.height] = image
        stack.from_numpy(whole)

    def compute(self, depth: np.ndarray, intrinsics: Intrinsics, grey: np.ndarray | None = None,
                color: np.ndarray | None = None, color_level: int = 0) -> None:
        """Upload a float32 depth image (metres, 0 = invalid) and build every level's maps; with ``grey``,
        the intensity pyramid too (``compute_intensity``); with ``color`` (uint8 RGB of the input's size),
        that image packed at level ``color_level`` for the fusion step (``packed_color``). The images given
        cross in one launch where the layout allows: off the CPU every image given to a launch is a wait for
        the device.

        With a smoothing radius r > 0 the depth is first replaced by its range-checked (2r+1)² mean (see the
        module docstring); ``depth[0]`` then holds the smoothed depth."""
        if depth.shape != self.input_shape:
            raise ValueError(f"depth of shape {depth.shape} given to FramePyramid of shape {self.input_shape}")
        if self._shift:  # its level 0 would be written at the fields' first rows, the other pyramid's
            raise ValueError("the second pyramid of a pair (FramePyramid.pair) is built by compute_from_field")
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        if grey is not None:
            grey = self._checked_grey(grey)
        self._color_source = None
        packed = self._checked_color(color, color_level) if color is not None else None
        if not self._input_launches(depth, intrinsics, grey, packed):
            self._compute_depth(depth, intrinsics)
            if grey is not None:
                self._intensity_maps(grey)
            if packed is not None:
                pack_color(packed[1], packed[0], packed[2])
        if packed is not None:  # weakly: the pyramid does not keep the frame's image alive
            self._color_source = (weakref.ref(color), int(color_level))

    def packed_color(self, level: int, color: np.ndarray):
        """The frame's colour packed r | g << 8 | b << 16 at ``level`` (a Taichi field of ``shapes[level]``)
        if the last ``compute`` packed this very image (``color``, the same object) at that level, else
        None."""
        source = self._color_source
        if source is None or source[0]() is not color or source[1] != level:
            return None
        return self._color[level]

    def _checked_color(self, color: np.ndarray, level: int):
        """(rgb as uint8 C-contiguous, the level's packed field, the step from the input) for ``compute``;
        ValueError for another size or a level this pyramid does not have."""
        if not 0 <= level < self.levels:
            raise ValueError(f"color_level {level} of a pyramid of {self.levels} levels")
        if color.shape != (*self.input_shape, 3):
            raise ValueError(f"colour of shape {color.shape} given to FramePyramid of shape {self.input_shape}")
        if level not in self._color:
            self._color[level] = ti.field(ti.i32, shape=self.shapes[level])
        return np.ascontiguousarray(color, dtype=np.uint8), self._color[level], 2**(self.input_level + level)

    def _compute_depth(self, depth: np.ndarray, intrinsics: Intrinsics) -> None:
        """``compute`` of the depth for a layout ``_input_launches`` does not take, in several launches."""
        smooth = self.smooth_radius > 0
        stack = self.depth[0].field
        if self.input_level == 0:
            if smooth:
                self._packed_fields()[0].from_numpy(self._pack(depth))
            else:
                self._upload_level0(stack, depth)
        else:
            intrinsics = intrinsics.downsampled(2**self.input_level)
            self._inputs[0].from_numpy(depth)
            # the last step writes the smoothing's packed input, or level 0 of the stack
            targets = self._inputs[1:] + [self._packed_fields()[0] if smooth else stack]
            for i, (fine, coarse) in enumerate(zip(self._inputs, targets)):
                h, w = fine.shape
                packed = smooth and i == len(targets) - 1
                pyramid_down(fine, 0, h, w, coarse, 0, self.max_depth_diff, packed,
                             serial_for(((h + 1) // 2) * ((w + 1) // 2)))
        if smooth:
            raw, rows = self._packed
            smooth_rows(raw, rows, self.width, self.smooth_radius, self.max_depth_diff)
            smooth_columns(rows, stack, self.smooth_radius, self.max_depth_diff)
        self.compute_from_field(intrinsics)

    def _input_launches(self, depth: np.ndarray, intrinsics: Intrinsics, grey: np.ndarray | None, packed) -> bool:
        """``compute`` of an input averaged down once and smoothed (the default at 640×480), with the
        intensity pyramid of ``grey`` and the colour ``packed`` (from ``_checked_color``) if given: the
        caller's arrays in one launch (``input_images``), then the smoothing, the pyramid, the maps and the
        intensity levels, a launch each; False for any other layout. Kernels rather than one: Taichi's
        compile time grows faster than the kernel (docs/PERFORMANCE.md, "The frame's maps as five kernels")."""
        if self.input_level != 1 or self.smooth_radius <= 0:
            return False
        self._set_geometry(intrinsics.downsampled(2))
        raw, rows = self._packed_fields()
        h, w = self.input_shape
        serial_input = serial_for(((h + 1) // 2) * ((w + 1) // 2))
        intensity = self.intensity[0].field if grey is not None else 0
        colour = packed if packed is not None else (_NO_RGB, 0, 0)  # not read: with_color is off
        # the colour packed inside the pyramid's loop where it is of the loop's size (on the CPU: a
        # parallel loop fewer; elsewhere the loops' order does not cost a dispatch)
        in_pyramid = packed is not None and tuple(packed[1].shape) == (self.height, self.width) \
            and on_cpu()
        input_images(depth, raw, self.max_depth_diff, serial_input, grey if grey is not None else _NO_GREY,
                     intensity, grey is not None, *colour, packed is not None, in_pyramid)
        stack = self.depth[0].field
        smooth_depth(raw, rows, stack, self.width, self.smooth_radius, self.max_depth_diff)
        self._levels_and_maps(0)
        if grey is not None:
            intensity_maps(intensity, intensity, self.intensity_grad[0].field, self._rows, False, self._serial,
                           self._serial)
        return True

    def _checked_grey(self, grey: np.ndarray) -> np.ndarray:
        """``grey`` as float32 C-contiguous, with the intensity fields allocated and its ``blockiness`` measured;
        ValueError for another size."""
        if grey.shape != self.input_shape:
            raise ValueError(f"grey image of shape {grey.shape} given to FramePyramid of shape {self.input_shape}")
        self._intensity_fields(True)
        grey = np.ascontiguousarray(grey, dtype=np.float32)
        self.blockiness = jpeg_blockiness(grey)
        return grey

    def _intensity_fields(self, gradients: bool) -> None:
        if self.intensity is None:
            self.intensity = self._levels(ti.field(ti.f32, shape=self._stack_shape))
        if gradients and self.intensity_grad is None:
            self.intensity_grad = self._levels(ti.Vector.field(3, ti.f32, shape=self._stack_shape))

    def compute_intensity(self, grey: np.ndarray) -> None:
        """The live frame's intensity pyramid and gradients from a float32 grey image of the input's size
        (``grey_image``; values in [0, 1], negative = none), averaged down like the depth."""
        if self._shift:  # its level 0 would be written at the field's first rows
            raise ValueError("the second pyramid of a pair (FramePyramid.pair) takes its intensity from surfels")
        self._intensity_maps(self._checked_grey(grey))

    def _intensity_maps(self, grey: np.ndarray) -> None:
        """``compute_intensity`` of a grey image ``_checked_grey`` returned."""
        stack, grad = self.intensity[0].field, self.intensity_grad[0].field
        if self.input_level == 0:
            self._upload_level0(stack, grey)
            intensity_maps(stack, stack, grad, self._rows, False, self._serial, self._serial)
            return
        if self.input_level == 1:  # the default at 640×480: one launch, no copy first
            h, w = self.input_shape
            intensity_input_maps(grey, stack, grad, self._rows, serial_for(((h + 1) // 2) * ((w + 1) // 2)),
                                 self._serial)
            return
        if not self._grey_inputs:
            self._grey_inputs = [ti.field(ti.f32, shape=f.shape) for f in self._inputs]
        self._grey_inputs[0].from_numpy(grey)
        for fine, coarse in zip(self._grey_inputs, self._grey_inputs[1:]):  # input_level > 1
            h, w = fine.shape
            intensity_down(fine, 0, h, w, coarse, 0, serial_for(((h + 1) // 2) * ((w + 1) // 2)))
        h, w = self._grey_inputs[-1].shape
        intensity_maps(self._grey_inputs[-1], stack, grad, self._rows, True,
                       serial_for(((h + 1) // 2) * ((w + 1) // 2)), self._serial)

    def intensity_from_surfels(self, view_index, color) -> None:
        """The model's intensity pyramid: level 0 the grey level of the surfel seen at each pixel
        (``view_index`` of a prediction of this size, ``color`` the surfels' RGB field), the others averaged
        down; no gradients (the model's intensity is compared, the live frame's differentiated)."""
        if tuple(view_index.shape) != self.shapes[0]:
            raise ValueError(f"view_index of shape {view_index.shape} for maps of shape {self.shapes[0]}")
        self._intensity_fields(False)
        surfel_intensity_maps(view_index, color, self.intensity[0].field, self._rows, self._serial)

    def _packed_fields(self):
        """The packed level-0 images of the smoothing (allocated when smoothing is first asked for)."""
        if self._packed is None:
            shape = (self.height, -(-self.width // LANES))
            self._packed = (Pack.field(shape=shape), Pack.field(shape=shape))
        return self._packed

    def _pack(self, depth: np.ndarray) -> np.ndarray:
        """H × W → H × ⌈W/8⌉ × 8 (zero-padded): the memory layout of the packed field, for ``from_numpy``."""
        H, W = depth.shape
        packs = -(-W // LANES)
        if packs * LANES != W:
            depth = np.pad(depth, ((0, 0), (0, packs * LANES - W)))
        return depth.reshape(H, packs, LANES)

    def compute_from_field(self, intrinsics: Intrinsics, level0_maps: bool = True, level1_from=None) -> None:
        """Build every level from ``self.depth[0]`` already on the Taichi side (without level 0's vertex
        and normal maps when ``level0_maps`` is False: a renderer that writes them itself). No smoothing.
        With ``level1_from`` (a depth of level 0's size, a field or a ``Level``: the render's filled depth, in
        ``spare_depth``), level 1 is averaged down from it instead of from level 0
        (``SurfelMapper.render_pyramid``)."""
        self._set_geometry(intrinsics)
        if level1_from is not None and tuple(level1_from.shape) != tuple(self.shapes[0]):
            raise ValueError(f"level 1 from a depth of {level1_from.shape[0]}x{level1_from.shape[1]} pixels for "
                             f"maps whose level 0 is {self.shapes[0][0]}x{self.shapes[0][1]}")
        self._levels_and_maps(0 if level0_maps else 1, level1_from)

    def _levels_and_maps(self, first_maps: int, level1_from=None) -> None:
        """Every level's depth from level 0 (``pyramid_down``, a launch per level; level 1 from ``level1_from``
        when given), then the vertex and normal maps of levels ``first_maps`` and on (``maps_levels``). A
        launch per level rather than the levels' loops in one kernel, which compiled slower
        (docs/PERFORMANCE.md, "Cold start")."""
        stack = self.depth[0].field
        for l in range(1, self.levels):
            h, w = self.shapes[l - 1]
            if l == 1 and level1_from is not None:
                fine = as_level(level1_from)
                pyramid_down(fine.field, fine.row0, h, w, stack, self.row0[1], self.max_depth_diff, False, self._serial)
            else:
                pyramid_down(stack, self.row0[l - 1], h, w, stack, self.row0[l], self.max_depth_diff, False,
                             self._serial)
        maps_levels(stack, self.vertex[0].field, self.normal[0].field, self._geo["field"], self.levels, first_maps,
                    self._serial, self._shift)

    def _set_geometry(self, intrinsics: Intrinsics) -> None:
        """``intrinsics`` (of level 0) and the levels' rows and sizes into ``_geometry``, where they changed."""
        self.intrinsics = [intrinsics.downsampled(2**l) for l in range(self.levels)]
        key = (tuple(K.as_tuple() for K in self.intrinsics), self.max_depth_jump)
        geo = self._geo
        if geo["for"] != key:  # once per run (a pair's with equal intrinsics too): a copy from NumPy waits for a GPU
            g = np.zeros((self.levels, N_GEOMETRY), np.float32)
            for l, (K, (h, w)) in enumerate(zip(self.intrinsics, self.shapes)):
                # A depth edge at a coarse level spans 2**l fine pixels: scale the jump threshold with it.
                g[l] = (self.row0[l] - self._shift, h, w, *K.as_tuple(), self.max_depth_jump * 2**l)
            if geo["field"] is None:
                geo["field"] = ti.field(ti.f32, shape=(self.levels, N_GEOMETRY))
            geo["field"].from_numpy(g)
            geo["for"] = key
