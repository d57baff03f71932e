"""The colour camera's extrinsics, T_color_depth (p_color = T p_depth, metres): from a file or a bag's
transform message (``dataset.color_extrinsics``, ``--color-extrinsics``).

A file holds a 4×4 or 3×4 matrix row by row, or seven numbers ``tx ty tz qx qy qz qw`` (TUM's order,
the quaternion of R); ``#`` starts a comment. A bag topic holds a ``geometry_msgs/Transform`` (taken as
T_color_depth), or a ``TransformStamped`` / ``tf2_msgs/TFMessage`` (``/tf_static``), whose transform between
the colour image's and the depth image's ``frame_id`` is taken in the direction it states (tf's parent ←
child: a transform from the colour frame to the depth frame is inverted).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, quat_to_rot

TRANSFORM = "geometry_msgs/msg/Transform"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def check_rigid(T: np.ndarray, where) -> np.ndarray:
    """``T`` when it is a rigid transform (rotation orthonormal with determinant 1, last row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(where, "colour extrinsics must be a finite 4x4 transform")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3 or \
            not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(where, "colour extrinsics are not a rotation and a translation (R^T R != I, det R != 1, "
                                "or last row not 0 0 0 1)")
    if np.linalg.norm(T[:3, 3]) > 1.0:
        raise InputError(where, f"colour extrinsics put the colour camera {np.linalg.norm(T[:3, 3]):.2f} m from the "
                                "depth camera: metres are expected (a baseline is a few centimetres)")
    return T


def read_extrinsics_file(path: str | Path) -> np.ndarray:
    """T_color_depth from a file (see the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the colour extrinsics: {exc}") from None
    numbers = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].replace(",", " ").strip()
        try:
            numbers += [float(x) for x in line.split()]
        except ValueError:
            raise InputError(path, f"colour extrinsics: {line!r} is not a line of numbers") from None
    values = np.array(numbers)
    if values.size == 7:
        t, q = values[:3], values[3:]
        if abs(np.linalg.norm(q) - 1) > 1e-3:
            raise InputError(path, f"colour extrinsics: the quaternion (qx qy qz qw) has norm {np.linalg.norm(q):.4f}")
        return check_rigid(make_pose(quat_to_rot(q / np.linalg.norm(q)), t), path)
    if values.size in (12, 16):
        T = np.eye(4)
        T[: values.size // 4] = values.reshape(-1, 4)
        return check_rigid(T, path)
    raise InputError(path, f"colour extrinsics: {values.size} numbers; expected a 4x4 or 3x4 matrix (16 or 12) or "
                           "tx ty tz qx qy qz qw (7)")


def transform_matrix(msg) -> np.ndarray:
    """4×4 of a ``geometry_msgs/Transform`` (p_parent = R p_child + t)."""
    q, t = msg.rotation, msg.translation
    return make_pose(quat_to_rot(np.array([q.x, q.y, q.z, q.w], dtype=np.float64)),
                     np.array([t.x, t.y, t.z], dtype=np.float64))


def extrinsics_from_message(msg, msgtype: str, depth_frame: str, color_frame: str, where: str) -> np.ndarray:
    """T_color_depth from a Transform, TransformStamped or TFMessage (see the module docstring)."""
    if msgtype == TRANSFORM:
        return check_rigid(transform_matrix(msg), where)
    stamped = [msg] if msgtype == TRANSFORM_STAMPED else list(msg.transforms)
    for s in stamped:
        parent, child = s.header.frame_id.lstrip("/"), s.child_frame_id.lstrip("/")
        if (parent, child) == (color_frame.lstrip("/"), depth_frame.lstrip("/")):
            return check_rigid(transform_matrix(s.transform), where)
        if (parent, child) == (depth_frame.lstrip("/"), color_frame.lstrip("/")):
            return check_rigid(np.linalg.inv(transform_matrix(s.transform)), where)
    found = ", ".join(f"{s.header.frame_id} <- {s.child_frame_id}" for s in stamped) or "none"
    raise InputError(None, f"{where}: no transform between the colour frame {color_frame!r} and the depth frame "
                           f"{depth_frame!r} (transforms: {found})")
