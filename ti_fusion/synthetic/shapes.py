"""The synthetic scene: analytic primitives with procedural materials, the furnished room and its camera
path.

World frame: metres, z up, the room spans x ∈ [−2.5, 2.5], y ∈ [−2, 2], z ∈ [0, 2.7]. Camera frame:
x right, y down, z forward (as every loader's). Poses are camera-to-world.

The scene is a list of analytic primitives (walls, boxes rotated about z, spheres, vertical cylinders),
each with a procedural material; ``Scene.table()`` packs them for the ray caster in
``ti_fusion.kernels.scene_render`` and ``Scene.distances`` gives exact point-to-surface distances, so tests
can check that reconstructed points lie on the true surfaces. The other scenes are in ``scenes.py``; the
sequence that renders them is in ``scene.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FPS = 30.0
T0 = 1.0  # timestamp of frame 0 (seconds)

ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.7])


# -- scene ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Material:
    """Procedural texture: ``pattern`` cells of ``scale`` × ``scale·aspect`` metres mixing two colours."""

    pattern: str                   # checker | tiles | bricks | plaid | blobs
    scale: float                   # metres
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    aspect: float = 1.0
    detail: float = 0.3            # contrast of the fine value-noise detail
    salt: int | None = None        # texture seed; None = from the primitive's index (copies look alike only with one)


@dataclass(frozen=True)
class Plane:
    """An infinite plane seen from the side its normal points to (the room's walls, normals inward)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    material: Material


@dataclass(frozen=True)
class Box:
    center: tuple[float, float, float]
    half: tuple[float, float, float]  # half extents along the box's own axes
    material: Material
    yaw: float = 0.0                  # radians, rotation about the vertical z axis


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    material: Material


@dataclass(frozen=True)
class Cylinder:
    """A vertical capped cylinder."""

    center: tuple[float, float, float]
    radius: float
    half_height: float
    material: Material


Primitive = Plane | Box | Sphere | Cylinder


class Scene:
    """A list of primitives: packed for the ray caster, and exact distances to their surfaces."""

    def __init__(self, primitives: list[Primitive]):
        self.primitives = list(primitives)

    def __len__(self) -> int:
        return len(self.primitives)

    def table(self) -> np.ndarray:
        """P × NUM_COLUMNS float32 rows as ``ti_fusion.kernels.scene_render`` reads them."""
        from ti_fusion.kernels import scene_render as rc

        patterns = {"checker": rc.CHECKER, "tiles": rc.TILES, "bricks": rc.BRICKS, "plaid": rc.PLAID,
                    "blobs": rc.BLOBS}
        rows = np.zeros((len(self.primitives), rc.NUM_COLUMNS), np.float64)
        for k, prim in enumerate(self.primitives):
            row = rows[k]
            row[rc.YAW:rc.YAW + 2] = (1.0, 0.0)
            if isinstance(prim, Plane):
                n = np.asarray(prim.normal, float)
                row[rc.KIND] = rc.PLANE
                row[rc.CENTER:rc.CENTER + 3] = prim.point
                row[rc.NORMAL:rc.NORMAL + 3] = n / np.linalg.norm(n)
                row[rc.BOUND] = -1.0
            elif isinstance(prim, Box):
                row[rc.KIND] = rc.BOX
                row[rc.CENTER:rc.CENTER + 3] = prim.center
                row[rc.HALF:rc.HALF + 3] = prim.half
                row[rc.YAW:rc.YAW + 2] = (np.cos(prim.yaw), np.sin(prim.yaw))
                row[rc.BOUND] = np.linalg.norm(prim.half)
            elif isinstance(prim, Sphere):
                row[rc.KIND] = rc.SPHERE
                row[rc.CENTER:rc.CENTER + 3] = prim.center
                row[rc.HALF:rc.HALF + 3] = prim.radius
                row[rc.BOUND] = prim.radius
            elif isinstance(prim, Cylinder):
                row[rc.KIND] = rc.CYLINDER
                row[rc.CENTER:rc.CENTER + 3] = prim.center
                row[rc.HALF:rc.HALF + 3] = (prim.radius, prim.radius, prim.half_height)
                row[rc.BOUND] = np.hypot(prim.radius, prim.half_height)
            else:
                raise TypeError(f"unknown primitive {prim!r}")
            m = prim.material
            row[rc.PATTERN] = patterns[m.pattern]
            row[rc.SCALE] = m.scale
            row[rc.ASPECT] = m.aspect
            row[rc.DETAIL] = m.detail
            row[rc.COLOR_A:rc.COLOR_A + 3] = m.color_a
            row[rc.COLOR_B:rc.COLOR_B + 3] = m.color_b
            row[rc.SALT] = 101 * k + 7 if m.salt is None else m.salt
        return rows.astype(np.float32)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """N × P float64: unsigned distance from each point to each primitive's surface (planes: infinite)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.empty((len(p), len(self.primitives)))
        for k, prim in enumerate(self.primitives):
            out[:, k] = np.abs(_signed_distance(prim, p))
        return out

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (metres, float64) from each of N×3 world points to the nearest scene surface."""
        return self.distances(points).min(axis=1)


def _signed_distance(prim: Primitive, p: np.ndarray) -> np.ndarray:
    if isinstance(prim, Plane):
        n = np.asarray(prim.normal, float)
        return (p - prim.point) @ (n / np.linalg.norm(n))
    if isinstance(prim, Sphere):
        return np.linalg.norm(p - prim.center, axis=1) - prim.radius
    if isinstance(prim, Box):
        c, s = np.cos(prim.yaw), np.sin(prim.yaw)
        q = p - prim.center
        local = np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], axis=1)
        d = np.abs(local) - prim.half
        outside = np.linalg.norm(np.maximum(d, 0.0), axis=1)
        return outside + np.minimum(d.max(axis=1), 0.0)
    if isinstance(prim, Cylinder):
        q = p - prim.center
        d = np.stack([np.hypot(q[:, 0], q[:, 1]) - prim.radius, np.abs(q[:, 2]) - prim.half_height], axis=1)
        return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
    raise TypeError(f"unknown primitive {prim!r}")


