import numpy as np
import pytest

from ti_fusion import geometry as g


def random_rotation(rng):
    return g.so3_exp(rng.normal(size=3))


def test_so3_exp_closed_form_about_z():
    a = 0.7
    R = g.so3_exp([0, 0, a])
    expected = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(R, expected, atol=1e-12)


@pytest.mark.parametrize("angle", [1e-9, 1e-4, 0.5, 2.0, np.pi - 1e-6, np.pi])
def test_so3_log_roundtrip(rng, angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    w = axis * angle
    w2 = g.so3_log(g.so3_exp(w))
    np.testing.assert_allclose(g.so3_exp(w2), g.so3_exp(w), atol=1e-9)
    if angle < np.pi - 1e-3:
        np.testing.assert_allclose(w2, w, atol=1e-9)


def test_se3_exp_is_rigid_and_log_inverts(rng):
    for _ in range(20):
        xi = rng.normal(size=6)
        xi[:3] *= min(1.0, 3.0 / np.linalg.norm(xi[:3]))  # |ω| < π: the log's principal branch
        T = g.se3_exp(xi)
        assert g.rigidity_error(T) is None
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(g.se3_log(T), xi, atol=1e-9)


def test_se3_exp_pure_translation():
    T = g.se3_exp([0, 0, 0, 1, 2, 3])
    np.testing.assert_allclose(T, g.make_pose(np.eye(3), [1, 2, 3]), atol=1e-15)


def test_quaternion_roundtrip(rng):
    for _ in range(50):
        R = random_rotation(rng)
        q = g.rot_to_quat(R)
        assert q[3] >= 0
        np.testing.assert_allclose(g.quat_to_rot(q), R, atol=1e-12)
    # 180° about x: w = 0, a branch of Shepperd's method
    np.testing.assert_allclose(np.abs(g.rot_to_quat(np.diag([1.0, -1.0, -1.0]))), [1, 0, 0, 0], atol=1e-12)


def test_invert_and_orthonormalize(rng):
    T = g.se3_exp(rng.normal(size=6))
    np.testing.assert_allclose(g.invert(T) @ T, np.eye(4), atol=1e-12)
    R = random_rotation(rng) + rng.normal(scale=1e-3, size=(3, 3))
    Q = g.orthonormalize(R)
    np.testing.assert_allclose(Q.T @ Q, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)


def test_rigidity_error_messages():
    assert "NaN" in g.rigidity_error(np.full((4, 4), np.nan))
    S = np.eye(4)
    S[0, 0] = 2
    assert "orthonormal" in g.rigidity_error(S)
    F = np.diag([1.0, 1.0, -1.0, 1.0])
    assert "reflection" in g.rigidity_error(F)
    assert "4x4" in g.rigidity_error(np.eye(3))


def test_pose_error():
    A = g.se3_exp([0, 0, np.radians(3), 0.05, 0, 0])
    rot, trans = g.pose_error(A, np.eye(4))
    assert rot == pytest.approx(3.0)
    assert trans == pytest.approx(np.linalg.norm(A[:3, 3]))


def test_fast_paths_give_numpys_bits(rng):
    """orthonormalize, se3_log, the norms and rigidity_error's last-row test call NumPy's gufuncs without the
    wrappers: the same bits as np.linalg.svd / det / solve / norm and np.allclose give."""
    for _ in range(200):
        xi = rng.normal(size=6) * 10.0 ** rng.uniform(-9, 0.4)
        T = g.se3_exp(xi)
        T[:3, :3] += rng.normal(scale=1e-6, size=(3, 3))
        R = T[:3, :3]
        U, _, Vt = np.linalg.svd(R)
        expected = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        assert g.orthonormalize(R).tobytes() == expected.tobytes()
        w = g.so3_log(R)
        assert g.se3_log(T)[3:].tobytes() == np.linalg.solve(g._left_jacobian(w), T[:3, 3]).tobytes()
        assert g._norm(xi) == np.linalg.norm(xi) and g._norm(xi[::2]) == np.linalg.norm(xi[::2])
    for value in (1e-6, 1.0001e-6, -1e-6, 2e-6):
        row = np.array([0.0, value, 0.0, 1.0])
        T = np.eye(4)
        T[3] = row
        assert (g.rigidity_error(T) is None) == np.allclose(row, [0, 0, 0, 1], atol=1e-6)
    for value in (1 + 1.1e-5, 1 + 1.0999e-5, 1 - 1.1e-5, 1 - 1.2e-5):
        T = np.eye(4)
        T[3, 3] = value
        assert (g.rigidity_error(T) is None) == np.allclose(T[3], [0, 0, 0, 1], atol=1e-6)
    with pytest.raises(np.linalg.LinAlgError):  # NumPy's own path and error where the matrix is not finite
        g.orthonormalize(np.full((3, 3), np.nan))
