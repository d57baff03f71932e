"""What a Kinect v1 does at depth edges, applied to a rendered depth image (NumPy, float64 inside).

The structured-light sensor sees the projector's pattern from ``baseline`` metres beside it: background just
beside a nearer edge lies in the projector's shadow and has no depth, and the correlation window that spans
an edge gives no depth, or a depth between the two sides (flying pixels). These remove or corrupt exactly the
points that hold ICP along the directions that large planes leave weak (docs/TRACKING.md, real cameras).
"""

from __future__ import annotations

import numpy as np

EDGE_JUMP = 0.04  # a depth edge: neighbours differ by more than this × the nearer depth


def projector_shadow(depth: np.ndarray, fx_baseline: float, step: int = 1) -> np.ndarray:
    """H×W bool: pixels the projector cannot light. ``fx_baseline`` is fx · baseline of the full-resolution
    image (pixel·metres); ``depth`` may be every ``step``-th pixel of it. The projector sits to the camera's
    left, so a pixel is lit where its column in the projector's image lies right of every nearer pixel's to
    its left in the row (the pattern reaches it)."""
    z = np.asarray(depth, dtype=np.float64)
    cols = np.arange(z.shape[1], dtype=np.float64) * step
    with np.errstate(divide="ignore"):
        proj = np.where(z > 0, cols[None, :] + fx_baseline / np.where(z > 0, z, 1.0), -np.inf)
    before = np.maximum.accumulate(proj, axis=1)
    before = np.concatenate([np.full((z.shape[0], 1), -np.inf), before[:, :-1]], axis=1)
    # a margin of a tenth of a pixel keeps a plane's own rounding from shadowing it
    return (z > 0) & (before > proj + 0.1)


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """H×W bool: valid pixels with a 4-neighbour that is invalid or farther/nearer by more than EDGE_JUMP × z."""
    z = np.asarray(depth, dtype=np.float64)
    valid = z > 0
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = np.take(z, np.arange(z.shape[axis] - 1), axis=axis)
        b = np.take(z, np.arange(1, z.shape[axis]), axis=axis)
        jump = (np.abs(a - b) > EDGE_JUMP * np.minimum(np.where(a > 0, a, np.inf), np.where(b > 0, b, np.inf))) | \
            (a <= 0) | (b <= 0)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        edge[tuple(lo)] |= jump
        edge[tuple(hi)] |= jump
    return edge & valid


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` grown by ``radius`` pixels (a square)."""
    out = mask.copy()
    H, W = mask.shape
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            src = mask[max(0, -dy):H - max(0, dy), max(0, -dx):W - max(0, dx)]
            out[max(0, dy):H - max(0, -dy), max(0, dx):W - max(0, -dx)] |= src
    return out


def kinect_edges(depth: np.ndarray, fx_baseline: float, step: int, shadow: bool, holes: float,
                 flying: float, seed: int) -> np.ndarray:
    """``depth`` (float32, 0 = invalid) with the projector's shadow dropped (``shadow``), depth dropped within
    ``holes`` full-resolution pixels of a depth edge, and of those dropped edge pixels a share ``flying``
    where their 3×3 neighbourhood spans an edge given a depth drawn uniformly between its nearest and farthest
    valid depth instead. ``seed`` fixes the draw."""
    z = np.asarray(depth, dtype=np.float64).copy()
    if shadow:
        z[projector_shadow(z, fx_baseline, step)] = 0.0
    if holes > 0:
        radius = int(round(holes / step))
        band = dilate(depth_edges(z), radius) & (z > 0) if radius > 0 else np.zeros(z.shape, bool)
        if flying > 0 and band.any():
            rng = np.random.default_rng(seed)
            pad = np.pad(z, 1)
            stack = np.stack([pad[1 + dy:1 + dy + z.shape[0], 1 + dx:1 + dx + z.shape[1]]
                              for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
            near = np.where(stack > 0, stack, np.inf).min(0)
            far = stack.max(0)
            with np.errstate(invalid="ignore"):
                fly = band & (rng.random(z.shape) < flying) & (far - near > EDGE_JUMP * near)
            mix = rng.random(z.shape)
            with np.errstate(invalid="ignore"):  # near is infinite where no neighbour is valid
                z_fly = near + mix * (far - near)
            z[band] = 0.0
            z[fly] = z_fly[fly]
        else:
            z[band] = 0.0
    return z.astype(np.float32)
