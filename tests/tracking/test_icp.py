"""Point-to-plane ICP: the association / reduction kernels against the NumPy float64 reference on every
backend, the solvers, and the coarse-to-fine loop on synthetic and real pairs.

Tolerances. cpu (float64 arithmetic): the 30 sums agree with NumPy to 1e-5 relative (in practice 1e-11).
vulkan (float32 arithmetic and per-chunk float32 partials, Kahan-summed): each AᵀA entry within 1e-4 of
√(AᵀA_ii AᵀA_jj), each Aᵀb entry within 1e-4 of √(AᵀA_ii Σr²), Σr² within 1e-4 relative, counts exact;
the scale is the Cauchy–Schwarz bound of the entry, because entries that are sums of signed terms (Aᵀb near
convergence) may be close to zero while their rounding is not.
"""

import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from ti_fusion.reference import icp as icp_numpy
from ti_fusion.backend import current_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig, ICPConfig, PyramidConfig, SynthConfig
from ti_fusion.geometry import flatten_pose, invert, make_pose, pose_error, se3_exp, so3_exp
from ti_fusion.tracking.icp import ICP, ICPResult, IterationRecord
from ti_fusion.kernels import icp as kicp
from ti_fusion.kernels.pyramid import FramePyramid
from ti_fusion.synthetic.scene import SyntheticSequence
from ti_fusion.tracking.terms.point_to_plane import point_to_plane
from ti_fusion.tracking.solve import check_system, condition_number, condition_numbers, solve_normal_equations

ROOT = Path(__file__).resolve().parents[2]
THR = 0.1
THETA = 30.0


# -- helpers -------------------------------------------------------------------------------------------
def vec_field(a: np.ndarray):
    f = ti.Vector.field(3, ti.f32, shape=a.shape[:2])
    f.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return f


def pass_for(n_pixels: int, n_chunks: int | None = None) -> kicp.PointToPlane:
    b = current_backend()
    return kicp.PointToPlane(n_pixels, b.has_f64, n_chunks, min_chunk_pixels=1 if n_chunks else None)


def rays(K: Intrinsics, u, v):
    return np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, dtype=np.float64)], axis=-1)


def random_unit_near(rng, axis, max_deg, size):
    """Unit vectors at angles uniform in [0, max_deg] from ``axis`` (an array of unit vectors)."""
    a = rng.normal(size=(size, 3))
    a -= np.einsum("ij,ij->i", a, axis)[:, None] * axis
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    ang = np.radians(rng.uniform(0, max_deg, size))
    return np.cos(ang)[:, None] * axis + np.sin(ang)[:, None] * a


def random_pose(rng, scale):
    """A random pose whose target camera sits 0.5 m in front of the source camera, so that some source
    points (z > 0) are behind the target camera."""
    T = se3_exp(rng.normal(scale=scale, size=6))
    T[2, 3] -= 0.5
    return T


def random_pass_inputs(rng, T, K_t: Intrinsics, src_shape=(48, 64)):
    """Source and target vertex/normal maps whose association hits every status code, with no pixel
    within rounding distance of a decision boundary (so float32 and float64 must agree exactly)."""
    Ht, Wt = K_t.height, K_t.width
    v, u = np.mgrid[0:Ht, 0:Wt]
    zt = rng.uniform(0.8, 3.0, (Ht, Wt))
    Vt = rays(K_t, u, v) * zt[..., None]
    Nt = random_unit_near(rng, np.broadcast_to([0.0, 0.0, -1.0], (Ht * Wt, 3)), 60, Ht * Wt).reshape(Ht, Wt, 3)
    Vt[rng.random((Ht, Wt)) < 0.08] = 0.0
    Nt[rng.random((Ht, Wt)) < 0.05] = 0.0

    n = src_shape[0] * src_shape[1]
    uc = rng.uniform(-3.0, Wt + 3.0, n)  # projected position, some outside the image
    vc = rng.uniform(-3.0, Ht + 3.0, n)
    ui = np.clip(np.floor(uc + 0.5), 0, Wt - 1).astype(int)
    vi = np.clip(np.floor(vc + 0.5), 0, Ht - 1).astype(int)
    zq = np.where(Vt[vi, ui, 2] > 0, Vt[vi, ui, 2], rng.uniform(0.8, 3.0, n))
    z = zq + rng.uniform(-2 * THR, 2 * THR, n)
    behind = rng.random(n) < 0.05
    z[behind] = -rng.uniform(0.0, 0.4, behind.sum())  # behind the target camera, in front of the source
    p_t = rays(K_t, uc, vc) * z[:, None]
    nq = Nt[vi, ui]
    base = np.where(np.any(nq != 0, axis=1)[:, None], nq, [0.0, 0.0, -1.0])
    n_t = random_unit_near(rng, base, 2 * THETA, n)
    R, t = T[:3, :3], T[:3, 3]
    P = (p_t - t) @ R  # source points: p = Rᵀ (p′ − t)
    N = n_t @ R
    P[rng.random(n) < 0.06] = 0.0
    N[rng.random(n) < 0.04] = 0.0

    # Keep only pixels clear of every boundary (else mark them source-invalid).
    frac_u = np.abs((uc + 0.5) - np.round(uc + 0.5))
    frac_v = np.abs((vc + 0.5) - np.round(vc + 0.5))
    d = np.linalg.norm(p_t - Vt[vi, ui], axis=1)
    cosang = np.einsum("ij,ij->i", n_t, nq)
    ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    clear = (frac_u > 0.02) & (frac_v > 0.02) & (np.abs(d - THR) > 0.01 * THR) & (np.abs(ang - THETA) > 0.3) \
        & (np.abs(z) > 0.01)
    P[~clear] = 0.0
    shape = src_shape + (3,)  # float32, as the fields hold them: the references see the same numbers
    return (P.reshape(shape).astype(np.float32), N.reshape(shape).astype(np.float32), Vt.astype(np.float32),
            Nt.astype(np.float32))


