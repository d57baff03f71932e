"""The catalogue of synthetic scenes, each with its own hand-held camera path and length.

``room``      the furnished 5 m × 4 m room (``shapes.default_scene``), 120 frames circling the table.
``loop``      a closed corridor loop, 12 m × 8 m outside around an 8 m × 4 m block, corridors 2 m wide and
              2.6 m high, textured walls and furniture (no door frames or pilasters: long stretches of wall and
              floor give depth-only tracking room to drift); the camera walks once around it
              (≈ 0.65 m/s) and on past its start, so the last views re-observe the first ones.
``twins``     ``loop`` with two identical 4 m sections (walls, floor, ceiling panels and furniture) in the
              middle of the south and north corridors, one the other turned half a turn about the centre:
              walking round, the north one looks exactly like the south one (a false loop).
``wall``      one large textured wall and the floor in front of it (an edge, no corner): the camera moves
              along it, up and down and toward it. Depth fixes only the two planes: motion along the wall
              is unobservable without colour.
``corridor``  an endless straight corridor with plain walls, floor and ceiling and textured posters flat on
              the walls (1 mm thick, 0.8 m × 1 m, every 1.2 m on each wall): depth cannot see motion along the corridor.
``jerky``     the furnished room seen at irregular, large steps: frames at random gaps of 0.1–0.7 s of a fast
              hand-held 30 Hz path (up to ~17° and ~30 cm per step), as from a dropped-frame stream or a fast
              turn: a constant-velocity guess is often further from the truth than the last pose.
``cabinet``   a plain box (a cabinet) in a room of plain walls, only mild colour gradients, circled once by a
              camera whose speed changes; one frame every 0.67 s (every 20th of the 30 Hz path), steps of up
              to ~23 cm and ~17°: wide baselines on low texture, where feature re-localisation has little to match.
``slats``     a chair back of vertical slats with 3 cm slots between them, 0.6 m in front of a wall, seen from an
              arc of ±35° in front of it: the wall shows through every slot (a mesh must keep them open).

World frame as in ``shapes``: metres, z up. The loop scenes are centred under the renderer's point light
(``kernels.scene_render.LIGHT``) so their shading, like their geometry, is symmetric under a half turn about
the centre (what makes the twins identical, light included). Paths are functions of time (seconds from
the first frame) sampled at 30 Hz, except where a scene's ``times`` samples them otherwise (``jerky``,
``cabinet``); evaluated past their default length they go on (the loop keeps walking round, so ``frames``
= 2 × the default is about two laps).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ti_fusion.synthetic.shapes import (FPS, Box, Cylinder, Material, Plane, Primitive, Scene, Sphere,
                                        camera_path, default_scene, look_at)


def regular_times(frames: int) -> np.ndarray:
    """Seconds from the first frame of ``frames`` frames at 30 Hz."""
    return np.arange(frames) / FPS

M = Material

# -- the loop ------------------------------------------------------------------------------------------
LOOP_CENTER = np.array([0.4, -0.3])  # under kernels.scene_render.LIGHT: shading symmetric under a half turn
LOOP_OUTER = np.array([6.0, 4.0])    # half extents of the outside walls
LOOP_BLOCK = np.array([4.0, 2.0])    # half extents of the central block
LOOP_HEIGHT = 2.6
LOOP_RADIUS = 1.0                     # the walk's centre line: the block grown by 1 m (corridor middle)
LOOP_SPEED = 0.65                     # m/s, mean walking speed
LOOP_LENGTH = 2 * 2 * (LOOP_BLOCK[0] + LOOP_BLOCK[1]) + 2 * np.pi * LOOP_RADIUS  # centre line, ≈ 30.3 m
LOOP_OVERLAP = 3.0                    # metres walked past the start, re-observing the first views
LOOP_FRAMES = int(round((LOOP_LENGTH + LOOP_OVERLAP) / LOOP_SPEED * FPS))
TWIN_HALF_LENGTH = 2.0                # the twin sections span x ∈ [−2, 2] (relative to the centre)


def _at(x: float, y: float) -> tuple[float, float]:
    """A point given relative to the loop's centre, in world coordinates."""
    return float(LOOP_CENTER[0] + x), float(LOOP_CENTER[1] + y)


