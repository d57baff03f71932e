"""Per-frame maps on the Taichi side: depth pyramid, vertex maps and normal maps.

Level 0 is the input resolution; level l is subsampled by 2**l. The coarse depth at (u', v') is the
average of the 3×3 fine neighbourhood centred on (2u', 2v') over the pixels within a range of the
centre depth, so the average never mixes the two sides of a depth edge, and pixel u' stays exactly at
fine pixel 2u' (intrinsics of level l are ``Intrinsics.downsampled(2**l)``).
"""


import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics


@ti.kernel
def pyramid_down(fine: ti.template(), coarse: ti.template(), max_diff: ti.f32):
    H, W = fine.shape
    for v, u in coarse:
        c = fine[2 * v, 2 * u]
        total = 0.0
        count = 0
        if c > 0:
            for dv, du in ti.static(ti.ndrange((-1, 2), (-1, 2))):
                y = 2 * v + dv
                x = 2 * u + du
                if 0 <= y < H and 0 <= x < W:
                    d = fine[y, x]
                    if d > 0 and ti.abs(d - c) < max_diff:
                        total += d
                        count += 1
        coarse[v, u] = total / count if count > 0 else 0.0


@ti.kernel
def backproject(depth: ti.template(), vertex: ti.template(), fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32):
    """vertex[v, u] = ((u - cx) z / fx, (v - cy) z / fy, z); zero where depth is invalid (≤ 0)."""
    for v, u in depth:
        z = depth[v, u]
        p = ti.Vector([0.0, 0.0, 0.0])
        if z > 0:
            p = ti.Vector([(u - cx) * z / fx, (v - cy) * z / fy, z])
        vertex[v, u] = p


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
            l = vertex[v, u - 1]
            r = vertex[v, u + 1]
            t = vertex[v - 1, u]
            b = vertex[v + 1, u]
            ok = c.z > 0 and l.z > 0 and r.z > 0 and t.z > 0 and b.z > 0
            jump = ti.max(ti.max(ti.abs(l.z - c.z), ti.abs(r.z - c.z)), ti.max(ti.abs(t.z - c.z), ti.abs(b.z - c.z)))
            if ok and jump <= max_depth_jump:
                m = (r - l).cross(b - t)
                length = m.norm()
                if length > 0:
                    m = m / length
                    if m.dot(c) > 0:  # face the camera
                        m = -m
                    n = m
        normal[v, u] = n


@ti.data_oriented
class FrameMaps:
    """Depth, vertex and normal maps of one frame at every pyramid level (camera frame, metres)."""

    def __init__(self, height: int, width: int, levels: int = 3):
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

    def compute(self, depth: np.ndarray, intrinsics: Intrinsics, max_depth_jump: float = 0.05,
                pyramid_max_diff: float = 0.09) -> None:
        """Upload a float32 depth image (metres, 0 = invalid) and build every level's maps."""
        if depth.shape != self.shapes[0]:
            raise ValueError(f"depth of shape {depth.shape} given to FrameMaps of shape {self.shapes[0]}")
        self.depth[0].from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
        self.compute_from_field(intrinsics, max_depth_jump, pyramid_max_diff)

    def compute_from_field(self, intrinsics: Intrinsics, max_depth_jump: float = 0.05,
                           pyramid_max_diff: float = 0.09) -> None:
        """Build every level from ``self.depth[0]`` already on the Taichi side."""
        self.intrinsics = [intrinsics.downsampled(2**l) for l in range(self.levels)]
        for l in range(1, self.levels):
            pyramid_down(self.depth[l - 1], self.depth[l], pyramid_max_diff)
        for l in range(self.levels):
            backproject(self.depth[l], self.vertex[l], *self.intrinsics[l].as_tuple())
            # A depth edge at a coarse level spans 2**l fine pixels: scale the jump threshold with it.
            compute_normals(self.vertex[l], self.normal[l], max_depth_jump * 2**l)