def cs_scale(sums: np.ndarray) -> np.ndarray:
    """Cauchy–Schwarz bound of every sum's magnitude (see the module docstring)."""
    s = kicp.unpack_sums(sums)
    diag = np.diag(s["AtA"])
    scale = np.ones(kicp.N_SUMS)
    scale[:21] = [math.sqrt(diag[i] * diag[j]) for i, j in kicp.UPPER]
    scale[kicp.SUM_ATB:kicp.SUM_ATB + 6] = np.sqrt(diag * s["r2"])
    scale[kicp.SUM_R2] = s["r2"]
    return scale


def assert_sums_close(got, ref):
    np.testing.assert_array_equal(got[kicp.SUM_INLIERS:], ref[kicp.SUM_INLIERS:])
    if current_backend().has_f64:
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=0)
    else:
        err = np.abs(got - ref) / cs_scale(ref)
        assert err.max() < 1e-4, f"float32 sums off by {err.max():.2e} of their scale"


# -- association ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("robust", ["none", "huber", "tukey", "none+depth", "huber+depth"])
@pytest.mark.parametrize("chunks", ["parallel", pytest.param("serial", marks=pytest.mark.slow), "default"])
def test_status_and_sums_match_reference(arch, rng, robust, chunks):
    """Chunks: "parallel", 1100 chunks that do not divide the image (more than 2 × 512, so that Taichi's CPU
    backend splits them between threads); "serial", 97 such chunks on the calling thread; "default", the
    pass's own choice for a source this small (on the CPU, serial chunks of at least 256 pixels)."""
    T = random_pose(rng, 0.1)
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t)
    n = P.shape[0] * P.shape[1]
    kp = pass_for(n) if chunks == "default" else pass_for(n, n_chunks=1100 if chunks == "parallel" else 97)
    if chunks != "default":
        kp.serial_below = n + 1 if chunks == "serial" else 0  # on the calling thread, or in parallel
    args = (vec_field(P), vec_field(N), vec_field(Vt), vec_field(Nt))
    status = kp.status(*args, T, K_t.as_tuple(), THR, THETA)
    sums = kp.reduce(*args, T, K_t.as_tuple(), THR, THETA, [point_to_plane(robust, 0.05)])
    ref_status, ref_sums = icp_numpy.icp_pass(P, N, Vt, Nt, T, K_t.as_tuple(), THR, THETA, robust, 0.05)
    np.testing.assert_array_equal(status, ref_status)
    counts = np.bincount(status.ravel(), minlength=7)
    assert np.all(counts >= 20), f"every status code exercised: {counts}"
    assert sums[kicp.SUM_INLIERS] == counts[kicp.STATUS_OK]
    assert sums[kicp.SUM_SOURCE] == status.size - counts[kicp.STATUS_SOURCE_INVALID]
    assert_sums_close(sums, ref_sums)


@pytest.mark.parametrize("robust", ["none", "tukey", "huber+depth"])
def test_benchmark_numpy_iteration_matches_reference(rng, robust):
    """The lean NumPy iteration of scripts/bench_icp.py (source masked once) gives icp_pass's sums."""
    T = random_pose(rng, 0.1)
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t)
    level = icp_numpy.LevelIteration(P, N, Vt, Nt, K_t.as_tuple(), THR, THETA, robust, 0.05)
    _, ref = icp_numpy.icp_pass(P, N, Vt, Nt, T, K_t.as_tuple(), THR, THETA, robust, 0.05)
    assert ref[kicp.SUM_INLIERS] >= 20
    got = level.sums(T)
    np.testing.assert_array_equal(got[kicp.SUM_INLIERS:], ref[kicp.SUM_INLIERS:])
    assert np.all(np.abs(got - ref) <= 1e-12 * cs_scale(ref))  # the same float64 math, rows in the same order


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
@pytest.mark.parametrize("march", ["x86-64", "native"])
@pytest.mark.parametrize("robust", ["none", "tukey", "huber+depth"])
def test_c_pass_of_ceiling_benchmark_matches_reference(rng, tmp_path, robust, march, script):
    """scripts/icp_pass.c, built as scripts/bench_icp_ceiling.py builds it, gives icp_pass's sums."""
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    T = random_pose(rng, 0.1)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t, src_shape=(K_t.height, K_t.width))
    exe = tmp_path / "icp_pass"
    subprocess.run(script("bench_icp_ceiling").c_command("cc", march, robust, exe), check=True)
    for fname, a in zip(("sv", "sn", "tv", "tn"), (P, N, Vt, Nt)):
        a.astype(np.float32).tofile(tmp_path / f"{fname}.bin")
    params = np.concatenate([flatten_pose(T), K_t.as_tuple(), [THR ** 2, np.cos(np.radians(THETA)), 0.05]])
    params.tofile(tmp_path / "params.bin")
    out = subprocess.run([str(exe), str(tmp_path), str(K_t.height), str(K_t.width), "1"], capture_output=True,
                         text=True, check=True).stdout.split()
    got = np.array([float(x) for x in out[1:]])
    _, ref = icp_numpy.icp_pass(P, N, Vt, Nt, T, K_t.as_tuple(), THR, THETA, robust, 0.05)
    assert ref[kicp.SUM_INLIERS] >= 20
    np.testing.assert_array_equal(got[kicp.SUM_INLIERS:], ref[kicp.SUM_INLIERS:])
    assert np.all(np.abs(got - ref) <= 1e-9 * cs_scale(ref))