def _loop_shell() -> list[Primitive]:
    """Floor, ceiling, the four outside walls (infinite planes facing in) and the central block."""
    cx, cy = LOOP_CENTER
    ox, oy = LOOP_OUTER
    return [
        Plane((0, 0, 0), (0, 0, 1), M("tiles", 0.3, (0.45, 0.40, 0.35), (0.80, 0.76, 0.68), detail=0.35)),
        Plane((0, 0, LOOP_HEIGHT), (0, 0, -1), M("checker", 0.6, (0.72, 0.72, 0.76), (0.93, 0.92, 0.88), detail=0.25)),
        Plane((cx - ox, 0, 0), (1, 0, 0), M("bricks", 0.25, (0.50, 0.22, 0.16), (0.85, 0.50, 0.35), aspect=0.4)),
        Plane((cx + ox, 0, 0), (-1, 0, 0), M("tiles", 0.12, (0.18, 0.28, 0.50), (0.78, 0.84, 0.92))),
        Plane((0, cy - oy, 0), (0, 1, 0), M("plaid", 0.09, (0.28, 0.45, 0.30), (0.88, 0.82, 0.60))),
        Plane((0, cy + oy, 0), (0, -1, 0), M("blobs", 0.16, (0.30, 0.30, 0.38), (0.92, 0.86, 0.74), detail=0.4)),
        Box((cx, cy, LOOP_HEIGHT / 2), (LOOP_BLOCK[0], LOOP_BLOCK[1], LOOP_HEIGHT / 2),
            M("bricks", 0.3, (0.55, 0.45, 0.30), (0.95, 0.85, 0.60), aspect=0.3, detail=0.35)),
    ]


def _loop_furniture() -> list[tuple[float, float, Primitive]]:
    """(x, y relative to the centre, primitive) of the loop's furniture: what stands higher than 1 m reaches
    at most 0.32 m into a corridor, so the walk (within 0.2 m of the corridor's middle) keeps ≥ 0.4 m away."""
    ox, oy = LOOP_OUTER
    bx, by = LOOP_BLOCK
    h = LOOP_HEIGHT / 2
    items: list[tuple[float, float, Primitive]] = []

    def box(x, y, half, material, yaw=0.0, z=None):
        wx, wy = _at(x, y)
        items.append((x, y, Box((wx, wy, half[2] if z is None else z), half, material, yaw=yaw)))

    def cyl(x, y, r, hh, material, z=None):
        wx, wy = _at(x, y)
        items.append((x, y, Cylinder((wx, wy, hh if z is None else z), r, hh, material)))

    def ball(x, y, z, r, material):
        wx, wy = _at(x, y)
        items.append((x, y, Sphere((wx, wy, z), r, material)))

    # south corridor (y ∈ [−4, −2]): cabinet, bins, pictures, bench
    box(-3.6, -oy + 0.3, (0.45, 0.28, 0.5), M("tiles", 0.1, (0.55, 0.50, 0.40), (0.95, 0.92, 0.85)))
    box(-3.6, -oy + 0.3, (0.2, 0.15, 0.12), M("plaid", 0.04, (0.60, 0.10, 0.10), (0.95, 0.85, 0.30)), yaw=0.4, z=1.12)
    cyl(-1.2, -by - 0.25, 0.2, 0.35, M("plaid", 0.05, (0.10, 0.35, 0.45), (0.90, 0.90, 0.90)))
    box(1.0, -oy + 0.02, (0.5, 0.02, 0.35), M("checker", 0.05, (0.60, 0.20, 0.15), (0.95, 0.95, 0.85)), z=1.5)
    box(2.4, -oy + 0.25, (0.7, 0.22, 0.23), M("blobs", 0.08, (0.25, 0.40, 0.20), (0.85, 0.90, 0.60)))
    box(-0.2, -by - 0.02, (0.4, 0.02, 0.3), M("tiles", 0.04, (0.10, 0.20, 0.35), (0.95, 0.80, 0.40)), z=1.6)
    # east corridor (x ∈ [4, 6]): shelf, plant, ball
    box(ox - 0.17, -0.9, (0.15, 0.6, 0.9), M("plaid", 0.06, (0.20, 0.15, 0.45), (0.95, 0.75, 0.35)))
    cyl(ox - 0.3, 1.1, 0.18, 0.25, M("bricks", 0.08, (0.45, 0.25, 0.15), (0.80, 0.55, 0.40), aspect=0.5))
    ball(ox - 0.3, 1.1, 0.75, 0.28, M("blobs", 0.05, (0.15, 0.45, 0.15), (0.60, 0.85, 0.40)))
    box(bx + 0.02, 0.8, (0.02, 0.45, 0.3), M("checker", 0.05, (0.05, 0.05, 0.08), (0.55, 0.70, 0.85)), z=1.45)
    ball(bx + 0.3, -1.3, 0.25, 0.25, M("tiles", 0.05, (0.85, 0.45, 0.10), (0.98, 0.90, 0.55)))
    # north corridor (y ∈ [2, 4]): desk with a monitor, column, cube, pictures
    box(2.8, oy - 0.3, (0.6, 0.3, 0.38), M("bricks", 0.2, (0.30, 0.35, 0.40), (0.80, 0.82, 0.80), aspect=0.5))
    box(2.8, oy - 0.15, (0.3, 0.03, 0.2), M("checker", 0.03, (0.05, 0.05, 0.08), (0.55, 0.70, 0.85)), z=0.96)
    cyl(0.6, by + 0.2, 0.16, h, M("bricks", 0.12, (0.55, 0.55, 0.55), (0.90, 0.88, 0.80), aspect=0.5))
    box(-1.5, oy - 0.25, (0.25, 0.25, 0.25), M("tiles", 0.07, (0.60, 0.55, 0.15), (0.20, 0.25, 0.55)), yaw=0.3)
    box(-3.3, oy - 0.02, (0.45, 0.02, 0.3), M("blobs", 0.06, (0.75, 0.15, 0.20), (0.95, 0.90, 0.85)), z=1.5)
    box(-0.9, by + 0.02, (0.35, 0.02, 0.45), M("plaid", 0.05, (0.10, 0.35, 0.45), (0.90, 0.90, 0.90)), z=1.4)
    # west corridor (x ∈ [−6, −4]): lockers, bin, picture
    box(-ox + 0.17, 0.6, (0.15, 0.7, 0.9), M("tiles", 0.15, (0.35, 0.45, 0.55), (0.85, 0.88, 0.90), aspect=2.0))
    cyl(-bx - 0.25, -0.8, 0.2, 0.3, M("checker", 0.04, (0.35, 0.15, 0.45), (0.85, 0.75, 0.90)))
    box(-bx - 0.02, 1.0, (0.02, 0.4, 0.3), M("tiles", 0.04, (0.40, 0.10, 0.10), (0.95, 0.85, 0.70)), z=1.5)
    box(-ox + 0.3, -1.4, (0.25, 0.25, 0.45), M("blobs", 0.07, (0.25, 0.25, 0.45), (0.85, 0.85, 0.95)), yaw=0.2)
    return items


