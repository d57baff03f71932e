"""Per-frame maps on the Taichi side: depth pyramid, vertex maps and normal maps.

Level 0 is the input resolution (optionally smoothed, see below), or with ``input_level`` L the input
averaged down L times by the same pyramid step; level l is subsampled by 2**l from level 0. The
coarse depth at (u', v') is the average of the 3×3 fine neighbourhood centred on (2u', 2v') over the
pixels within a range of the centre depth, so the average never mixes the two sides of a depth edge, and
pixel u' stays exactly at fine pixel 2u' (intrinsics of level l are ``Intrinsics.downsampled(2**l)``).
On the image border the window is the symmetric part that fits (a one-sided window would bend slanted
surfaces there, and that bend, fixed to the image, would hold ICP back from sliding along a plane).

Smoothing (``smooth_radius`` > 0, the role of KinectFusion's bilateral filter): the level-0 depth is
replaced by the mean of the (2r+1)×(2r+1) neighbours within the same range of the centre depth, computed
separably (a row pass, then a column pass, each range-checked against its own centre). Normals from
central differences of raw Kinect-like depth are noisy enough at full resolution that most of them fail
ICP's normal-angle test; r = 2 cuts the normal noise several-fold at ~3 ms per 640×480 frame.

Speed (the 2-core CPU, 640×480, CPU time of one call, min of 9 runs): backproject 0.9 ms, normals 5.1 ms,
pyramid_down to level 1 1.5 ms, smoothing r = 2 (both passes) 4.2 ms; about 15 ms for every level of one
frame. These kernels are scalar: Taichi's CPU backend does not vectorise the loop over pixels (the
field's root pointer is reloaded in every iteration, which stops LLVM's loop vectoriser; checked in the
generated IR), and the normal and back-projection kernels were already at about the speed of the same
loop in C at -O2: a struct-for, an ndrange-for and a row loop, AoS and SoA layouts, and fewer divisions
changed them by less than 15%. What did pay is short dependency chains: a 5×5 range mean written as one
running sum took 22.8 ms, the separable, branch-free version 4.2 ms.

Compilation: Taichi compiles a kernel once per set of fields it is given, so the first ``compute`` of
each new FrameMaps costs about 2 s on that machine (0.5 s per kernel); allocate FrameMaps once and reuse
them. (One fused kernel for all levels compiled slower still, 4.5 s.)
"""


import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics


@ti.kernel
def pyramid_down(fine: ti.template(), coarse: ti.template(), max_diff: ti.f32):
    H, W = fine.shape
    for v, u in coarse:
        y0 = 2 * v
        x0 = 2 * u
        c = fine[y0, x0]
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
                d = fine[y0 + dv * ry, x0 + du * rx]  # outside the window: re-reads a row/column inside
                ok = (ti.abs(dv) <= ry) & (ti.abs(du) <= rx) & (d > 0) & (ti.abs(d - c) < max_diff)
                total[dv + 1] += ti.select(ok, d, 0.0)
                count[dv + 1] += ti.select(ok, 1.0, 0.0)
            out = total.sum() / count.sum()  # the centre always counts
        coarse[v, u] = out


@ti.kernel
def smooth_pass(src: ti.template(), dst: ti.template(), radius: ti.template(), along_rows: ti.template(),
                max_diff: ti.f32):
    """One separable pass of the range-checked mean: dst = mean of the 2r+1 neighbours along a row (or a
    column) that are valid and within ``max_diff`` of the centre; invalid stays invalid."""
    H, W = src.shape
    for v, u in src:
        c = src[v, u]
        out = 0.0
        if c > 0:
            total = 0.0
            count = 0.0
            i = u if ti.static(along_rows) else v  # position along the pass
            n = W if ti.static(along_rows) else H
            if radius <= i < n - radius:  # interior: branch-free taps
                for k in ti.static(range(-radius, radius + 1)):
                    d = src[v, u + k] if ti.static(along_rows) else src[v + k, u]
                    ok = (d > 0) & (ti.abs(d - c) < max_diff)
                    total += ti.select(ok, d, 0.0)
                    count += ti.select(ok, 1.0, 0.0)
            else:  # near the border: a symmetric window of the radius that fits (a one-sided window
                # would bend a slanted surface towards the image edge)
                fit = ti.min(i, n - 1 - i)
                for k in ti.static(range(-radius, radius + 1)):
                    if ti.abs(k) <= fit:
                        d = src[v, u + k] if ti.static(along_rows) else src[v + k, u]
                        if d > 0 and ti.abs(d - c) < max_diff:
                            total += d
                            count += 1.0
            out = total / count  # the centre always counts
        dst[v, u] = out


@ti.kernel
def backproject(depth: ti.template(), vertex: ti.template(), fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32):
    """vertex[v, u] = ((u - cx) z / fx, (v - cy) z / fy, z); zero where depth is invalid (≤ 0 or NaN)."""
    ifx = 1.0 / fx  # one division per launch, not two per pixel
    ify = 1.0 / fy
    for v, u in depth:
        z = depth[v, u]
        z = ti.select(z > 0, z, 0.0)  # branch-free: the zero vector falls out of z = 0
        vertex[v, u] = ti.Vector([(u - cx) * ifx * z, (v - cy) * ify * z, z])