def boundary_case(K_t: Intrinsics, T: np.ndarray):
    """Source points placed a hair inside and outside every association boundary. Returns the maps and
    the expected status code per source pixel (one row of the source image per case). The point on the
    camera plane (z′ = 0 exactly) is included only for a pure translation, where float32 keeps it exact."""
    Ht, Wt = K_t.height, K_t.width
    v, u = np.mgrid[0:Ht, 0:Wt]
    Vt = rays(K_t, u, v) * 1.5
    Nt = np.broadcast_to([0.0, 0.0, -1.0], Vt.shape).copy()
    Vt[2, 3] = 0.0   # invalid target vertex
    Nt[2, 5] = 0.0   # invalid target normal
    eps, deg = 0.02, 0.3
    cos_t, sin_t = math.cos(math.radians(THETA - deg)), math.sin(math.radians(THETA - deg))
    cos_f, sin_f = math.cos(math.radians(THETA + deg)), math.sin(math.radians(THETA + deg))
    # (target-camera point p′ as (u, v, z) on the pixel grid, target-camera normal, expected status)
    n0 = [0.0, 0.0, -1.0]
    cases = [
        ((-0.5 + eps, 4, 1.5), n0, kicp.STATUS_OK),                   # rounds to u = 0
        ((-0.5 - eps, 4, 1.5), n0, kicp.STATUS_OUT_OF_IMAGE),         # rounds to u = −1
        ((Wt - 0.5 - eps, 4, 1.5), n0, kicp.STATUS_OK),               # u = W − 1
        ((Wt - 0.5 + eps, 4, 1.5), n0, kicp.STATUS_OUT_OF_IMAGE),     # u = W
        ((6, -0.5 + eps, 1.5), n0, kicp.STATUS_OK),
        ((6, -0.5 - eps, 1.5), n0, kicp.STATUS_OUT_OF_IMAGE),
        ((6, Ht - 0.5 - eps, 1.5), n0, kicp.STATUS_OK),
        ((6, Ht - 0.5 + eps, 1.5), n0, kicp.STATUS_OUT_OF_IMAGE),
        ((6, 4, 1e-3), n0, kicp.STATUS_TOO_FAR),                     # just in front: associates, far away
        ((6, 4, 0.0), n0, kicp.STATUS_BEHIND),                       # on the camera plane (z′ = 0)
        ((6, 4, -1e-3), n0, kicp.STATUS_BEHIND),
        ((3, 2, 1.5), n0, kicp.STATUS_TARGET_INVALID),               # target vertex zero
        ((5, 2, 1.5), n0, kicp.STATUS_TARGET_INVALID),               # target normal zero
        ((6, 4, 1.5 + THR * 0.99), n0, kicp.STATUS_OK),              # ‖p′ − q‖ just below d_thr
        ((6, 4, 1.5 + THR * 1.01), n0, kicp.STATUS_TOO_FAR),         # just above
        ((6, 4, 1.5 - THR * 1.01), n0, kicp.STATUS_TOO_FAR),
        ((6, 4, 1.5), [sin_t, 0.0, -cos_t], kicp.STATUS_OK),         # angle just below θ
        ((6, 4, 1.5), [0.0, sin_f, -cos_f], kicp.STATUS_NORMAL_ANGLE),  # just above
        ((6, 4, 1.5), [0.0, 0.0, 1.0], kicp.STATUS_NORMAL_ANGLE),    # back-facing
    ]
    R, t = T[:3, :3], T[:3, 3]
    if not np.array_equal(R, np.eye(3)):
        cases = [c for c in cases if c[0][2] != 0.0]
    P = np.zeros((len(cases) + 2, 1, 3))
    N = np.zeros_like(P)
    expected = []
    for i, ((pu, pv, z), n_t, code) in enumerate(cases):
        p_t = rays(K_t, np.array([pu], float), np.array([pv], float))[0] * z
        if z == 0.0:
            p_t = np.array([0.3, -0.2, 0.0])
        P[i, 0] = R.T @ (p_t - t)
        N[i, 0] = R.T @ np.asarray(n_t)
        expected.append(code)
    P[len(cases), 0], N[len(cases), 0] = 0.0, [0.0, 0.0, -1.0]    # source vertex invalid
    P[len(cases) + 1, 0], N[len(cases) + 1, 0] = [0.1, 0.1, 1.0], 0.0  # source normal invalid
    expected += [kicp.STATUS_SOURCE_INVALID] * 2
    return P, N, Vt, Nt, np.array(expected).reshape(-1, 1)