def _twin_section(turn: bool, salt0: int = 5000) -> list[Primitive]:
    """The twin section of the south corridor (x ∈ [−2, 2] about the centre), or (``turn``) its copy turned
    half a turn about the centre, in the north corridor. Every surface seen there is a box with an explicit
    texture seed, so the copy is identical, seen from the turned viewpoint, pixel for pixel."""
    ox, oy = LOOP_OUTER
    bx, by = LOOP_BLOCK
    L = TWIN_HALF_LENGTH
    h = LOOP_HEIGHT / 2
    parts = [  # (x, y, z, half, yaw, material), relative to the centre
        (0.0, -oy + 0.005, h, (L, 0.005, h), 0.0, M("blobs", 0.14, (0.20, 0.30, 0.45), (0.90, 0.85, 0.70), detail=0.4)),
        (0.0, -by - 0.005, h, (L, 0.005, h), 0.0, M("bricks", 0.22, (0.45, 0.20, 0.25), (0.90, 0.70, 0.60), aspect=0.4)),
        (0.0, -oy / 2 - by / 2, 0.005, (L, 1.0, 0.005), 0.0, M("tiles", 0.2, (0.30, 0.30, 0.30), (0.85, 0.80, 0.70))),
        (0.0, -oy / 2 - by / 2, LOOP_HEIGHT - 0.005, (L, 1.0, 0.005), 0.0,
         M("checker", 0.5, (0.75, 0.75, 0.80), (0.95, 0.95, 0.90))),
        (-1.2, -oy + 0.3, 0.45, (0.4, 0.28, 0.45), 0.0, M("tiles", 0.09, (0.50, 0.40, 0.25), (0.95, 0.90, 0.75))),
        (-1.2, -oy + 0.3, 1.0, (0.15, 0.12, 0.1), 0.5, M("plaid", 0.04, (0.10, 0.40, 0.60), (0.95, 0.85, 0.35))),
        (0.9, -oy + 0.015, 1.5, (0.45, 0.01, 0.3), 0.0, M("checker", 0.05, (0.55, 0.15, 0.10), (0.95, 0.95, 0.80))),
        (0.4, -by - 0.25, 0.35, (0.2, 0.2, 0.35), 0.3, M("blobs", 0.06, (0.25, 0.45, 0.20), (0.90, 0.90, 0.60))),
        (-0.6, -by - 0.015, 1.45, (0.35, 0.01, 0.35), 0.0, M("tiles", 0.04, (0.15, 0.15, 0.35), (0.95, 0.80, 0.40))),
        (1.6, -oy + 0.2, 0.2, (0.25, 0.18, 0.2), 0.0, M("checker", 0.06, (0.60, 0.55, 0.15), (0.20, 0.25, 0.55))),
    ]
    out: list[Primitive] = []
    for k, (x, y, z, half, yaw, material) in enumerate(parts):
        material = replace(material, salt=salt0 + 101 * k)
        if turn:
            x, y, yaw = -x, -y, yaw + np.pi
        wx, wy = _at(x, y)
        out.append(Box((wx, wy, z), half, material, yaw=yaw))
    return out


