"""SO(3)/SE(3) in float64 NumPy: exponential and logarithm maps, quaternions, checks.

Conventions used across ti-fusion:
- poses are 4×4 homogeneous camera-to-world matrices T = [R | t];
- a twist is ξ = (ω, v) with the ROTATION FIRST (ω: axis-angle, v: translation part), matching the
  ICP Jacobian [(p × n)ᵀ, nᵀ];
- quaternions are (qx, qy, qz, qw), the TUM order.
"""

from __future__ import annotations

import numpy as np

try:  # the gufuncs behind np.linalg.svd, det and solve: the same LAPACK calls without their wrappers' Python
    from numpy.linalg import _umath_linalg as _lapack

    _svd_f, _det, _solve1 = _lapack.svd_f, _lapack.det, _lapack.solve1
except (ImportError, AttributeError):  # pragma: no cover - another NumPy layout: the public functions
    _svd_f = _det = _solve1 = None

_EPS = 1e-10
_I3 = np.eye(3)
_D_KEEP, _D_FLIP = np.diag([1.0, 1.0, 1.0]), np.diag([1.0, 1.0, -1.0])  # orthonormalize's D for det ±1
_I3.flags.writeable = _D_KEEP.flags.writeable = _D_FLIP.flags.writeable = False
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def hat(w: np.ndarray) -> np.ndarray:
    """The skew-symmetric matrix [w]× with [w]× x = w × x."""
    wx, wy, wz = np.asarray(w, dtype=np.float64).tolist()
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def _norm(w: np.ndarray):
    """np.linalg.norm of a vector, as it computes a float64 one (the square root of the dot product of its
    raveled copy), without the checks of its other cases."""
    if w.ndim != 1 or w.dtype != np.float64:
        return np.linalg.norm(w)
    x = w.ravel(order="K")
    return np.sqrt(x.dot(x))


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the axis-angle vector ``w`` (Rodrigues' formula)."""
    w = np.asarray(w, dtype=np.float64)
    theta = _norm(w)
    W = hat(w)
    if theta < 1e-8:
        return _I3 + W + 0.5 * W @ W
    return _I3 + np.sin(theta) / theta * W + (1.0 - np.cos(theta)) / theta**2 * W @ W


def so3_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (inverse of so3_exp, angle in [0, π])."""
    R = np.asarray(R, dtype=np.float64)
    cos_theta = (R.trace() - 1.0) / 2.0
    if cos_theta < -1.0:  # np.clip's result, NaN kept
        cos_theta = np.float64(-1.0)
    elif cos_theta > 1.0:
        cos_theta = np.float64(1.0)
    theta = np.arccos(cos_theta)
    r = R.tolist()
    vee = np.array([r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]])
    if theta < 1e-6:
        return 0.5 * vee
    if np.pi - theta < 1e-4:
        # Near π the antisymmetric part vanishes: read the axis off the symmetric part instead.
        B = 0.5 * (0.5 * (R + R.T) + np.eye(3))  # = a aᵀ at θ = π
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        k = int(np.argmax(axis))
        axis = B[k] / max(axis[k], _EPS)
        axis /= np.linalg.norm(axis)
        if np.dot(axis, vee) < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * np.sin(theta)) * vee


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = _norm(w)
    W = hat(w)
    if theta < 1e-8:
        return _I3 + 0.5 * W + W @ W / 6.0
    return (
        _I3
        + (1.0 - np.cos(theta)) / theta**2 * W
        + (theta - np.sin(theta)) / theta**3 * W @ W
    )


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4×4 rigid transform of the twist ξ = (ω, v), rotation first. Exact, always rigid."""
    xi = np.asarray(xi, dtype=np.float64)
    w = xi[:3]
    theta, W = _norm(w), hat(w)  # so3_exp's and _left_jacobian's, computed once
    T = np.eye(4)
    if theta < 1e-8:
        T[:3, :3] = _I3 + W + 0.5 * W @ W
        T[:3, 3] = (_I3 + 0.5 * W + W @ W / 6.0) @ xi[3:]
        return T
    sin, cos = np.sin(theta), np.cos(theta)
    T[:3, :3] = _I3 + sin / theta * W + (1.0 - cos) / theta**2 * W @ W
    T[:3, 3] = (_I3 + (1.0 - cos) / theta**2 * W + (theta - sin) / theta**3 * W @ W) @ xi[3:]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ξ = (ω, v) of a rigid transform (inverse of se3_exp)."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[:3, :3])
    J = _left_jacobian(w)
    # np.linalg.solve's gufunc where J is finite (then regular: |ω| ≤ π); the wrapper's errors for the others
    v = _solve1(J, T[:3, 3], signature="dd->d") if _solve1 is not None and np.isfinite(J).all() else \
        np.linalg.solve(J, T[:3, 3])
    return np.concatenate([w, v])


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def flatten_pose(T: np.ndarray) -> np.ndarray:
    """The 12 numbers the kernels take a pose as (float64): R row-major, then t."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[:3, :3].ravel(), T[:3, 3]])


def unflatten_pose(p12: np.ndarray) -> np.ndarray:
    """4×4 float64 pose of the 12 numbers of ``flatten_pose``."""
    p12 = np.asarray(p12, dtype=np.float64)
    return make_pose(p12[:9].reshape(3, 3), p12[9:12])


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, using Rᵀ rather than a general inverse."""
    Rt = T[:3, :3].T
    out = np.empty((4, 4))
    out[:3, :3] = Rt
    out[:3, 3] = -Rt @ T[:3, 3]
    out[3] = _LAST_ROW
    return out


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD projection onto SO(3))."""
    R = np.asarray(R, dtype=np.float64)
    # np.linalg.svd's and det's own gufuncs where the matrix is finite (the wrappers' error handling is for
    # the others, which take them): they were much of a pose update's host time
    if _svd_f is not None and R.shape == (3, 3) and np.isfinite(R).all():
        U, _, Vt = _svd_f(R, signature="d->ddd")
        sign = np.sign(_det(U @ Vt, signature="d->d"))
    else:
        U, _, Vt = np.linalg.svd(R)
        sign = np.sign(np.linalg.det(U @ Vt))
    D = _D_KEEP if sign == 1.0 else _D_FLIP if sign == -1.0 else np.diag([1.0, 1.0, sign])
    return U @ D @ Vt


def renormalize(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected back onto SO(3).

    Chains of compositions and transpose-inverses let round-off grow geometrically (an inverse by
    transposition of a slightly non-orthonormal R doubles its error); poses kept across frames are
    renormalised after every composition.
    """
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = orthonormalize(out[:3, :3])
    return out