@pytest.mark.parametrize("rotation", [[0.02, -0.03, 0.01], [0.0, 0.0, 0.0]])
def test_status_codes_at_every_boundary(arch, rotation):
    T = se3_exp(rotation + [0.0, 0.0, 0.0])
    T[:3, 3] = [0.05, -0.025, -0.5]  # the target camera 0.5 m ahead: see random_pose
    K_t = Intrinsics(100.0, 100.0, 6.3, 4.2, 12, 9)
    P, N, Vt, Nt, expected = boundary_case(K_t, T)
    kp = pass_for(P.shape[0])
    args = (vec_field(P), vec_field(N), vec_field(Vt), vec_field(Nt))
    status = kp.status(*args, T, K_t.as_tuple(), THR, THETA)
    ref_status, _ = icp_numpy.icp_pass(P, N, Vt, Nt, T, K_t.as_tuple(), THR, THETA)
    np.testing.assert_array_equal(ref_status, expected)
    np.testing.assert_array_equal(status, expected)


# -- solve ---------------------------------------------------------------------------------------------
def test_solve_on_a_known_system(rng):
    A = rng.normal(size=(500, 6)) * [1.0, 2.0, 0.5, 1.0, 3.0, 1.0]
    delta = rng.normal(size=6)
    b = -A @ delta + 1e-9 * rng.normal(size=500)
    np.testing.assert_allclose(solve_normal_equations(A.T @ A, A.T @ b), delta, atol=1e-8)


def test_cholesky_keeps_the_step_up_to_the_condition_limit(rng):
    """The normal equations square cond(A); at the largest cond(AᵀA) the checks accept (1e7), the Cholesky
    step still matches a QR solve of the stacked rows, which does not square it, to 1e-7 of its size."""
    U, _ = np.linalg.qr(rng.normal(size=(500, 6)))
    V, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    A = U @ np.diag(np.sqrt(np.logspace(0, 6.999, 6))) @ V.T  # cond(AᵀA) just under 1e7
    b = rng.normal(size=500)
    assert check_system(A.T @ A, 500, 100, 1e7)[0] is None
    Q, R = np.linalg.qr(A)
    qr = np.linalg.solve(R, -(Q.T @ b))
    np.testing.assert_allclose(solve_normal_equations(A.T @ A, A.T @ b), qr, atol=1e-7 * np.abs(qr).max())


def test_degenerate_systems_are_reported():
    assert check_system(np.eye(6), 12, 100, 1e7)[0] == "too few inliers (12 < 100)"
    singular = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    assert check_system(singular, 1000, 100, 1e7)[0].startswith("rank-deficient AᵀA (rank 5")
    ill = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1e-9])
    failure, cond = check_system(ill, 1000, 100, 1e7)
    assert failure.startswith("ill-conditioned AᵀA (cond 1.0e+09") and cond == pytest.approx(1e9)
    assert check_system(np.diag([1.0, 2, 3, 4, 5, 6]), 1000, 100, 1e7) == (None, pytest.approx(6.0))


def test_condition_numbers_of_a_stack_are_each_matrixs(rng):
    """The batched condition numbers (ICP's replay) against NumPy's float64 cond, per matrix: positive
    definite, singular, negative, non-finite."""
    A = rng.normal(size=(5, 40, 6))
    stack = np.einsum("kij,kil->kjl", A, A)  # AᵀA of each
    stack[1] = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    stack[2] = -np.eye(6)
    stack[3, 0, 0] = np.nan
    got = condition_numbers(stack)
    for k in (0, 4):
        assert got[k] == pytest.approx(np.linalg.cond(stack[k]), rel=1e-9)
        assert got[k] == condition_number(stack[k])
    assert np.all(np.isinf(got[1:4]))
    assert condition_numbers(np.zeros((0, 6, 6))).shape == (0,)


# -- the loop on synthetic pairs ---------------------------------------------------------------------
SYNTH = SynthConfig(width=320, height=240, fx=262.5)


@pytest.fixture
def sequence():
    """The synthetic renderer (on the running backend) at 320×240."""
    return SyntheticSequence(SYNTH)


