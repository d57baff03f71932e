"""A coloured triangle mesh of the confirmed surfels (docs/MESH.md).

``mesh_surfels`` splats the surfels into a sparse signed-distance grid (``kernels/mesh.py``: each disc
writes its plane distance into the voxels it reaches, weighted by confidence; only the blocks of voxels
the surfels reach exist), then runs scikit-image's marching cubes (Lewiner) block by block on the cubes
whose eight corners a surfel reached, so no surface is made where no surfel was confirmed. Vertices
shared by neighbouring blocks are welded; colours are interpolated from the voxels, normals come from the
triangles and point to the side the surfels faced (the cameras').
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ti_fusion.config import MeshConfig
from ti_fusion.errors import InputError
from ti_fusion.timing import Stopwatch

log = logging.getLogger(__name__)

E = 8  # voxels along a block's edge (kernels/mesh.py's BLOCK_EDGE; kept here so that NumPy-only callers need no Taichi)
# Memory per voxel, for the messages of the grids' bound: each grid's sums (Σw·d, Σw, Σw·colour in float32), the
# depth grid's carving counts where carving is on, and the copies padded to 9³ per block that marching cubes reads.
SUMS_BYTES_PER_VOXEL = 4 + 4 + 12
CARVE_BYTES_PER_VOXEL = 4 + 4
EXTRACT_BYTES_PER_VOXEL = 4 * 5 * 729 // 512  # distance, colour, masks: about five floats
VOXEL_RANGE = (0.001, 0.5)  # metres: finer is below any RGB-D sensor's noise, coarser is no longer a surface


@dataclass
class Mesh:
    """Triangles over shared vertices, world frame, metres."""

    vertices: np.ndarray   # V × 3 float32
    faces: np.ndarray      # F × 3 int64, counter-clockwise seen from the side the normals point to
    normals: np.ndarray    # V × 3 float32, unit
    colors: np.ndarray    # V × 3 uint8 RGB

    def __len__(self) -> int:
        return len(self.faces)

    def area(self) -> float:
        a, b, c = (self.vertices[self.faces[:, k]].astype(np.float64) for k in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


MeshSettings = MeshConfig  # the [mesh] section of the config: voxel_size, min_weight, band, max_reach, ...


def check_voxel_size(voxel: float, where: str = "mesh.voxel_size") -> None:
    lo, hi = VOXEL_RANGE
    if not (np.isfinite(voxel) and lo <= voxel <= hi):
        raise InputError(None, f"{where} {voxel:g}: must be between {lo:g} and {hi:g} metres")


def select_surfels(surfels: dict, min_weight: float, source: str | Path | None = None) -> dict:
    """The surfels to mesh: confirmed (weight ≥ ``min_weight``), finite, with a unit normal."""
    p = np.asarray(surfels["position"], np.float32).reshape(-1, 3)
    n = np.asarray(surfels["normal"], np.float32).reshape(-1, 3)
    if len(p) == 0:
        raise InputError(source, "the map is empty: no surfels to mesh")
    keep = np.isfinite(p).all(1) & np.isfinite(n).all(1)
    norm = np.linalg.norm(n, axis=1)
    keep &= norm > 0.5
    w = np.asarray(surfels.get("weight", np.full(len(p), np.inf)), np.float32).reshape(-1)
    keep &= w >= min_weight
    if not keep.any():
        raise InputError(source, f"none of the map's {len(p)} surfels is confirmed (confidence ≥ {min_weight:g}, "
                                 "mesh.min_weight): no surface to mesh")
    radius = surfels.get("radius")
    color = surfels.get("color")
    return {
        "position": p[keep],
        "normal": (n[keep] / norm[keep, None]).astype(np.float32),
        "color": np.full((int(keep.sum()), 3), 200, np.float32) if color is None
        else np.asarray(color, np.float32).reshape(-1, 3)[keep],
        "weight": np.where(np.isfinite(w), w, 1.0).astype(np.float32)[keep],
        "radius": None if radius is None else np.asarray(radius, np.float32).reshape(-1)[keep],
    }


class SparseGrid:
    """The blocks of voxels the surfels reach: sorted packed keys, their block coordinates, the origin."""

    def __init__(self, position: np.ndarray, extent: np.ndarray, voxel: float, max_voxels: int,
                 source: str | Path | None = None):
        from ti_fusion.kernels.mesh import KEY_BITS, KEY_SPAN

        # every block a surfel's box (centre ± extent) touches: extent < one block, so 2 per axis at most
        lo = np.floor(np.floor((position - extent) / voxel) / E).astype(np.int64)
        hi = np.floor(np.floor((position + extent) / voxel) / E).astype(np.int64)
        self.origin = lo.min(axis=0)
        span = hi.max(axis=0) - self.origin + 1
        if (span > KEY_SPAN).any():
            axis = "xyz"[int(np.argmax(span))]
            raise InputError(source, f"the map spans {span.max() * E * voxel:.1f} m along {axis}: at a voxel size "
                                     f"of {voxel:g} m the mesh grid reaches {KEY_SPAN * E * voxel:.1f} m at most; "
                                     "choose a larger mesh.voxel_size")
        lo, hi = lo - self.origin, hi - self.origin
        keys = []
        for corner in range(8):
            pick = [(corner >> a) & 1 for a in range(3)]
            b = np.stack([hi[:, a] if pick[a] else lo[:, a] for a in range(3)], axis=1)
            keys.append((b[:, 0] << (2 * KEY_BITS)) | (b[:, 1] << KEY_BITS) | b[:, 2])
        self.keys = np.unique(np.concatenate(keys)).astype(np.int32)
        voxels = len(self.keys) * E ** 3
        if voxels > max_voxels:
            gb = voxels * (SUMS_BYTES_PER_VOXEL + EXTRACT_BYTES_PER_VOXEL) / 2**30
            raise InputError(source, f"the surface needs {voxels / 1e6:.1f} M voxels of {voxel:g} m "
                                     f"(~{gb:.1f} GB), more than mesh.max_voxels "
                                     f"({max_voxels / 1e6:.1f} M): choose a larger mesh.voxel_size or raise the bound")
        k = self.keys.astype(np.int64)
        mask = KEY_SPAN - 1
        self.blocks = np.stack([k >> (2 * KEY_BITS), (k >> KEY_BITS) & mask, k & mask], axis=1)  # relative coords

    @classmethod
    def of_blocks(cls, blocks: np.ndarray, voxel: float, source=None) -> "SparseGrid":
        """The grid of the given absolute block coordinates (B × 3 int64, sorted as their keys: x, then y, z)."""
        from ti_fusion.kernels.mesh import KEY_BITS, KEY_SPAN

        grid = cls.__new__(cls)
        grid.origin = blocks.min(axis=0) if len(blocks) else np.zeros(3, np.int64)
        rel = blocks - grid.origin
        span = rel.max(axis=0) + 1 if len(blocks) else np.ones(3, np.int64)
        if (span > KEY_SPAN).any():
            axis = "xyz"[int(np.argmax(span))]
            raise InputError(source, f"the frames span {span.max() * E * voxel:.1f} m along {axis}: at a voxel size "
                                     f"of {voxel:g} m the mesh grid reaches {KEY_SPAN * E * voxel:.1f} m at most; "
                                     "choose a larger mesh.voxel_size")
        grid.blocks = rel
        grid.keys = ((rel[:, 0] << (2 * KEY_BITS)) | (rel[:, 1] << KEY_BITS) | rel[:, 2]).astype(np.int32)
        return grid

    def __len__(self) -> int:
        return len(self.keys)

    def find(self, blocks: np.ndarray) -> np.ndarray:
        """Index of each relative block coordinate (M × 3), −1 where that block does not exist."""
        from ti_fusion.kernels.mesh import KEY_BITS, KEY_SPAN

        inside = ((blocks >= 0) & (blocks < KEY_SPAN)).all(axis=1)
        key = (blocks[:, 0] << (2 * KEY_BITS)) | (blocks[:, 1] << KEY_BITS) | blocks[:, 2]
        i = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        return np.where(inside & (self.keys[i] == key), i, -1)


def reach_of(selected: dict, settings: MeshSettings) -> np.ndarray:
    """Metres a surfel writes across its normal: its disc radius, at least one voxel, at most ``max_reach``."""
    v = settings.voxel_size
    r = selected["radius"]
    if r is None:
        r = np.full(len(selected["position"]), v, np.float32)
    return np.clip(r, v, settings.max_reach * v).astype(np.float32)


def splat_surfels(selected: dict, settings: MeshSettings, source=None) -> tuple[SparseGrid, dict]:
    """The sparse grid and its voxels: ``sdf`` (weighted mean distance), ``weight`` and ``color`` per voxel,
    each (blocks, E, E, E[, 3]) float32; the Taichi kernel does the per-surfel work."""
    from ti_fusion.backend import current_backend
    from ti_fusion.kernels import mesh as kmesh

    current_backend()
    v = float(settings.voxel_size)
    band = float(settings.band) * v
    reach = reach_of(selected, settings)
    n = np.abs(selected["normal"].astype(np.float64))
    extent = reach[:, None] * np.sqrt(np.maximum(1.0 - n * n, 0.0)) + band * n  # the kernel's cylinder box
    grid = SparseGrid(selected["position"].astype(np.float64), extent, v, settings.max_voxels, source)
    nb = len(grid)
    sdf = np.zeros(nb * E ** 3, np.float32)
    wsum = np.zeros(nb * E ** 3, np.float32)
    rgb = np.zeros((nb * E ** 3, 3), np.float32)
    import taichi as ti

    kmesh.splat(np.ascontiguousarray(selected["position"]), np.ascontiguousarray(selected["normal"]),
                np.ascontiguousarray(selected["color"]), np.ascontiguousarray(selected["weight"]), reach,
                len(reach), grid.keys, nb, ti.math.ivec3(*(int(o) for o in grid.origin)), v, band, sdf, wsum, rgb)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(wsum > 0, 1.0 / wsum, 0.0).astype(np.float32)
    shape = (nb, E, E, E)
    return grid, {"sdf": (sdf * inv).reshape(shape), "weight": wsum.reshape(shape),
                  "color": (rgb * inv[:, None]).reshape(shape + (3,))}


def _padded(grid: SparseGrid, values: np.ndarray, fill) -> np.ndarray:
    """Each block with one more layer of voxels from its +x, +y, +z neighbours: (blocks, E+1, E+1, E+1, ...)."""
    nb = len(grid)
    out = np.full((nb, E + 1, E + 1, E + 1) + values.shape[4:], fill, values.dtype)
    out[:, :E, :E, :E] = values
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                if dx == dy == dz == 0:
                    continue
                nbr = grid.find(grid.blocks + np.array([dx, dy, dz]))
                has = nbr >= 0
                dst = (has, slice(E, E + 1) if dx else slice(0, E), slice(E, E + 1) if dy else slice(0, E),
                       slice(E, E + 1) if dz else slice(0, E))
                src = (nbr[has], slice(0, 1) if dx else slice(0, E), slice(0, 1) if dy else slice(0, E),
                       slice(0, 1) if dz else slice(0, E))
                out[dst] = values[src]
    return out


def extract(grid: SparseGrid, voxels: dict, voxel: float, min_weight: float = 0.0) -> Mesh:
    """Marching cubes on every block whose complete cubes (all eight corners reached, with a weight above
    ``min_weight``) change sign."""
    from skimage.measure import marching_cubes

    sdf = _padded(grid, voxels["sdf"], np.float32(0))
    valid = _padded(grid, voxels["weight"] > min_weight, False)
    color = _padded(grid, voxels["color"], np.float32(0))
    # a cube is complete when its eight corners are valid; skimage tests the mask at a cube's far corner
    # (cube (x, y, z) is made where mask[x + 1, y + 1, z + 1]: checked in tests/mapping/test_mesh.py)
    cube = valid[:, :-1, :-1, :-1].copy()
    for dx, dy, dz in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)]:
        cube &= valid[:, dx:E + dx, dy:E + dy, dz:E + dz]
    positive = np.where(valid, sdf > 0, False)
    negative = np.where(valid, sdf <= 0, False)

    def any_corner(a):
        out = a[:, :-1, :-1, :-1].copy()
        for dx, dy, dz in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)]:
            out |= a[:, dx:E + dx, dy:E + dy, dz:E + dz]
        return out

    crossing = cube & any_corner(positive) & any_corner(negative)
    todo = np.flatnonzero(crossing.reshape(len(grid), -1).any(axis=1))
    verts, faces, owner, count = [], [], [], 0
    mask = np.zeros((E + 1,) * 3, bool)
    for b in todo:
        mask[:] = False
        mask[1:, 1:, 1:] = crossing[b]
        vol = np.where(valid[b], sdf[b], np.float32(1.0))  # unreached corners: cubes there are masked off
        try:
            v, f, _, _ = marching_cubes(vol, 0.0, mask=mask, gradient_direction="ascent", allow_degenerate=False)
        except RuntimeError:  # only corners exactly at the level: no triangle of positive area
            continue
        if len(f) == 0:
            continue
        verts.append(v)
        faces.append(f + count)
        owner.append(np.full(len(v), b))
        count += len(v)
    if not faces:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32),
                    np.zeros((0, 3), np.uint8))
    local = np.concatenate(verts).astype(np.float64)
    faces = np.concatenate(faces).astype(np.int64)
    owner = np.concatenate(owner)
    gridpos = local + ((grid.blocks[owner] + grid.origin) * E).astype(np.float64)  # voxel units
    # blocks that share a face compute the same vertices on it from the same two values: weld them
    key = np.round(gridpos * 4096.0).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    vertices = (gridpos[first] * voxel).astype(np.float32)
    rgb = _trilinear(color, valid, owner[first], local[first])
    mesh = Mesh(vertices, faces, vertex_normals(vertices, faces), rgb)
    return _orient(mesh, grid, voxels, voxel, min_weight)


def _trilinear(color: np.ndarray, valid: np.ndarray, owner: np.ndarray, local: np.ndarray) -> np.ndarray:
    """RGB at each vertex from the valid voxels around it (its block's padded array), as uint8."""
    base = np.clip(np.floor(local).astype(np.int64), 0, E - 1)
    frac = local - base
    acc = np.zeros((len(local), 3))
    wsum = np.zeros(len(local))
    for c in range(8):
        o = np.array([(c >> a) & 1 for a in range(3)])
        idx = base + o
        w = np.prod(np.where(o, frac, 1.0 - frac), axis=1)
        w = w * valid[owner, idx[:, 0], idx[:, 1], idx[:, 2]]
        acc += w[:, None] * color[owner, idx[:, 0], idx[:, 1], idx[:, 2]]
        wsum += w
    return np.clip(np.rint(acc / np.maximum(wsum, 1e-12)[:, None]), 0, 255).astype(np.uint8)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted mean of the normals of the triangles around each vertex (unit; +z where none)."""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):  # bincount: np.add.at is several times slower at a million triangles
        for c in range(3):
            acc[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=len(v))
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 0, acc / np.maximum(norm, 1e-300), np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)


def _orient(mesh: Mesh, grid: SparseGrid, voxels: dict, voxel: float, min_weight: float = 0.0) -> Mesh:
    """Triangles wound so that their normals point where the distance grows (the surfels' front side).

    Marching cubes winds all triangles one way for a given gradient direction; this checks which against
    the grid itself, so a change of library convention cannot silently flip the mesh inside out."""
    if len(mesh.faces) == 0:
        return mesh
    def sdf_at(points):
        g = np.floor(points / voxel + 0.5).astype(np.int64)  # the nearest voxel centre
        idx = grid.find(np.floor_divide(g, E) - grid.origin)
        loc = np.mod(g, E)
        ok = idx >= 0
        idx, loc = np.where(ok, idx, 0), np.where(ok[:, None], loc, 0)
        ok &= voxels["weight"][idx, loc[:, 0], loc[:, 1], loc[:, 2]] > min_weight
        return voxels["sdf"][idx, loc[:, 0], loc[:, 1], loc[:, 2]], ok

    # one voxel in front of and behind each vertex: never both on the vertex's own layer of voxels
    v, n = mesh.vertices.astype(np.float64), mesh.normals.astype(np.float64)
    front, ok_f = sdf_at(v + voxel * n)
    back, ok_b = sdf_at(v - voxel * n)
    d = (front - back)[ok_f & ok_b]
    if len(d) and np.median(d) < 0:
        faces = mesh.faces[:, ::-1].copy()
        return Mesh(mesh.vertices, faces, -mesh.normals, mesh.colors)
    return mesh


def mesh_surfels(surfels: dict, settings: MeshConfig | None = None, source=None, stats: dict | None = None) -> Mesh:
    """The mesh of a map's confirmed surfels (``surfels``: position, normal, colour, weight, radius arrays).

    ``stats``, when given, receives the counts (surfels meshed, blocks, voxels) and milliseconds per stage."""
    
    settings = settings or MeshConfig()
    check_voxel_size(settings.voxel_size)
    stats = {} if stats is None else stats
    watch, ms = Stopwatch(), {}
    selected = select_surfels(surfels, settings.min_weight, source)
    grid, voxels = splat_surfels(selected, settings, source)
    ms["splat"] = round(watch.lap(), 1)
    mesh = extract(grid, voxels, settings.voxel_size)
    ms["extract"] = round(watch.lap(), 1)
    if settings.max_triangles and len(mesh) > settings.max_triangles:
        mesh = decimate(mesh, settings.max_triangles)
    ms["decimate"] = round(watch.lap(), 1)
    stats.update({"surfels_meshed": len(selected["position"]), "surfels_in_map": len(surfels["position"]),
                  "blocks": len(grid), "voxels": len(grid) * E ** 3,
                  "voxels_reached": int((voxels["weight"] > 0).sum()),
                  "ms": ms})
    return mesh


class DepthFusion:
    """``mesh.method = "depth"``: the run's depth frames re-integrated at their poses into a sparse truncated
    signed-distance grid (``kernels/mesh.py``: each pixel writes d − z_c into the voxels its ray crosses within
    ``mesh.truncation`` voxels of its depth), then the same marching cubes as the surfels' grid.

    Blocks of 8³ voxels get a slot in a pool when a frame's samples first reach them, so memory grows with the
    observed surface (and a band of ± the truncation about it), never with the bounding box; a frame's own
    lookup table spans only the box of its samples. More than ``mesh.max_voxels`` stops the integration with
    one line naming the setting.

    Each frame also counts, per voxel of the blocks in its view, whether it saw through the voxel (its depth
    beyond it by more than the truncation and ``mesh.carve_sigmas`` σ of the sensor's noise) or saw a surface
    within a voxel of it; voxels seen through by ``mesh.carve_frames`` frames and more often than at a surface
    are empty space when the grid is meshed, so openings that the band behind a surface closed stay open."""

    OFFSET = 1 << 20  # block coordinates are packed into 21 bits each, shifted by this

    def __init__(self, settings: MeshConfig, source=None):
        check_voxel_size(settings.voxel_size)
        self.settings = settings
        self.source = source
        self.voxel = float(settings.voxel_size)
        self.trunc = float(settings.truncation) * self.voxel
        self.step = self.voxel  # along z: about one sample per voxel a ray crosses (neighbouring rays fill the rest)
        self.keys = np.zeros(0, np.int64)   # packed block keys, sorted
        self.slots = np.zeros(0, np.int64)  # the pool slot of each key
        self.blocks = np.zeros((0, 3), np.int64)  # per slot: the block's absolute coordinates
        self.capacity = 0
        self.sdf = np.zeros(0, np.float32)
        self.wsum = np.zeros(0, np.float32)
        self.rgb = np.zeros((0, 3), np.float32)
        # Carving's counts per voxel (None with mesh.carve_frames = 0): frames that saw through it (depth well beyond
        # it), and frames that saw a surface within a voxel of it.
        self.carving = settings.carve_frames > 0
        self.free = np.zeros(0, np.float32) if self.carving else None
        self.near = np.zeros(0, np.float32) if self.carving else None
        self.frames = 0
        self.carved = 0  # voxels with samples that the last grid() turned into empty space

    def __len__(self) -> int:
        return len(self.keys)

    def _grow(self, blocks: int) -> None:
        if blocks * E ** 3 > self.settings.max_voxels:
            per_voxel = SUMS_BYTES_PER_VOXEL + CARVE_BYTES_PER_VOXEL * self.carving + EXTRACT_BYTES_PER_VOXEL
            raise InputError(self.source, f"the frames' surface needs {blocks * E ** 3 / 1e6:.1f} M voxels of "
                                          f"{self.voxel:g} m (~{blocks * E ** 3 * per_voxel / 2**30:.1f} GB), "
                                          f"more than mesh.max_voxels ({self.settings.max_voxels / 1e6:.1f} M): "
                                          "choose a larger mesh.voxel_size or raise the bound")
        if blocks <= self.capacity:
            return
        cap = max(blocks, 2 * self.capacity, 256)
        cap = min(cap, max(blocks, self.settings.max_voxels // E ** 3))
        arrays = [("sdf", ()), ("wsum", ()), ("rgb", (3,))] + ([("free", ()), ("near", ())] if self.carving else [])
        for name, shape in arrays:
            new = np.zeros((cap * E ** 3,) + shape, np.float32)
            old = getattr(self, name)
            new[:len(old)] = old
            setattr(self, name, new)
        blocks = np.zeros((cap, 3), np.int64)
        blocks[:len(self.keys)] = self.blocks[:len(self.keys)]
        self.blocks = blocks
        self.capacity = cap

    def integrate(self, depth: np.ndarray, color: np.ndarray | None, intrinsics, pose: np.ndarray) -> None:
        """Add one frame (depth in metres, 0 = invalid; colour H×W×3 uint8 or None) at ``pose`` (camera to world)."""
        from ti_fusion.backend import current_backend
        from ti_fusion.kernels import mesh as kmesh
        import taichi as ti

        current_backend()
        depth = np.ascontiguousarray(np.where(np.isfinite(depth), depth, 0), np.float32)
        h, w = depth.shape
        valid = depth[depth > 0]
        if len(valid) == 0:
            return
        K = intrinsics
        pose = np.asarray(pose, np.float64)
        lo, hi = self._frame_box((h, w), float(valid.min()), float(valid.max()), K, pose)
        dims = hi - lo + 1
        if np.prod(dims) > max(self.settings.max_voxels // E ** 3, 1 << 22):
            raise InputError(self.source, f"a frame's depth spans {dims.max() * E * self.voxel:.1f} m: more blocks "
                                          f"of {E * self.voxel:g} m than mesh.max_voxels allows; choose a larger "
                                          "mesh.voxel_size or cut the depth range")
        table = np.zeros(tuple(int(x) for x in dims), np.int32)
        args = (ti.math.vec4(K.fx, K.fy, K.cx, K.cy), ti.Matrix(pose[:3, :3].astype(np.float32)),
                ti.math.vec3(*pose[:3, 3].astype(np.float32)), self.voxel, self.trunc, self.step,
                ti.math.ivec3(*(int(x) for x in lo)))
        kmesh.touch_blocks(depth, *args, table)
        touched = np.flatnonzero(table)
        rel = np.stack(np.unravel_index(touched, table.shape), axis=1)
        absolute = rel + lo
        o = self.OFFSET
        key = ((absolute[:, 0] + o) << 42) | ((absolute[:, 1] + o) << 21) | (absolute[:, 2] + o)
        pos = np.searchsorted(self.keys, key)
        known = (pos < len(self.keys)) & (self.keys[np.minimum(pos, max(len(self.keys) - 1, 0))] == key) \
            if len(self.keys) else np.zeros(len(key), bool)
        slot = np.empty(len(key), np.int64)
        slot[known] = self.slots[pos[known]]
        fresh = np.flatnonzero(~known)
        if len(fresh):
            self._grow(len(self.keys) + len(fresh))
            slot[fresh] = len(self.keys) + np.arange(len(fresh))
            self.blocks[slot[fresh]] = absolute[fresh]
            keys = np.concatenate([self.keys, key[fresh]])
            slots = np.concatenate([self.slots, slot[fresh]])
            order = np.argsort(keys, kind="stable")
            self.keys, self.slots = keys[order], slots[order]
        table[...] = -1
        table.reshape(-1)[touched] = slot.astype(np.int32)
        has_color = color is not None
        if has_color:
            c = np.asarray(color)
            if c.shape[:2] != (h, w):  # nearest pixel of a colour image of another size
                c = c[(np.arange(h) * c.shape[0] // h)[:, None], (np.arange(w) * c.shape[1] // w)[None, :]]
            c = np.ascontiguousarray(c[..., :3], np.float32)
        else:
            c = np.zeros((1, 1, 3), np.float32)
        kmesh.integrate_depth(depth, c, int(has_color), *args, table, self.sdf, self.wsum, self.rgb)
        if self.carving:
            self._carve(depth, K, pose, lo, hi)
        self.frames += 1

    def _frame_box(self, shape: tuple[int, int], nearest: float, farthest: float, K,
                   pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first and last block coordinates of a box holding every sample of a frame of ``shape`` (h, w) whose
        valid depth lies in [nearest, farthest]: its frustum's corners there, widened by the truncation."""
        h, w = shape
        z0, z1 = max(nearest - self.trunc, 0.0), farthest + self.trunc
        u = np.array([0.0, w - 1.0, 0.0, w - 1.0])
        v = np.array([0.0, 0.0, h - 1.0, h - 1.0])
        cam = np.concatenate([np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, np.full(4, z)], axis=1)
                              for z in (z0, z1)])
        pts = cam @ pose[:3, :3].T + pose[:3, 3]
        lo = np.floor(np.floor(pts.min(axis=0) / self.voxel - 0.5) / E).astype(np.int64) - 1
        hi = np.floor(np.floor(pts.max(axis=0) / self.voxel + 1.5) / E).astype(np.int64) + 1
        return lo, hi

    def _carve(self, depth: np.ndarray, K, pose: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """Count the frame's look through every voxel of the blocks so far inside its frustum's box (``free``,
        ``near``: the kernel's ``carve_depth``)."""
        from ti_fusion.kernels import mesh as kmesh
        import taichi as ti

        blocks = self.blocks[:len(self.keys)]  # slot order: block i's voxels are at slot i
        inside = np.flatnonzero(((blocks >= lo) & (blocks <= hi)).all(axis=1))
        if not len(inside):
            return
        kmesh.carve_depth(depth, ti.math.vec4(K.fx, K.fy, K.cx, K.cy), ti.Matrix(pose[:3, :3].astype(np.float32)),
                          ti.math.vec3(*pose[:3, 3].astype(np.float32)), self.voxel, self.trunc,
                          float(self.settings.carve_sigmas), self.voxel,
                          np.ascontiguousarray(blocks[inside], np.int32), inside.astype(np.int32), len(inside),
                          self.free, self.near)

    def grid(self) -> tuple[SparseGrid, dict]:
        """The sparse grid of the blocks so far and its voxels (as ``splat_surfels`` returns them)."""
        if not len(self.keys):
            raise InputError(self.source, "no frame had valid depth: no surface to mesh")
        grid = SparseGrid.of_blocks(self.blocks[self.slots], self.voxel, self.source)  # in the keys' order
        idx = (self.slots[:, None] * E ** 3 + np.arange(E ** 3)).reshape(-1)
        wsum = self.wsum[idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = np.where(wsum > 0, 1.0 / wsum, 0.0).astype(np.float32)
        sdf = self.sdf[idx] * inv
        self.carved = 0
        # counted while integrating, and still asked for (mesh.carve_frames set to 0 since: the same frames uncarved)
        if self.carving and self.settings.carve_frames > 0:
            self._carve_empty(idx, wsum, sdf)
        shape = (len(grid), E, E, E)
        return grid, {"sdf": sdf.reshape(shape), "weight": wsum.reshape(shape),
                      "color": (self.rgb[idx] * inv[:, None]).reshape(shape + (3,))}

    def _carve_empty(self, idx: np.ndarray, wsum: np.ndarray, sdf: np.ndarray) -> None:
        """Make no surface in the empty space among the voxels ``idx`` (pool indices; their ``wsum`` and mean ``sdf``
        are changed in place): voxels seen through by at least ``mesh.carve_frames`` frames, and by more frames than
        saw a surface within a voxel of them."""
        # Seen-through voxels that the band behind a surface made negative (a slot beside a slat, the space behind
        # it) are empty space. Where a frame saw a surface within a voxel of one, it stays as one voxel in front
        # of that surface, so the surface it borders is contoured (a slot's sides); elsewhere it leaves the grid,
        # so that no surface is made in the middle of empty space (a spurious one between it and the shadow
        # behind a slat, which no camera saw).
        free, near = self.free[idx], self.near[idx]
        empty = (free >= self.settings.carve_frames) & (free > near)
        carved = empty & (wsum > self.settings.depth_min_weight) & (sdf <= 0)
        seen = near > 0
        sdf[carved & seen] = np.float32(self.voxel)
        wsum[carved & ~seen] = np.float32(0)
        self.carved = int(carved.sum())

    def mesh(self, stats: dict | None = None) -> Mesh:
        """Marching cubes over the voxels with more than ``mesh.depth_min_weight`` samples."""
        stats = {} if stats is None else stats
        watch, ms = Stopwatch(), {}
        grid, voxels = self.grid()
        ms["gather"] = round(watch.lap(), 1)
        mesh = extract(grid, voxels, self.voxel, self.settings.depth_min_weight)
        ms["extract"] = round(watch.lap(), 1)
        if self.settings.max_triangles and len(mesh) > self.settings.max_triangles:
            mesh = decimate(mesh, self.settings.max_triangles)
        ms["decimate"] = round(watch.lap(), 1)
        stats.update({"method": "depth", "frames_integrated": self.frames, "blocks": len(grid),
                      "voxels_carved": self.carved,
                      "voxels": len(grid) * E ** 3,
                      "voxels_reached": int((voxels["weight"] > self.settings.depth_min_weight).sum()),
                      "ms": ms})
        return mesh


class RunMesh:
    """``slam --mesh``: the mesh of the map at the end of a run, on the log's /map/mesh before the log
    closes, then mesh.ply and mesh.glb with the run's other files. A map that cannot be meshed (no confirmed
    surfel, too large for the bound) costs the run a warning, not its other outputs."""

    def __init__(self, config: MeshConfig):
        self.config = config
        self.mesh: Mesh | None = None
        self.summary: dict = {}
        # mesh.method = "depth": each tracked frame goes into the grid at its pose as the run goes
        self.depth = DepthFusion(config) if config.method == "depth" else None
        self.depth_error: InputError | None = None
        self.integrate_s = 0.0
        self.first_pose: np.ndarray | None = None  # its camera's up is mesh.glb's up

    def integrate(self, frame, pose: np.ndarray | None) -> None:
        """A tracked frame's depth and colour at its pose (mesh.method = "depth"; otherwise nothing)."""
        if self.first_pose is None and pose is not None:
            self.first_pose = np.array(pose, np.float64)
        if self.depth is None or pose is None or self.depth_error is not None:
            return
        watch = Stopwatch()
        try:
            self.depth.integrate(frame.depth, frame.color, frame.intrinsics, pose)
        except InputError as exc:  # over the bound: the mesh is given up, the run goes on
            log.warning(f"no mesh: {exc.problem}")
            self.depth_error = exc
        self.integrate_s += watch.ms / 1e3

    def make(self, mapper, run_log=None, t: float = 0.0) -> None:
        watch = Stopwatch()
        stats: dict = {}
        try:
            if self.depth_error is not None:
                raise self.depth_error
            if self.depth is not None:
                self.mesh = self.depth.mesh(stats)
                stats["integrate_s"] = round(self.integrate_s, 3)
            else:
                self.mesh = mesh_surfels(mapper.to_numpy(), self.config, stats=stats)
        except InputError as exc:
            if exc is not self.depth_error:
                log.warning(f"no mesh: {exc.problem}")
            self.summary = {"mesh_error": str(exc)}
            return
        self.summary = {"method": self.config.method, "triangles": len(self.mesh), "vertices": len(self.mesh.vertices),
                        "area_m2": round(self.mesh.area(), 4), "voxel_size": self.config.voxel_size,
                        "mesh_s": round(watch.ms / 1e3, 3), **stats}
        source = (f"{stats['frames_integrated']} depth frames" if self.depth is not None
                  else f"{stats['surfels_meshed']} confirmed surfels")
        log.info(f"mesh: {len(self.mesh)} triangles, {self.summary['area_m2']:.2f} m² from {source} "
                 f"at {self.config.voxel_size * 100:g} cm voxels in {self.summary['mesh_s']:.2f} s")
        cap = self.config.log_triangles
        if run_log is not None and cap and len(self.mesh):
            run_log.log_mesh(t, self.mesh if len(self.mesh) <= cap else decimate(self.mesh, cap))

    def outputs(self, out) -> dict:
        """mesh.ply and mesh.glb in ``out``; the ``mesh`` field of summary.json."""
        from ti_fusion.io.mesh_files import camera_up, write_run_mesh

        if self.mesh is not None:
            up = None if self.first_pose is None else camera_up(self.first_pose)
            self.summary.update(write_run_mesh(out, self.mesh, up))
        return {"mesh": self.summary} if self.summary else {}


def decimate(mesh: Mesh, max_triangles: int) -> Mesh:
    """At most ``max_triangles`` triangles by vertex clustering: vertices in one cell of a coarser grid become
    their mean (colours and normals averaged too), and triangles that collapse are dropped. The cell is the
    smallest power-of-1.25 multiple of the mesh's mean edge that meets the count."""
    v = mesh.vertices.astype(np.float64)
    edge = float(np.mean(np.linalg.norm(v[mesh.faces[:, 0]] - v[mesh.faces[:, 1]], axis=1)))
    cell = edge
    for _ in range(60):
        key = np.floor(v / cell).astype(np.int64)
        _, cluster = np.unique(key, axis=0, return_inverse=True)
        cluster = cluster.reshape(-1)
        f = cluster[mesh.faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        if len(np.unique(np.sort(f, axis=1), axis=0)) <= max_triangles:
            break
        cell *= 1.25
    f = cluster[mesh.faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    m = cluster.max() + 1
    counts = np.bincount(cluster, minlength=m)[:, None]
    pos = np.zeros((m, 3))
    col = np.zeros((m, 3))
    nrm = np.zeros((m, 3))
    np.add.at(pos, cluster, v)
    np.add.at(col, cluster, mesh.colors.astype(np.float64))
    np.add.at(nrm, cluster, mesh.normals.astype(np.float64))
    pos /= counts
    col /= counts
    used = np.unique(f)
    remap = np.full(m, -1)
    remap[used] = np.arange(len(used))
    vertices = pos[used].astype(np.float32)
    faces = remap[f]
    normals = vertex_normals(vertices, faces)
    # keep the side the full mesh faced: the clustered vertex normals agree with the averaged ones
    flip = np.sum(normals * nrm[used], axis=1) < 0
    if flip.mean() > 0.5:
        faces = faces[:, ::-1].copy()
        normals = -normals
    return Mesh(vertices, faces, normals, np.clip(np.rint(col[used]), 0, 255).astype(np.uint8))


def surfels_from_ply(path: str | Path) -> dict:
    """A map.ply's surfels: position, normal, colour, and confidence and radius where the file has them."""
    from ti_fusion.io.ply import read_ply

    path = Path(path)
    data = read_ply(path)
    names = data.dtype.names
    if not {"nx", "ny", "nz"} <= set(names):
        raise InputError(path, "has no normals (nx, ny, nz): a mesh needs oriented surfels, such as a run's map.ply")
    out = {"position": np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float32),
           "normal": np.stack([data["nx"], data["ny"], data["nz"]], axis=1).astype(np.float32)}
    if {"red", "green", "blue"} <= set(names):
        out["color"] = np.stack([data["red"], data["green"], data["blue"]], axis=1).astype(np.float32)
    if "confidence" in names:
        out["weight"] = data["confidence"].astype(np.float32)
    elif len(data):
        log.warning(f"{path} has no confidence: every surfel is taken as confirmed")
    if "radius" in names:
        out["radius"] = data["radius"].astype(np.float32)
    return out
