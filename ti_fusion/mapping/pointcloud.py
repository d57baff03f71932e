"""Point clouds in NumPy: back-projection, rigid transforms, voxel-grid downsampling, joining clouds.

Voxel downsampling keeps one point per occupied voxel of edge ``voxel_size`` (cells
floor(p / voxel_size)): the centroid of the points that fell in it, and their mean colour.
``VoxelCloud`` joins clouds incrementally while keeping per-voxel sums and counts, so joining many
frames gives exactly the cloud ``voxel_downsample`` would give for all their points at once, in
memory bounded by the number of occupied voxels rather than the number of points.
"""

from __future__ import annotations

import numpy as np

from ti_fusion.interrupts import critical

_KEY_BITS = 21                      # bits per axis in a packed voxel key (3 × 21 = 63 bits)
_KEY_HALF = 1 << (_KEY_BITS - 1)


def backproject(depth: np.ndarray, intrinsics, color: np.ndarray | None = None,
                stride: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """(N×3 float64 camera points, N×3 uint8 colours or None) of the valid pixels of a depth image.

    Every ``stride``-th pixel in u and v; depth 0 or non-finite is invalid. ``color`` must have the
    depth image's size (taken at the same pixel: for unregistered colour, e.g. 7-Scenes, it is only
    approximately the surface's colour).
    """
    K = intrinsics
    d = depth[::stride, ::stride].astype(np.float64)
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    z = d[v, u]
    u = u * stride
    v = v * stride
    xyz = np.column_stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z])
    rgb = None
    if color is not None:
        if color.shape[:2] != depth.shape:
            raise ValueError(f"colour {color.shape[:2]} and depth {depth.shape} differ in size")
        rgb = np.ascontiguousarray(color[v, u, :3], dtype=np.uint8)
    return xyz, rgb


def transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Points ``xyz`` (N×3) mapped by the 4×4 rigid transform ``T``."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(xyz, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def voxel_keys(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """One int64 key per point naming its voxel (packed cell indices, or N×3 cells if out of range)."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    cells = np.floor(np.asarray(xyz, dtype=np.float64) / voxel_size).astype(np.int64)
    if cells.size and (cells.min() < -_KEY_HALF or cells.max() >= _KEY_HALF):
        return cells  # too far out to pack into 63 bits: callers fall back to row-wise unique
    c = cells + _KEY_HALF
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


def _group(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unique keys, inverse index) for packed (1-D) or cell (N×3) keys."""
    if keys.ndim == 1:
        return np.unique(keys, return_inverse=True)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)


def _sum_by(inverse: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    return np.stack([np.bincount(inverse, weights=values[:, k], minlength=n) for k in range(values.shape[1])], axis=1)


def voxel_downsample(xyz: np.ndarray, rgb: np.ndarray | None = None,
                     voxel_size: float = 0.02) -> tuple[np.ndarray, np.ndarray | None]:
    """(centroids N′×3 float64, mean colours N′×3 uint8 or None): one point per occupied voxel.

    Output order: by voxel key (deterministic).
    """
    cloud = VoxelCloud(voxel_size)
    cloud.add(xyz, rgb)
    return cloud.points()


class VoxelCloud:
    """A cloud joined from many clouds on a voxel grid: per-voxel sums of positions and colours.

    ``add(xyz, rgb, pose)`` merges a cloud (optionally transformed to world by a camera-to-world
    ``pose`` first); ``points()`` gives the downsampled cloud.
    """

    def __init__(self, voxel_size: float):
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self._keys: np.ndarray | None = None
        self._xyz_sum = np.zeros((0, 3))
        self._rgb_sum: np.ndarray | None = None
        self._count = np.zeros(0)
        self.has_color: bool | None = None
        self._pending: list[tuple] = []   # grouped clouds not merged yet (merging is batched)
        self._pending_voxels = 0

    def __len__(self) -> int:
        """Occupied voxels."""
        self._flush()
        return len(self._count)

    def add(self, xyz: np.ndarray, rgb: np.ndarray | None = None, pose: np.ndarray | None = None) -> None:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if pose is not None:
            xyz = transform(pose, xyz)
        if self.has_color is None:
            self.has_color = rgb is not None
        if (rgb is not None) != self.has_color:
            raise ValueError("every cloud added must have colours, or none")
        if len(xyz) == 0:
            return
        keys = voxel_keys(xyz, self.voxel_size)
        rgb_f = None if rgb is None else np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
        unique, inverse = _group(keys)
        n = len(unique)
        xyz_sum = _sum_by(inverse, xyz, n)
        count = np.bincount(inverse, minlength=n).astype(np.float64)
        rgb_sum = None if rgb_f is None else _sum_by(inverse, rgb_f, n)
        self._pending.append((unique, xyz_sum, rgb_sum, count))
        self._pending_voxels += n
        # Regrouping the whole cloud costs O(size): do it once the pending part is as large as the
        # merged part, which keeps joining linear overall.
        if self._pending_voxels > max(len(self._count), 100_000):
            self._flush()

    def _flush(self) -> None:
        """Merge the pending clouds into the sums. A stop (Ctrl-C, SIGTERM) waits until the sums are whole
        again (``critical``): the run's last map snapshot reads them on its way out."""
        if not self._pending:
            return
        with critical():
            self._merge_pending()

    def _merge_pending(self) -> None:
        parts = self._pending if self._keys is None else [(self._keys, self._xyz_sum, self._rgb_sum, self._count)] + self._pending
        self._pending, self._pending_voxels = [], 0
        if len(parts) == 1:
            self._keys, self._xyz_sum, self._rgb_sum, self._count = parts[0]
            return
        keys = [p[0] for p in parts]
        if len({k.ndim for k in keys}) > 1:  # some cloud outgrew packed keys: compare as cells
            keys = [self._as_cells(k) for k in keys]
        unique, inverse = _group(np.concatenate(keys))
        n = len(unique)
        self._xyz_sum = _sum_by(inverse, np.concatenate([p[1] for p in parts]), n)
        self._count = np.bincount(inverse, weights=np.concatenate([p[3] for p in parts]), minlength=n)
        if self.has_color:
            self._rgb_sum = _sum_by(inverse, np.concatenate([p[2] for p in parts]), n)
        self._keys = unique

    @staticmethod
    def _as_cells(keys: np.ndarray) -> np.ndarray:
        if keys.ndim == 2:
            return keys
        mask = (1 << _KEY_BITS) - 1
        return np.column_stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask]) - _KEY_HALF

    def points(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(centroids N×3 float64, mean colours N×3 uint8 or None)."""
        self._flush()
        if self._keys is None:
            return np.zeros((0, 3)), (np.zeros((0, 3), np.uint8) if self.has_color else None)
        xyz = self._xyz_sum / self._count[:, None]
        rgb = None
        if self.has_color:
            rgb = np.clip(np.rint(self._rgb_sum / self._count[:, None]), 0, 255).astype(np.uint8)
        return xyz, rgb