def default_scene() -> Scene:
    """A 5 m × 4 m × 2.7 m room with furniture: every view has planes in three directions and curves."""
    M = Material
    x0, y0, z0 = ROOM_MIN
    x1, y1, z1 = ROOM_MAX
    prims: list[Primitive] = [
        # walls, floor, ceiling (normals into the room)
        Plane((0, 0, z0), (0, 0, 1), M("bricks", 0.6, (0.42, 0.27, 0.16), (0.78, 0.57, 0.36), aspect=0.22, detail=0.35)),
        Plane((0, 0, z1), (0, 0, -1), M("checker", 0.6, (0.70, 0.72, 0.76), (0.92, 0.91, 0.86), detail=0.25)),
        Plane((x0, 0, 0), (1, 0, 0), M("bricks", 0.25, (0.50, 0.22, 0.16), (0.85, 0.50, 0.35), aspect=0.4)),
        Plane((x1, 0, 0), (-1, 0, 0), M("tiles", 0.12, (0.18, 0.28, 0.50), (0.78, 0.84, 0.92))),
        Plane((0, y0, 0), (0, 1, 0), M("plaid", 0.09, (0.28, 0.45, 0.30), (0.88, 0.82, 0.60))),
        Plane((0, y1, 0), (0, -1, 0), M("blobs", 0.16, (0.30, 0.30, 0.38), (0.92, 0.86, 0.74), detail=0.4)),
        # table: a rotated top on four legs, two balls on it
        Box((0.2, 0.1, 0.74), (0.65, 0.42, 0.02), M("checker", 0.08, (0.40, 0.22, 0.10), (0.85, 0.70, 0.45)), yaw=0.3),
        *[Box(_rotated_offset((0.2, 0.1), (sx * 0.58, sy * 0.35), 0.3) + (0.36,), (0.03, 0.03, 0.36),
              M("tiles", 0.05, (0.15, 0.15, 0.15), (0.65, 0.60, 0.55)), yaw=0.3)
          for sx in (-1, 1) for sy in (-1, 1)],
        Sphere((0.38, 0.05, 0.90), 0.14, M("tiles", 0.05, (0.85, 0.45, 0.10), (0.98, 0.90, 0.55))),
        Sphere((-0.05, 0.28, 0.85), 0.09, M("checker", 0.04, (0.35, 0.15, 0.45), (0.85, 0.75, 0.90))),
        # along the walls: cabinet with a box and a picture above, bookshelf, desk with a monitor, pictures
        Box((-2.2, 0.4, 0.45), (0.3, 0.6, 0.45), M("tiles", 0.1, (0.55, 0.50, 0.40), (0.95, 0.92, 0.85))),
        Box((-2.2, 0.25, 1.0), (0.15, 0.22, 0.1), M("plaid", 0.04, (0.60, 0.10, 0.10), (0.95, 0.85, 0.30)), yaw=0.35),
        Box((-2.47, -0.8, 1.6), (0.03, 0.35, 0.25), M("tiles", 0.04, (0.10, 0.20, 0.35), (0.95, 0.80, 0.40))),
        Box((-0.6, 1.78, 0.95), (0.55, 0.22, 0.95), M("plaid", 0.06, (0.20, 0.15, 0.45), (0.95, 0.75, 0.35))),
        Box((0.6, -1.7, 0.38), (0.7, 0.3, 0.38), M("bricks", 0.2, (0.30, 0.35, 0.40), (0.80, 0.82, 0.80), aspect=0.5)),
        Box((0.6, -1.82, 0.96), (0.3, 0.03, 0.2), M("checker", 0.03, (0.05, 0.05, 0.08), (0.55, 0.70, 0.85))),
        Box((2.47, -0.4, 1.5), (0.03, 0.45, 0.32), M("checker", 0.05, (0.60, 0.20, 0.15), (0.95, 0.95, 0.85))),
        # free-standing: armchair-like block with a back, cube, pillar, bin, ball, floor lamp
        Box((1.55, 1.35, 0.22), (0.4, 0.36, 0.22), M("blobs", 0.08, (0.25, 0.40, 0.20), (0.85, 0.90, 0.60)), yaw=0.6),
        Box(_rotated_offset((1.55, 1.35), (0.0, 0.3), 0.6) + (0.6,), (0.4, 0.07, 0.38),
            M("blobs", 0.07, (0.25, 0.40, 0.20), (0.85, 0.90, 0.60)), yaw=0.6),
        Box((1.75, -1.3, 0.25), (0.25, 0.25, 0.25), M("tiles", 0.07, (0.60, 0.55, 0.15), (0.20, 0.25, 0.55)), yaw=0.9),
        Cylinder((-2.05, -1.55, 1.35), 0.16, 1.35, M("bricks", 0.12, (0.55, 0.55, 0.55), (0.90, 0.88, 0.80), aspect=0.5)),
        Cylinder((-1.25, -1.3, 0.3), 0.2, 0.3, M("plaid", 0.05, (0.10, 0.35, 0.45), (0.90, 0.90, 0.90))),
        Sphere((-0.95, -0.55, 0.22), 0.22, M("blobs", 0.06, (0.75, 0.15, 0.20), (0.95, 0.90, 0.85))),
        Cylinder((2.05, 0.9, 0.78), 0.04, 0.78, M("tiles", 0.04, (0.20, 0.20, 0.20), (0.75, 0.75, 0.70))),
        Sphere((2.05, 0.9, 1.72), 0.17, M("checker", 0.05, (0.90, 0.85, 0.50), (0.99, 0.98, 0.90))),
    ]
    return Scene(prims)