def _in_twin_section(x: float, y: float) -> bool:
    return abs(x) <= TWIN_HALF_LENGTH + 0.3 and abs(y) >= LOOP_BLOCK[1] - 0.1


def loop_scene() -> Scene:
    return Scene(_loop_shell() + [p for _, _, p in _loop_furniture()])


def twins_scene() -> Scene:
    furniture = [p for x, y, p in _loop_furniture() if not _in_twin_section(x, y)]
    return Scene(_loop_shell() + furniture + _twin_section(False) + _twin_section(True))


def loop_centre_line(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points N×2, unit tangents N×2) of the loop's centre line at arc lengths ``s`` (metres, any value:
    periodic), counter-clockwise from the south corridor's west end, (−4, −3) about the centre."""
    bx, by = LOOP_BLOCK
    r = LOOP_RADIUS
    # straight pieces: (start point, direction, length); each followed by a quarter arc round a block corner
    pieces = [((-bx, -by - r), (1.0, 0.0), 2 * bx, (bx, -by), -np.pi / 2),
              ((bx + r, -by), (0.0, 1.0), 2 * by, (bx, by), 0.0),
              ((bx, by + r), (-1.0, 0.0), 2 * bx, (-bx, by), np.pi / 2),
              ((-bx - r, by), (0.0, -1.0), 2 * by, (-bx, -by), np.pi)]
    s = np.mod(np.asarray(s, dtype=np.float64), LOOP_LENGTH)
    points = np.zeros((len(s), 2))
    tangents = np.zeros((len(s), 2))
    start = 0.0
    arc = r * np.pi / 2
    for p0, d, length, corner, a0 in pieces:
        on = (s >= start) & (s < start + length)
        points[on] = np.asarray(p0) + np.outer(s[on] - start, d)
        tangents[on] = d
        start += length
        on = (s >= start) & (s < start + arc)
        a = a0 + (s[on] - start) / r
        points[on] = np.asarray(corner) + r * np.stack([np.cos(a), np.sin(a)], 1)
        tangents[on] = np.stack([-np.sin(a), np.cos(a)], 1)
        start += arc
    return points + LOOP_CENTER, tangents


def loop_path(times: np.ndarray) -> np.ndarray:
    """A walk round the loop's corridors: ≈ 0.65 m/s along the centre line (speed varying by ±10%), up
    to 0.2 m to either side, eye height with a walking bob, the gaze swinging between the walls about the
    way ahead (±30°) and up and down, a few degrees of roll.

    Where the walker is and where it looks depend on how far round it is (whole cycles per lap), so the
    second time past a place (after the 30.3 m lap) it stands and looks as the first time, within the bob
    and roll (which follow the clock): the end of the default path re-observes the first views. The cycles
    per lap are even, so half a lap on it stands and looks as before turned half a turn about the centre:
    in ``twins`` the pass through the north section sees what the pass through the south one saw.
    """
    t = np.asarray(times, dtype=np.float64)
    s = LOOP_SPEED * t + 0.15 * np.sin(0.4 * t)
    phase = 2 * np.pi * s / LOOP_LENGTH  # one turn per lap
    p, tangent = loop_centre_line(s)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], 1)  # towards the block
    lateral = 0.18 * np.sin(4 * phase + 0.5) + 0.01 * np.sin(2 * np.pi * 0.9 * t)
    xy = p + lateral[:, None] * left
    z = 1.45 + 0.06 * np.sin(2 * phase + 0.3) + 0.01 * np.sin(2 * np.pi * 1.8 * t)
    ahead, ahead_tangent = loop_centre_line(s + 2.0)
    ahead_left = np.stack([-ahead_tangent[:, 1], ahead_tangent[:, 0]], 1)
    swing = 1.1 * np.sin(8 * phase + 0.2) + 0.2 * np.sin(18 * phase)
    target_xy = ahead + swing[:, None] * ahead_left
    target_z = 1.15 + 0.35 * np.sin(10 * phase + 1.0)
    roll = np.radians(3.0 * np.sin(6 * phase + 0.4) + 1.5 * np.sin(1.9 * t))
    return np.array([look_at(np.array([xy[i, 0], xy[i, 1], z[i]]),
                             np.array([target_xy[i, 0], target_xy[i, 1], target_z[i]]), roll[i])
                     for i in range(len(t))])