def rigidity_error(T: np.ndarray) -> str | None:
    """Why ``T`` is not a rigid 4×4 transform (None when it is, to a tolerance that accepts real data)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.isfinite(T).all():
        return "contains NaN or infinite values"
    a, b, c, d = T[3].tolist()  # np.allclose(T[3], [0, 0, 0, 1], atol=1e-6), its default rtol 1e-5, finite values
    if not (abs(a) <= 1e-6 and abs(b) <= 1e-6 and abs(c) <= 1e-6 and abs(d - 1.0) <= 1e-6 + 1e-5):
        return f"last row is {T[3].tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    ortho = np.abs(R.T @ R - _I3).max()
    if ortho > 1e-2:
        return f"rotation block is not orthonormal (|RᵀR - I| = {ortho:.3g})"
    det = _det(R, signature="d->d") if _det is not None else np.linalg.det(R)
    if det < 0:
        return f"rotation block is a reflection (det = {det:.3g})"
    return None


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (qx, qy, qz, qw); normalises it first."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (qx, qy, qz, qw) with qw ≥ 0 of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return float(np.degrees(_norm(so3_log(R))))


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) of T_est against T_ref."""
    E = invert(T_ref) @ T_est
    return rotation_angle_deg(E[:3, :3]), float(_norm(T_est[:3, 3] - T_ref[:3, 3]))