def _rotated_offset(center: tuple[float, float], offset: tuple[float, float], yaw: float) -> tuple[float, float]:
    c, s = np.cos(yaw), np.sin(yaw)
    return (center[0] + c * offset[0] - s * offset[1], center[1] + s * offset[0] + c * offset[1])


# -- camera path ---------------------------------------------------------------------------------------
def look_at(position: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at ``position`` looking at ``target`` (world z up), rolled about its axis."""
    f = np.asarray(target, float) - position
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    c, s = np.cos(roll), np.sin(roll)
    R = np.stack([right, down, f], axis=1) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = position
    return T


def camera_path(times: np.ndarray) -> np.ndarray:
    """N × 4 × 4 camera-to-world poses at ``times`` (seconds from the start): a smooth hand-held walk.

    The camera circles the table at 1.3 m × 1.0 m around it (≈ 0.3 m/s, one lap in 24 s), at eye height
    with a slow bob and a little hand shake, looking at a point that wanders over the table and the
    furniture around it, with a few degrees of roll: rotation about all three axes, always at structure.
    """
    poses = []
    for t in np.asarray(times, dtype=np.float64):
        angle = -0.6 + 0.26 * t
        position = np.array([
            0.15 + 1.3 * np.cos(angle) + 0.006 * np.sin(2 * np.pi * 1.1 * t),
            0.05 + 1.0 * np.sin(angle) + 0.006 * np.sin(2 * np.pi * 0.9 * t + 1.0),
            1.40 + 0.12 * np.sin(0.5 * t + 0.3) + 0.005 * np.sin(2 * np.pi * 1.3 * t + 2.0),
        ])
        target = np.array([
            0.2 + 0.6 * np.sin(0.55 * t + 0.5),
            0.1 + 0.5 * np.sin(0.73 * t + 1.3),
            0.85 + 0.25 * np.sin(0.61 * t + 2.0),
        ])
        roll = np.radians(6.0 * np.sin(0.8 * t + 0.4) + 2.0 * np.sin(1.9 * t))
        poses.append(look_at(position, target, roll))
    return np.array(poses)