# -- the wall ------------------------------------------------------------------------------------------
WALL_Y = 1.7  # the wall: the plane y = 1.7 facing −y; the floor z = 0


def wall_scene() -> Scene:
    return Scene([
        Plane((0, 0, 0), (0, 0, 1), M("tiles", 0.25, (0.40, 0.36, 0.30), (0.82, 0.78, 0.70), detail=0.35)),
        Plane((0, WALL_Y, 0), (0, -1, 0), M("blobs", 0.18, (0.25, 0.30, 0.45), (0.92, 0.86, 0.72), detail=0.45)),
    ])


def wall_path(times: np.ndarray) -> np.ndarray:
    """Along the wall and back (x ±2.5 m, ≤ 0.6 m/s), 1.1–1.6 m from it, up and down, looking at the wall
    low enough that the floor fills the lower part of the view."""
    t = np.asarray(times, dtype=np.float64)
    x = 2.5 * np.sin(0.24 * t) + 0.005 * np.sin(2 * np.pi * 1.1 * t)
    y = WALL_Y - 1.35 + 0.25 * np.sin(0.31 * t + 1.0) + 0.005 * np.sin(2 * np.pi * 0.9 * t + 1.0)
    z = 1.35 + 0.25 * np.sin(0.4 * t) + 0.005 * np.sin(2 * np.pi * 1.3 * t + 2.0)
    target = np.stack([x + 0.7 * np.sin(0.37 * t + 0.3), np.full_like(t, WALL_Y), 0.3 + 0.25 * np.sin(0.5 * t + 1.2)], 1)
    roll = np.radians(5.0 * np.sin(0.8 * t + 0.4) + 2.0 * np.sin(1.9 * t))
    return np.array([look_at(np.array([x[i], y[i], z[i]]), target[i], roll[i]) for i in range(len(t))])


# -- the corridor --------------------------------------------------------------------------------------
CORRIDOR_Y = (-1.3, 0.7)   # the side walls (2 m apart, the light above the middle)
CORRIDOR_HEIGHT = 2.6
CORRIDOR_SPEED = 0.6       # m/s, mean: stop and go, 0.12 to 1.08 m/s every 6 s (looking at posters)
CORRIDOR_PACE = 6.0        # seconds
POSTER_HALF = 0.0005       # metres: posters 1 mm thick, far below the depth noise
CORRIDOR_START = -6.0      # x of the first frame; the walk goes towards +x


def corridor_scene() -> Scene:
    y0, y1 = CORRIDOR_Y
    plain = (lambda c: M("checker", 1.0, c, c, detail=0.0))
    prims: list[Primitive] = [
        Plane((0, 0, 0), (0, 0, 1), plain((0.55, 0.55, 0.52))),
        Plane((0, 0, CORRIDOR_HEIGHT), (0, 0, -1), plain((0.92, 0.92, 0.90))),
        Plane((0, y0, 0), (0, 1, 0), plain((0.85, 0.82, 0.74))),
        Plane((0, y1, 0), (0, -1, 0), plain((0.80, 0.84, 0.86))),
    ]
    posters = [M("blobs", 0.08, (0.20, 0.25, 0.50), (0.95, 0.85, 0.55), detail=0.4),
               M("checker", 0.07, (0.60, 0.15, 0.12), (0.95, 0.92, 0.80)),
               M("plaid", 0.06, (0.15, 0.40, 0.25), (0.95, 0.90, 0.70)),
               M("tiles", 0.06, (0.10, 0.15, 0.30), (0.95, 0.75, 0.35)),
               M("bricks", 0.1, (0.45, 0.20, 0.30), (0.90, 0.80, 0.85), aspect=0.4)]
    for k, x in enumerate(np.arange(-9.0, 12.01, 0.6)):  # each wall: a poster 0.8 m wide every 1.2 m
        y = y0 + POSTER_HALF if k % 2 == 0 else y1 - POSTER_HALF
        z = 1.4 + 0.12 * ((k * 7) % 3 - 1)
        prims.append(Box((float(x), y, z), (0.4, POSTER_HALF, 0.5), posters[(k * 3) % len(posters)]))
    return Scene(prims)