@ti.kernel
def compute_normals(vertex: ti.template(), normal: ti.template(), max_depth_jump: ti.f32):
    """Normal from the cross product of central differences, facing the camera; zero where undefined.

    Undefined: on the image border, where the pixel or one of its four neighbours is invalid, or where a
    neighbour's depth differs from the centre's by more than ``max_depth_jump`` (a depth edge).
    """
    H, W = vertex.shape
    for v, u in vertex:
        n = ti.Vector([0.0, 0.0, 0.0])
        if 0 < u < W - 1 and 0 < v < H - 1:
            c = vertex[v, u]
            if c.z > 0:  # holes are common: skip the four neighbour reads
                l = vertex[v, u - 1]
                r = vertex[v, u + 1]
                t = vertex[v - 1, u]
                b = vertex[v + 1, u]
                lo = ti.min(ti.min(l.z, r.z), ti.min(t.z, b.z))
                hi = ti.max(ti.max(l.z, r.z), ti.max(t.z, b.z))
                # all neighbours valid, and max |z_neighbour - z_centre| <= max_depth_jump
                if lo > 0 and hi - c.z <= max_depth_jump and c.z - lo <= max_depth_jump:
                    m = (r - l).cross(b - t)
                    len2 = m.dot(m)
                    if len2 > 0:
                        s = ti.rsqrt(len2)
                        n = m * ti.select(m.dot(c) > 0, -s, s)  # face the camera
        normal[v, u] = n


@ti.data_oriented
class FrameMaps:
    """Depth, vertex and normal maps of one frame at every pyramid level (camera frame, metres)."""

    def __init__(self, height: int, width: int, levels: int = 3, input_level: int = 0):
        """Maps of ``levels`` levels for depth images of ``height`` × ``width``. With ``input_level`` L > 0
        the input is first averaged down L times (``pyramid_down``) and level 0 is that 2**L times smaller
        image: the fine resolution is never smoothed or back-projected, which is what makes it cheaper."""
        self.input_shape = (height, width)
        self.input_level = int(input_level)
        self._inputs = []  # input_level > 0: the input and the intermediate averaged images
        for _ in range(self.input_level):
            self._inputs.append(ti.field(ti.f32, shape=(height, width)))
            height, width = (height + 1) // 2, (width + 1) // 2
        self.height, self.width, self.levels = height, width, levels
        self.shapes = []
        h, w = height, width
        for _ in range(levels):
            self.shapes.append((h, w))
            h, w = (h + 1) // 2, (w + 1) // 2
        self.depth = [ti.field(ti.f32, shape=s) for s in self.shapes]
        self.vertex = [ti.Vector.field(3, ti.f32, shape=s) for s in self.shapes]
        self.normal = [ti.Vector.field(3, ti.f32, shape=s) for s in self.shapes]
        self.intrinsics: list[Intrinsics] = []
        self._raw = self._tmp = None  # input depth and the row-pass result, when smoothing

    def compute(self, depth: np.ndarray, intrinsics: Intrinsics, max_depth_jump: float = 0.05,
                pyramid_max_diff: float = 0.09, smooth_radius: int = 0) -> None:
        """Upload a float32 depth image (metres, 0 = invalid) and build every level's maps.

        ``smooth_radius`` r > 0 first replaces the depth by its range-checked (2r+1)² mean (see the module
        docstring); ``depth[0]`` then holds the smoothed depth."""
        if depth.shape != self.input_shape:
            raise ValueError(f"depth of shape {depth.shape} given to FrameMaps of shape {self.input_shape}")
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        level0 = self._raw_field() if smooth_radius > 0 else self.depth[0]  # the unsmoothed level-0 depth
        if self.input_level == 0:
            level0.from_numpy(depth)
        else:
            intrinsics = intrinsics.downsampled(2**self.input_level)
            self._inputs[0].from_numpy(depth)
            for fine, coarse in zip(self._inputs, self._inputs[1:] + [level0]):
                pyramid_down(fine, coarse, pyramid_max_diff)
        if smooth_radius > 0:
            smooth_pass(level0, self._tmp, int(smooth_radius), True, pyramid_max_diff)
            smooth_pass(self._tmp, self.depth[0], int(smooth_radius), False, pyramid_max_diff)
        self.compute_from_field(intrinsics, max_depth_jump, pyramid_max_diff)

    def _raw_field(self):
        """The unsmoothed level-0 depth (allocated when smoothing is first asked for)."""
        if self._raw is None:
            self._raw = ti.field(ti.f32, shape=self.shapes[0])
            self._tmp = ti.field(ti.f32, shape=self.shapes[0])
        return self._raw

    def compute_from_field(self, intrinsics: Intrinsics, max_depth_jump: float = 0.05,
                           pyramid_max_diff: float = 0.09, level0_maps: bool = True) -> None:
        """Build every level from ``self.depth[0]`` already on the Taichi side (without level 0's vertex
        and normal maps when ``level0_maps`` is False: a renderer that writes them itself)."""
        self.intrinsics = [intrinsics.downsampled(2**l) for l in range(self.levels)]
        for l in range(1, self.levels):
            pyramid_down(self.depth[l - 1], self.depth[l], pyramid_max_diff)
        for l in range(0 if level0_maps else 1, self.levels):
            backproject(self.depth[l], self.vertex[l], *self.intrinsics[l].as_tuple())
            # A depth edge at a coarse level spans 2**l fine pixels: scale the jump threshold with it.
            compute_normals(self.vertex[l], self.normal[l], max_depth_jump * 2**l)
