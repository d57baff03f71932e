"""Trajectories in the TUM RGB-D format, and timestamp association.

A TUM trajectory file has one pose per line, ``timestamp tx ty tz qx qy qz qw``: the camera-to-world
translation in metres and rotation as a unit quaternion; blank lines and lines starting with ``#``
are ignored. evo, Open3D and the TUM benchmark tools read what ``write_tum`` writes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, orthonormalize, quat_to_rot, rigidity_error, rot_to_quat
from ti_fusion.io.outputs import atomic_write
from ti_fusion.io.tables import parse_floats, read_table

_QUAT_NORM_TOL = 1e-2  # files with 4-6 printed decimals have norms within ~1e-4 of 1


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), camera-to-world poses (N, 4, 4)) from a TUM trajectory file, in file order."""
    path = Path(path)
    stamps, poses = [], []
    for lineno, fields in read_table(path, "trajectory file"):
        if len(fields) != 8:
            raise InputError(path, f"line {lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', found {len(fields)}")
        values = parse_floats(fields, path, lineno)
        q = values[4:]
        norm = np.linalg.norm(q)
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise InputError(path, f"line {lineno}: quaternion has norm {norm:.6g}, not a rotation (expected 1)")
        stamps.append(values[0])
        poses.append(make_pose(quat_to_rot(q), values[1:4]))
    if not poses:
        raise InputError(path, "trajectory file has no poses")
    return np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64)


def write_tum(path: str | Path, timestamps, poses) -> Path:
    """Write camera-to-world ``poses`` (N×4×4) with their ``timestamps`` as a TUM trajectory file.

    Each rotation is projected onto SO(3) before conversion, so slightly non-orthonormal input (e.g.
    accumulated float error) writes a clean unit quaternion; a pose that is not rigid at all is refused.
    The file appears whole or not at all; a failed write raises ``OutputError``.
    """
    path = Path(path)
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(path, f"poses must be N×4×4, got shape {poses.shape}")
    if len(stamps) != len(poses):
        raise InputError(path, f"{len(stamps)} timestamps for {len(poses)} poses")
    if not np.all(np.isfinite(stamps)):
        raise InputError(path, "timestamps contain NaN or infinite values")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for i, (t, T) in enumerate(zip(stamps, poses)):
        problem = rigidity_error(T)
        if problem:
            raise InputError(path, f"pose {i} (line {i + 2}, timestamp {t:.6f}) is not rigid: {problem}")
        q = rot_to_quat(orthonormalize(T[:3, :3]))
        tx, ty, tz = T[:3, 3]
        lines.append(f"{t:.6f} {tx:.9f} {ty:.9f} {tz:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def associate(stamps_a, stamps_b, max_difference: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) matching ``stamps_a`` to ``stamps_b`` one-to-one, as TUM's associate.py does.

    Every candidate pair with |a − b| < max_difference is considered; pairs are taken greedily by
    smallest difference (ties: earlier a, then earlier b), each stamp used at most once. The result
    is sorted by ``ia``.
    """
    a = np.asarray(stamps_a, dtype=np.float64).reshape(-1)
    b = np.asarray(stamps_b, dtype=np.float64).reshape(-1)
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    # Candidate pairs: for each a, the b's inside the tolerance window (few at camera rates).
    lo = np.searchsorted(b_sorted, a - max_difference, side="left")
    hi = np.searchsorted(b_sorted, a + max_difference, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(len(a)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ib = order_b[np.repeat(lo, counts) + offsets]
    diff = np.abs(a[ia] - b[ib])
    keep = diff < max_difference  # strict, as in associate.py
    ia, ib, diff = ia[keep], ib[keep], diff[keep]
    # Same order as associate.py's sort of (diff, a, b) tuples.
    order = np.lexsort((b[ib], a[ia], diff))
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    pairs = []
    for k in order:
        i, j = ia[k], ib[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((i, j))
    pairs.sort()
    if not pairs:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    out = np.asarray(pairs, dtype=int)
    return out[:, 0], out[:, 1]