def corridor_path(times: np.ndarray) -> np.ndarray:
    """Down the corridor from x = −6, slowing down and speeding up (0.12–1.08 m/s, 0.6 m/s on average, every
    6 s: a constant-velocity motion model mispredicts it), within 0.2 m of the middle, the gaze swinging
    ±35° between the walls' posters and the way ahead."""
    t = np.asarray(times, dtype=np.float64)
    mid = 0.5 * (CORRIDOR_Y[0] + CORRIDOR_Y[1])
    w = 2 * np.pi / CORRIDOR_PACE
    x = CORRIDOR_START + CORRIDOR_SPEED * (t - 0.8 / w * np.sin(w * t))
    y = mid + 0.2 * np.sin(0.27 * t + 0.4) + 0.005 * np.sin(2 * np.pi * 0.9 * t)
    z = 1.5 + 0.06 * np.sin(0.5 * t) + 0.01 * np.sin(2 * np.pi * 1.8 * t)
    target = np.stack([x + 2.0, mid + 1.4 * np.sin(0.4 * t + 0.3), 1.3 + 0.3 * np.sin(0.45 * t + 1.0)], 1)
    roll = np.radians(4.0 * np.sin(0.7 * t + 0.4) + 1.5 * np.sin(1.9 * t))
    return np.array([look_at(np.array([x[i], y[i], z[i]]), target[i], roll[i]) for i in range(len(t))])


# -- irregular large steps -----------------------------------------------------------------------------
JERKY_GAPS = (3, 21)   # frames of the 30 Hz path between two frames, drawn uniformly: 0.1–0.7 s
JERKY_SEED = 31        # the gaps are part of the scene (synth.seed varies only the noise)


def jerky_times(frames: int) -> np.ndarray:
    """Seconds from the first frame: random whole gaps of 3–21 frames of the 30 Hz path (0.1–0.7 s)."""
    rng = np.random.default_rng(JERKY_SEED)
    gaps = rng.integers(JERKY_GAPS[0], JERKY_GAPS[1] + 1, size=max(frames - 1, 0))
    return np.concatenate([[0], np.cumsum(gaps)])[:frames] / FPS


def jerky_path(times: np.ndarray) -> np.ndarray:
    """A fast hand-held walk round the room's table (≈ 0.35 m/s, one lap in 21 s), the gaze swinging
    quickly over the table and the furniture (up to ~25°/s with the walk's own turn), a few degrees of
    roll: sampled 0.1–0.7 s apart, steps of up to ~17° and ~30 cm."""
    t = np.asarray(times, dtype=np.float64)
    angle = -0.6 + 0.22 * t
    x = 0.15 + 1.35 * np.cos(angle) + 0.006 * np.sin(2 * np.pi * 1.1 * t)
    y = 0.05 + 1.05 * np.sin(angle) + 0.006 * np.sin(2 * np.pi * 0.9 * t + 1.0)
    z = 1.40 + 0.15 * np.sin(0.7 * t + 0.3) + 0.005 * np.sin(2 * np.pi * 1.3 * t + 2.0)
    target = np.stack([0.2 + 0.3 * np.sin(0.8 * t + 0.5), 0.1 + 0.3 * np.sin(0.95 * t + 1.3),
                       0.85 + 0.2 * np.sin(0.7 * t + 2.0)], 1)
    roll = np.radians(6.0 * np.sin(0.9 * t + 0.4) + 2.0 * np.sin(1.9 * t))
    return np.array([look_at(np.array([x[i], y[i], z[i]]), target[i], roll[i]) for i in range(len(t))])