def synthetic_pair(sequence, rng, noise, deg=3.0, metres=0.05, cfg: ICPConfig = ICPConfig(), smooth: int = -1):
    """Maps of the synthetic room seen from a pose of the camera path and from that pose moved by
    ``deg`` degrees about a random axis and ``metres`` along a random direction, and the true relative
    pose G (p_target = G p_source)."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    G = make_pose(so3_exp(np.radians(deg) * axis / np.linalg.norm(axis)), metres * direction / np.linalg.norm(direction))
    pose = sequence.poses[rng.integers(len(sequence.poses))]
    seeds = rng.integers(2**31, size=2)
    depth_s, _ = sequence.render(pose, noise=noise, seed=int(seeds[0]))
    depth_t, _ = sequence.render(pose @ invert(G), noise=noise, seed=int(seeds[1]))
    K = sequence.intrinsics
    return maps_of(depth_s, K, cfg, smooth=smooth), maps_of(depth_t, K, cfg, slot="target", smooth=smooth), G


_MAPS: dict = {}


def maps_of(depth: np.ndarray, K: Intrinsics, cfg: ICPConfig = ICPConfig(), slot: str = "source",
            smooth: int = -1) -> FramePyramid:
    """The maps of one depth image as the ICP command builds them (``cfg``'s levels, smoothing radius ``smooth``).
    One FramePyramid per (backend, size, slot) is reused: Taichi compiles its kernels once per set of fields."""
    key = (depth.shape, len(cfg.iterations), slot, smooth)
    backend, pyramid = _MAPS.get(key, (None, None))
    if backend is not current_backend():  # fields do not survive a change of backend
        pyramid = FramePyramid(PyramidConfig(depth_smooth_radius=smooth), K.height, K.width, len(cfg.iterations))
        _MAPS[key] = (current_backend(), pyramid)
    pyramid.compute(depth, K)
    return pyramid


def test_synthetic_motion_recovered_without_noise(arch, rng, sequence):
    # Exact depth needs no smoothing, and smoothing is view-dependent at corners (a floor on the residual)
    src, tgt, G = synthetic_pair(sequence, rng, noise=False, smooth=0)
    result = ICP(ICPConfig()).align(src, tgt)
    rot, trans = pose_error(result.pose, G)
    assert result.failure is None and result.converged
    assert rot < 0.05 and trans < 0.5e-3, (rot, trans)
    losses = [r.loss for r in result.iterations if r.level == 0]
    assert losses[-1] < 1e-6 and result.inlier_ratio > 0.8


@pytest.mark.slow
@pytest.mark.parametrize("robust", ["none", "huber", "tukey", "huber+depth"])
def test_synthetic_motion_recovered_with_noise(cpu, rng, sequence, robust):
    robust, _, depth = robust.partition("+")
    scale = {"none": 0.01, "huber": 0.01, "tukey": 0.03}[robust]
    # Light smoothing (r = 2): the default's heavier, image-relative smoothing pays on real Kinect depth
    # (redkitchen ATE) but rounds the synthetic room's sharp corners differently in the two views, which
    # costs a frame pair ~0.3 mm here (median over 12 pairs 0.13 → 0.39 mm).
    config = ICPConfig(robust=robust, robust_scale=scale, depth_weighting=depth == "depth")
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=config, smooth=2)
    result = ICP(config).align(src, tgt)
    rot, trans = pose_error(result.pose, G)
    assert result.failure is None
    # The stated tolerance with the renderer's Kinect-like noise: 0.05° and 1.5 mm (over 8 random pairs
    # the worst was 0.02° and 0.67 mm).
    assert rot < 0.05 and trans < 1.5e-3, (rot, trans)


@pytest.mark.parametrize("robust", ["huber+depth", "tukey"])
def test_sums_at_convergence_match_reference(arch, rng, sequence, robust):
    """At the converged pose Aᵀb's signed terms cancel (Aᵀb → 0): the case where float32 accumulation
    would lose it. On cpu every one of the 30 sums still agrees with float64 NumPy to 1e-5 relative."""
    name, _, depth = robust.partition("+")
    cfg = ICPConfig(robust=name, robust_scale=0.03, depth_weighting=depth == "depth", stop_update=1e-7)
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    pose = ICP(cfg).align(src, tgt).pose
    fields = (src.vertex[0], src.normal[0], tgt.vertex[0], tgt.normal[0])
    K_t = tgt.intrinsics[0].as_tuple()
    thr = ICP(cfg).dist_threshold(0)
    sums = pass_for(src.width * src.height).reduce(*fields, pose, K_t, thr, cfg.normal_threshold_deg,
                                                   [point_to_plane(robust, 0.03)])
    _, ref = icp_numpy.icp_pass(*(f.to_numpy() for f in fields), pose, K_t, thr, cfg.normal_threshold_deg,
                                robust, 0.03)
    s = kicp.unpack_sums(ref)
    # Terms cancelled: Aᵀb is orders of magnitude below the scale of its terms (how far below depends on
    # where the iteration cap stopped ICP, so the bound is loose; the check that matters is the next one).
    assert np.abs(s["Atb"]).max() < 1e-3 * np.sqrt(np.diag(s["AtA"]) * s["r2"]).max()
    assert_sums_close(sums, ref)


def _align_in_python(cfg: ICPConfig, src, tgt, init=None):
    """ICP with every iteration's sums solved in NumPy (the path a system the kernel refused goes on in)."""
    icp = ICP(cfg)
    result = ICPResult(pose=np.eye(4) if init is None else init)
    schedule = list(zip(reversed(range(len(cfg.iterations))), cfg.iterations))
    icp._align_in_python(icp._kernels(src.width * src.height), src, tgt, schedule, result)
    return result


def assert_same_run(a: ICPResult, b: ICPResult):
    assert a.failure == b.failure and a.converged == b.converged
    assert [(r.level, r.iteration, r.inliers) for r in a.iterations] == \
        [(r.level, r.iteration, r.inliers) for r in b.iterations]
    np.testing.assert_allclose([r.loss for r in a.iterations], [r.loss for r in b.iterations], rtol=1e-9)
    np.testing.assert_allclose([r.update_norm for r in a.iterations], [r.update_norm for r in b.iterations],
                               rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(a.pose, b.pose, rtol=0, atol=1e-12)
    assert a.inliers == b.inliers
    # Two summation orders perturb the 6×6 system by ~eps of its scale, and its condition number moves by
    # about condition × eps relative: a singular system's (~1e10) differs in the 7th digit, a good one's not.
    rel = max(1e-9, 1e3 * np.finfo(np.float64).eps * max(a.condition, b.condition))
    assert a.condition == pytest.approx(b.condition, rel=rel)
    assert a.inlier_ratio == b.inlier_ratio
    np.testing.assert_allclose([a.residual_rms, a.update_norm], [b.residual_rms, b.update_norm], rtol=1e-6,
                               atol=1e-12)


def spy_on_python_path(monkeypatch) -> list:
    """The start points of every ``ICP._align_in_python`` call from now on."""
    starts = []
    in_python = ICP._align_in_python

    def spy(self, kernels, source, target, schedule, result, start=(0, 0)):
        starts.append(start)
        return in_python(self, kernels, source, target, schedule, result, start)

    monkeypatch.setattr(ICP, "_align_in_python", spy)
    return starts


@pytest.mark.parametrize("stop_update", [1e-4, 0.0])
def test_solve_in_kernel_matches_solve_in_numpy(cpu, rng, sequence, stop_update, monkeypatch):
    """The default path (Cholesky solve and SE(3) update inside the iteration's kernel, float64) runs the
    same iterations to the same pose as solving every iteration's sums in NumPy."""
    cfg = ICPConfig(stop_update=stop_update)
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    kernels = ICP(cfg)._kernels(src.width * src.height)
    assert kernels.solves_in_kernel
    starts = spy_on_python_path(monkeypatch)
    in_kernel = ICP(cfg).align(src, tgt)
    records = kernels.iteration_records()
    monkeypatch.undo()
    assert starts == []  # solved in the kernel throughout: no hand-over to NumPy
    assert len(records) == len(in_kernel.iterations) and (records[:, kicp.R_OUTCOME] == kicp.UPDATED).all()
    if stop_update == 0:
        assert len(in_kernel.iterations) == sum(cfg.iterations)
    else:  # the stop criterion ended a level early somewhere
        assert len(in_kernel.iterations) < sum(cfg.iterations)
    assert_same_run(in_kernel, _align_in_python(cfg, src, tgt))


def test_each_level_stops_at_its_own_update(cpu, rng, sequence):
    """A level stops once ‖δξ‖ falls below icp.stop_update · 2^level (its pixels are 2^level times larger),
    and not before."""
    cfg = ICPConfig(stop_update=1e-4)
    src, tgt, _ = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    icp = ICP(cfg)
    assert [icp.stop_update(level) for level in (0, 1, 2)] == [1e-4, 2e-4, 4e-4]
    result = icp.align(src, tgt)
    assert result.failure is None and result.converged
    for level, budget in zip((2, 1, 0), cfg.iterations):
        norms = [r.update_norm for r in result.iterations if r.level == level]
        assert all(n >= icp.stop_update(level) for n in norms[:-1]), (level, norms)
        assert len(norms) == budget or norms[-1] < icp.stop_update(level), (level, norms)

    # A threshold the coarsest level's second update lies between (×1 and ×4): that level stops there.
    every = ICP(ICPConfig(stop_update=0.0)).align(src, tgt)
    coarsest = [r.update_norm for r in every.iterations if r.level == 2]
    stop = coarsest[1] / 1.5
    assert coarsest[0] >= 4 * stop, coarsest  # the pair's first update is well above both
    stopped = ICP(ICPConfig(stop_update=stop)).align(src, tgt)
    assert [r.level for r in stopped.iterations].count(2) == 2


def test_converged_is_the_last_levels_stop_test():
    """With no iteration at the finest level, ``converged`` asks the last level that ran."""
    icp = ICP(ICPConfig(stop_update=1e-4))
    result = ICPResult(pose=np.eye(4), iterations=[IterationRecord(1, 0, 0.0, 500, 1.5e-4)], update_norm=1.5e-4)
    assert icp._converged(result)
    result.iterations[-1].level = 0
    assert not icp._converged(result)


@pytest.mark.parametrize("refused, resume", [(6, (0, 6)), (10, (1, 0)), (17, (2, 2))])
def test_solve_in_kernel_hands_over_to_numpy(cpu, rng, sequence, monkeypatch, refused, resume):
    """Where the kernel's Cholesky refuses a system that NumPy's checks accept, the run goes on in NumPy
    from the pose before that iteration (at that stage and iteration), and ends as a NumPy run does."""
    cfg = ICPConfig(stop_update=0.0)
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    kernels = ICP(cfg)._kernels(src.width * src.height)  # the pass every ICP object shares
    records = kernels.iteration_records

    def refused_there():
        r = records()
        r[refused, kicp.R_OUTCOME] = kicp.NOT_POSITIVE_DEFINITE
        return r[:refused + 1]

    monkeypatch.setattr(type(kernels), "iteration_records", lambda self: refused_there())
    starts = spy_on_python_path(monkeypatch)
    handed_over = ICP(cfg).align(src, tgt)
    monkeypatch.undo()
    assert starts == [resume]  # e.g. the 7th iteration is stage 0 (level 2, 10 iterations), iteration 6
    assert_same_run(handed_over, _align_in_python(cfg, src, tgt))


@pytest.mark.slow
def test_iterate_refuses_more_iterations_than_records(cpu, rng, sequence):
    src, tgt, G = synthetic_pair(sequence, rng, noise=False)
    kernels = ICP(ICPConfig())._kernels(src.width * src.height)
    kernels.begin_iterations(np.eye(4), 1)
    kernels.begin_level(src.vertex[0], src.normal[0], tgt.vertex[0], tgt.normal[0], tgt.intrinsics[0].as_tuple(),
                        0.1, 30.0, 0, 100, 0.0, [point_to_plane("huber", 0.01)])
    capacity = kernels.records.shape[0]
    for it in range(capacity):
        kernels.iterate(it)
    with pytest.raises(ValueError, match="iterations since begin_iterations"):
        kernels.iterate(capacity)


def test_a_longer_schedule_grows_the_state_to_at_least_twice(arch, rng, sequence):
    """An align whose schedule outgrows the state array's records gets a larger one, at least twice the
    records (off the CPU each new device field is a new instance of ``iterate``: the doubling bounds how
    many), and the longer schedule runs as on a fresh one."""
    short = ICPConfig(iterations=(4, 2, 2))
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=short, smooth=2)
    icp = ICP(short)
    assert icp.align(src, tgt).failure is None
    kernels = icp._kernels(src.width * src.height)
    first = kernels.records.shape[0]
    long = ICPConfig(iterations=(first - 1, 1, 1), stop_update=0.0)  # one record more than there is room for
    grown = ICP(long).align(src, tgt)
    assert kernels.records.shape[0] >= 2 * first
    assert grown.failure is None
    assert [(r.level, r.iteration) for r in grown.iterations] == \
        [(r.level, r.iteration) for r in _align_in_python(long, src, tgt).iterations]


@pytest.mark.slow
def test_single_plane_is_degenerate(cpu):
    K = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
    v, u = np.mgrid[0:K.height, 0:K.width]
    n = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    depth = (-2.0 / (rays(K, u.astype(float), v.astype(float)) @ n)).astype(np.float32)
    src, tgt = maps_of(depth, K), maps_of(depth, K, slot="target")
    init = se3_exp([0.0, 0.0, 0.0, 0.01, 0.0, 0.0])
    result = ICP(ICPConfig()).align(src, tgt, init=init)
    assert result.failure is not None and "AᵀA" in result.failure
    assert not result.converged
    np.testing.assert_allclose(result.pose, init)  # the last good estimate: nothing was solved
    assert_same_run(result, _align_in_python(ICPConfig(), src, tgt, init))  # found on replay, as in NumPy


@pytest.mark.slow
def test_all_invalid_depth_is_a_failure_not_an_exception(cpu, sequence):
    K = sequence.intrinsics
    depth, _ = sequence.render(sequence.poses[0], noise=False)
    src, tgt = maps_of(depth, K), maps_of(np.zeros((K.height, K.width), np.float32), K, slot="target")
    result = ICP(ICPConfig()).align(src, tgt)
    assert result.failure == "level 2 iteration 0: too few inliers (0 < 100)"
    assert result.inliers == 0 and result.inlier_ratio == 0.0 and not result.converged
    np.testing.assert_array_equal(result.pose, np.eye(4))
    python = _align_in_python(ICPConfig(), src, tgt)
    assert python.failure == result.failure and len(python.iterations) == len(result.iterations) == 1


# -- real data ---------------------------------------------------------------------------------------
# How the pairs were picked: ICP from the identity on all 49 pairs (s, s + 10),
# s = 0, 10, …, 480, at 640×480 with the default config: 48 converge (the median error against the
# reference is 8.9 mm and 0.29°, the worst converged 45 mm; s = 460 slides away), and 6 are within 5 mm
# and 0.5°: s = 10, 40, 140, 160, 220, 240. The reference is KinectFusion's trajectory, not ground truth:
# on 48 of the 49 pairs the ICP pose fits the two depth images better than the reference relative pose
# does (lower point-to-plane RMS at level 1 with the same association), so most of the remaining ~1 cm
# is disagreement with the reference, not a failure to minimise. These two pairs pass; most would not.
REAL_PAIRS = [(10, 20), (40, 50)]


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("source, target", REAL_PAIRS)
def test_redkitchen_pair_from_identity(cpu, redkitchen, source, target):
    from ti_fusion.io.datasets import open_dataset

    data = open_dataset(DatasetConfig(path=str(redkitchen)))
    fs, ft = data.frame_by_raw_index(source), data.frame_by_raw_index(target)
    cfg = ICPConfig()
    src, tgt = maps_of(fs.depth, fs.intrinsics, cfg), maps_of(ft.depth, ft.intrinsics, cfg, slot="target")
    reference = invert(ft.gt_pose) @ fs.gt_pose
    result = ICP(cfg).align(src, tgt)
    rot, trans = pose_error(result.pose, reference)
    assert result.failure is None
    assert rot < 0.5 and trans < 5e-3, (rot, trans)


# -- the command -------------------------------------------------------------------------------------
@pytest.mark.slow
def test_icp_command_on_the_synthetic_sequence(cpu, tmp_path, capsys):
    import json

    from ti_fusion.cli.main import main

    assert main(["icp", "--source", "3", "--target", "8", "--downsample", "2", "--quiet", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "level iter" in out and "error against ground truth" in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    for key in ("pose", "rot_err_deg", "trans_err_m", "converged", "failure", "iterations"):
        assert key in summary
    assert np.asarray(summary["pose"]).shape == (4, 4)
    assert summary["failure"] is None and summary["rot_err_deg"] < 0.5 and summary["trans_err_m"] < 0.01
    assert {"level", "iteration", "loss", "inliers"} <= set(summary["iterations"][0])
    assert (tmp_path / "icp.png").stat().st_size > 10_000


def test_icp_command_rejects_a_missing_frame(cpu, redkitchen, tmp_path, capsys):
    from ti_fusion.cli.main import main

    assert main(["icp", str(redkitchen), "--source", "10", "--target", "100000", "--quiet", "--out", str(tmp_path)]) == 2
    assert "--target 100000: no such frame (the sequence has frames 0 to " in capsys.readouterr().err


def test_a_non_rigid_initial_pose_is_refused():
    class Maps:  # align checks the pose before touching any map
        levels = 3

    with pytest.raises(ValueError, match="initial pose: rotation block is not orthonormal"):
        ICP().align(Maps, Maps, init=np.diag([2.0, 1.0, 1.0, 1.0]))


@pytest.mark.slow
def test_align_compiles_one_iterate_instance_for_every_level(cpu, sequence):
    """The pyramid levels are rows of one field per quantity (``kernels/pyramid.py``), so aligning a new pair
    of maps over three levels adds one instance of the ``iterate`` kernel, not one per level (here a frame
    aligned to itself: one iteration per level)."""
    cfg = ICPConfig()
    K = sequence.intrinsics
    pyramid = FramePyramid(PyramidConfig(depth_smooth_radius=0), K.height, K.width, len(cfg.iterations))  # new fields
    pyramid.compute(sequence.render(sequence.poses[0], noise=False)[0], K)
    icp = ICP(cfg)
    kp = icp._kernels(K.width * K.height)
    name = "iterate_sums" if kp.on_host else "iterate"  # (the CPU's sums half; its solve half has no images)
    iterate = kicp.kernels_for(kp.real, not kp.on_host, (icp.terms[0].row,))[name]._primal  # the geometry's
    before = len(iterate.compiled_kernels)
    result = icp.align(pyramid, pyramid)
    assert result.failure is None and {r.level for r in result.iterations} == {0, 1, 2}
    assert len(iterate.compiled_kernels) - before == 1


@pytest.mark.parametrize("stop_update", [1e-4, 0.0])
def test_whole_schedule_on_the_device_matches_numpy(arch, rng, sequence, stop_update):
    """On every backend the whole schedule runs in ``iterate`` launches (solve, stop test and the no-ops
    after a stop on the device) to the pose of solving each iteration's sums in NumPy: float64 on the CPU
    to rounding; float32 elsewhere (Jacobi-scaled Cholesky, the pose kept in float32) within 1e-5 m and
    1e-3°. Off the CPU every iteration of the schedule is launched, and the records show that the device
    stopped each level where NumPy does."""
    cfg = ICPConfig(stop_update=stop_update)
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    in_kernel = ICP(cfg).align(src, tgt)
    in_numpy = _align_in_python(cfg, src, tgt)
    assert in_kernel.failure is None and in_numpy.failure is None
    assert [(r.level, r.iteration) for r in in_kernel.iterations] == \
        [(r.level, r.iteration) for r in in_numpy.iterations]
    if stop_update:
        assert len(in_kernel.iterations) < sum(cfg.iterations)  # the stop ended a level early somewhere
    if arch == "cpu":
        assert_same_run(in_kernel, in_numpy)
    else:
        err = pose_error(in_kernel.pose, in_numpy.pose)
        assert err[0] < 1e-3 and err[1] < 1e-5
        assert in_kernel.inliers == pytest.approx(in_numpy.inliers, abs=2)


def test_align_reads_back_at_most_once(arch, rng, sequence, script):
    """One ``align`` (three levels, up to 19 iterations) reads nothing back from the device until its end,
    and then once (the state array with the pose and the records); on the CPU the kernels write the host's
    array in place, so not even that. Counted by ``bench_host.py``'s wrappers around Taichi."""
    cfg = ICPConfig()
    src, tgt, G = synthetic_pair(sequence, rng, noise=True, cfg=cfg, smooth=2)
    ICP(cfg).align(src, tgt)  # compiled before counting
    counter = script("bench_host").Counter(current_backend().arch)
    counter.install()
    try:
        counter.active = True
        result = ICP(cfg).align(src, tgt)
        counter.active = False
    finally:
        counter.uninstall()
    assert result.failure is None
    assert counter.total_reads() == (0 if arch == "cpu" else 1), counter.reads
    if arch == "cpu":  # the iteration as two kernels, each launched once per iteration run
        assert counter.launches["iterate_sums"] == counter.launches["iterate_solve"] == len(result.iterations)
    else:
        assert counter.launches["iterate"] == sum(cfg.iterations)