# -- a low-texture object circled ----------------------------------------------------------------------
CABINET_CENTER = (0.4, -0.3)   # under kernels.scene_render.LIGHT
CABINET_HALF = (0.45, 0.3, 0.5)  # metres: a waist-high cabinet
CABINET_STRIDE = 20            # one frame every 20th of the 30 Hz path (0.67 s apart)
CABINET_RADIUS = 1.55          # metres: the camera's mean distance from the cabinet's axis
CABINET_LAP_S = 45.0           # seconds per lap (the default 58 frames go about 0.85 of a lap)


def cabinet_scene() -> Scene:
    """A room 6 m × 5 m × 2.7 m with plain walls, floor and ceiling and a plain box: mild colour gradients
    only (blobs metres across, between two close shades), the shading of the light above the box."""
    cx, cy = CABINET_CENTER

    def mild(scale, a, b):
        return M("blobs", scale, a, b, detail=0.0)

    return Scene([
        Plane((0, 0, 0), (0, 0, 1), mild(1.5, (0.55, 0.53, 0.50), (0.62, 0.60, 0.56))),
        Plane((0, 0, 2.7), (0, 0, -1), mild(2.0, (0.90, 0.90, 0.88), (0.94, 0.94, 0.92))),
        Plane((cx - 3.0, 0, 0), (1, 0, 0), mild(1.8, (0.80, 0.78, 0.72), (0.86, 0.84, 0.78))),
        Plane((cx + 3.0, 0, 0), (-1, 0, 0), mild(1.8, (0.76, 0.80, 0.84), (0.82, 0.85, 0.88))),
        Plane((0, cy - 2.5, 0), (0, 1, 0), mild(1.8, (0.84, 0.80, 0.74), (0.88, 0.85, 0.80))),
        Plane((0, cy + 2.5, 0), (0, -1, 0), mild(1.8, (0.78, 0.80, 0.76), (0.84, 0.86, 0.82))),
        Box((cx, cy, CABINET_HALF[2]), CABINET_HALF, mild(0.8, (0.62, 0.50, 0.38), (0.68, 0.56, 0.44)), yaw=0.35),
    ])


def cabinet_times(frames: int) -> np.ndarray:
    """Seconds from the first frame: every 20th frame of the 30 Hz path."""
    return np.arange(frames) * CABINET_STRIDE / FPS


def cabinet_path(times: np.ndarray) -> np.ndarray:
    """Once round the cabinet (a lap in 45 s, ≈ 0.22 m/s on average), slowing down and speeding up
    (0.2–1.8 × the mean every 2.5 s), 1.35–1.75 m from its axis, at 1.1–1.5 m height, looking at the
    cabinet with the gaze wandering ±0.35 m over it: every view holds the box, the floor and a wall."""
    t = np.asarray(times, dtype=np.float64)
    cx, cy = CABINET_CENTER
    w = 2 * np.pi / 2.5
    angle = -2.2 + 2 * np.pi / CABINET_LAP_S * (t - 0.8 / w * np.sin(w * t))
    r = CABINET_RADIUS + 0.2 * np.sin(0.33 * t + 0.5)
    x = cx + r * np.cos(angle)
    y = cy + r * np.sin(angle)
    z = 1.3 + 0.2 * np.sin(0.27 * t + 1.0) + 0.005 * np.sin(2 * np.pi * 1.3 * t)
    target = np.stack([cx + 0.35 * np.sin(0.41 * t + 0.2), cy + 0.35 * np.sin(0.53 * t + 1.1),
                       0.55 + 0.2 * np.sin(0.37 * t + 2.0)], 1)
    roll = np.radians(4.0 * np.sin(0.6 * t + 0.4) + 1.5 * np.sin(1.9 * t))
    return np.array([look_at(np.array([x[i], y[i], z[i]]), target[i], roll[i]) for i in range(len(t))])


# -- the slats --------------------------------------------------------------------------------------------
SLATS_Y = 0.4                  # the slats' middle plane (world y); the wall behind at SLATS_WALL_Y
SLATS_WALL_Y = 1.0
SLAT_HALF = (0.02, 0.01, 0.3)  # 4 cm wide, 2 cm deep, 60 cm high
SLOT = 0.03                    # metres between two slats
SLATS = 10
SLATS_Z = 0.8                  # the slats' middle height


def slat_xs() -> np.ndarray:
    """The x of each slat's middle (symmetric about x = 0)."""
    pitch = 2 * SLAT_HALF[0] + SLOT
    return (np.arange(SLATS) - (SLATS - 1) / 2) * pitch


def slot_xs() -> np.ndarray:
    """The x of each slot's middle, between neighbouring slats."""
    xs = slat_xs()
    return 0.5 * (xs[1:] + xs[:-1])


def slats_scene() -> Scene:
    wood = M("plaid", 0.05, (0.45, 0.28, 0.15), (0.80, 0.62, 0.40))
    xs = slat_xs()
    width = xs[-1] - xs[0] + 2 * SLAT_HALF[0]
    rail_z = SLAT_HALF[2] + 0.02
    return Scene([
        Plane((0, 0, 0), (0, 0, 1), M("tiles", 0.25, (0.40, 0.36, 0.30), (0.82, 0.78, 0.70), detail=0.35)),
        Plane((0, SLATS_WALL_Y, 0), (0, -1, 0), M("blobs", 0.18, (0.25, 0.30, 0.45), (0.92, 0.86, 0.72), detail=0.45)),
        *[Box((float(x), SLATS_Y, SLATS_Z), SLAT_HALF, wood) for x in xs],
        # top and bottom rails close each slot's ends; two posts carry the frame to the floor
        *[Box((0.0, SLATS_Y, SLATS_Z + sign * rail_z), (width / 2 + 0.03, 0.015, 0.02), wood) for sign in (-1, 1)],
        *[Box((sign * (width / 2 + 0.05), SLATS_Y, (SLATS_Z + rail_z + 0.02) / 2), (0.02, 0.015,
              (SLATS_Z + rail_z + 0.02) / 2), wood) for sign in (-1, 1)],
    ])


def slats_path(times: np.ndarray) -> np.ndarray:
    """An arc 1.2–1.4 m in front of the slats, from 35° one side to 35° the other and back (one sweep in
    about 4 s), at eye height, looking at points that wander over the slats."""
    t = np.asarray(times, dtype=np.float64)
    a = np.radians(35.0) * np.sin(0.8 * t)
    r = 1.3 + 0.1 * np.sin(0.5 * t + 0.7)
    x = r * np.sin(a)
    y = SLATS_Y - r * np.cos(a)
    z = 1.15 + 0.1 * np.sin(0.6 * t + 0.3) + 0.004 * np.sin(2 * np.pi * 1.3 * t)
    target = np.stack([0.15 * np.sin(0.9 * t + 0.5), np.full_like(t, SLATS_Y),
                       SLATS_Z + 0.1 * np.sin(0.7 * t + 1.1)], 1)
    roll = np.radians(3.0 * np.sin(0.8 * t + 0.4))
    return np.array([look_at(np.array([x[i], y[i], z[i]]), target[i], roll[i]) for i in range(len(t))])


# -- the catalogue -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SceneSpec:
    name: str
    build: Callable[[], Scene]
    path: Callable[[np.ndarray], np.ndarray]  # times (s from the first frame) → N×4×4 camera-to-world
    frames: int                               # default length
    about: str
    times: Callable[[int], np.ndarray] = regular_times  # frames → seconds from the first frame (30 Hz)


SCENES: dict[str, SceneSpec] = {
    "room": SceneSpec("room", default_scene, camera_path, 120, "furnished 5 m × 4 m room, circling the table"),
    "loop": SceneSpec("loop", loop_scene, loop_path, LOOP_FRAMES,
                      "corridor loop 12 m × 8 m round a block, once round and 3 m on (loop closure)"),
    "twins": SceneSpec("twins", twins_scene, loop_path, LOOP_FRAMES,
                       "the loop with two identical sections on opposite sides (false loops)"),
    "wall": SceneSpec("wall", wall_scene, wall_path, 600, "textured wall and floor only (photometric tracking)"),
    "corridor": SceneSpec("corridor", corridor_scene, corridor_path, 600,
                          "plain corridor with textured posters (photometric tracking)"),
    "jerky": SceneSpec("jerky", default_scene, jerky_path, 80,
                       "the room at random gaps of 0.1-0.7 s of a fast path (irregular, large steps)",
                       jerky_times),
    "cabinet": SceneSpec("cabinet", cabinet_scene, cabinet_path, 58,
                         "a plain cabinet in a plain room circled at changing speed, a frame every 0.67 s "
                         "(wide baselines, low texture)", cabinet_times),
    "slats": SceneSpec("slats", slats_scene, slats_path, 120,
                       "a chair back of slats with 3 cm slots in front of a wall (openings a mesh keeps open)"),
}


def get_scene(name: str) -> SceneSpec:
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown synthetic scene {name!r}: one of {', '.join(SCENES)}") from None
