"""The photometric term of joint ICP: the joint pass's 59 sums against the NumPy float64 reference on every
backend, the in-kernel solve against NumPy's, and a textured plane (three directions depth cannot see)
tracked only with colour.

Tolerances as tests/tracking/test_icp.py: cpu 1e-5 relative; vulkan (float32) each entry within 1e-4 of its
Cauchy–Schwarz bound, per term (geometric, colour); counts exact."""

import math

import numpy as np
import pytest
import taichi as ti

from ti_fusion.backend import current_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import ICPConfig, PyramidConfig
from ti_fusion.geometry import make_pose, pose_error, so3_exp
from ti_fusion.kernels import icp as kicp
from ti_fusion.kernels.pyramid import FramePyramid
from ti_fusion.reference import icp as icp_numpy
from ti_fusion.tracking.icp import ICP
from ti_fusion.tracking.solve import weak_directions
from ti_fusion.tracking.terms.photometric import CLEAN_BLOCKINESS, JPEG_BLOCKINESS, photometric
from ti_fusion.tracking.terms.point_to_plane import point_to_plane
from tests.tracking.test_icp import THETA, THR, cs_scale, pass_for, random_pass_inputs, random_pose, rays, vec_field


def random_intensities(rng, P, T, K_t: Intrinsics):
    """Model intensities (−1 at some pixels), the target's (I, ∂I/∂x, ∂I/∂y) (I = −1 at some), and the
    source points with every pixel whose projection lies within rounding of a tap or image boundary made
    invalid (so float32 and float64 pick the same taps)."""
    Ht, Wt = K_t.height, K_t.width
    src_i = rng.uniform(0.0, 1.0, P.shape[:2])
    src_i[rng.random(P.shape[:2]) < 0.05] = -1.0
    tgt_ig = np.stack([rng.uniform(0.0, 1.0, (Ht, Wt)), rng.normal(0, 0.05, (Ht, Wt)), rng.normal(0, 0.05, (Ht, Wt))],
                      axis=-1)
    tgt_ig[rng.random((Ht, Wt)) < 0.03, 0] = -1.0
    p = P.reshape(-1, 3).astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = K_t.fx * p[:, 0] / p[:, 2] + K_t.cx
        y = K_t.fy * p[:, 1] / p[:, 2] + K_t.cy
    near = lambda a: np.abs(a - np.round(a)) < 0.01  # noqa: E731 (a tap or a boundary: integers)
    P = P.copy()
    P.reshape(-1, 3)[near(x) | near(y)] = 0.0
    return P, src_i.astype(np.float32), tgt_ig.astype(np.float32)


def scalar_field(a):
    f = ti.field(ti.f32, shape=a.shape)
    f.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return f


C = kicp.term_offset(1)  # the colour term's sums in a pass with the geometry first


def assert_joint_close(got, ref):
    np.testing.assert_array_equal(got[kicp.SUM_INLIERS:kicp.N_SUMS], ref[kicp.SUM_INLIERS:kicp.N_SUMS])
    assert got[C + kicp.TERM_COUNT] == ref[C + kicp.TERM_COUNT]
    if current_backend().has_f64:
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-12)
        return
    for part in (slice(0, kicp.N_SUMS), None):
        if part is None:  # the colour term laid out as a geometric pass's 30 sums
            g = np.concatenate([got[C:C + kicp.TERM_SUMS], [0.0]])
            r = np.concatenate([ref[C:C + kicp.TERM_SUMS], [0.0]])
        else:
            g, r = got[part], ref[part]
        err = np.abs(g - r) / np.maximum(cs_scale(r), 1e-30)
        assert err.max() < 1e-4, f"float32 sums off by {err.max():.2e} of their scale"


@pytest.mark.parametrize("chunks", ["parallel", "default"])
def test_joint_sums_match_reference(arch, rng, chunks):
    T = random_pose(rng, 0.1)
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t)
    P, src_i, tgt_ig = random_intensities(rng, P, T, K_t)
    n = P.shape[0] * P.shape[1]
    kp = pass_for(n) if chunks == "default" else pass_for(n, n_chunks=1100)
    if chunks != "default":
        kp.serial_below = 0
    args = (vec_field(P), vec_field(N), vec_field(Vt), vec_field(Nt))
    color = photometric(scalar_field(src_i), vec_field(tgt_ig), 0.3, 0.2)
    sums = kp.reduce(*args, T, K_t.as_tuple(), THR, THETA, [point_to_plane("huber+depth", 0.05), color])
    ref = icp_numpy.joint_pass(P, N, Vt, Nt, src_i, tgt_ig, T, K_t.as_tuple(), THR, THETA, "huber+depth", 0.05, 0.2)
    assert sums.shape == (kicp.n_sums(2),) == (59,)
    inliers, with_color = ref[kicp.SUM_INLIERS], ref[C + kicp.TERM_COUNT]
    assert 50 < with_color < inliers, (with_color, inliers)  # some correspondences have no colour residual
    assert_joint_close(sums, ref)
    # the depth-only pass of the same inputs: the first 30 sums, unchanged
    plain = kp.reduce(*args, T, K_t.as_tuple(), THR, THETA, [point_to_plane("huber+depth", 0.05)])
    np.testing.assert_allclose(plain, sums[:kicp.N_SUMS], rtol=1e-6 if current_backend().has_f64 else 1e-4,
                               atol=1e-12 if current_backend().has_f64 else 1e-4 * np.abs(plain).max())


def test_combined_system_and_weak_directions():
    rng = np.random.default_rng(3)
    sums = rng.normal(size=kicp.n_sums(2))
    AtA, Atb = kicp.combined_system(sums, (1.0, 0.5))
    s, c = kicp.unpack_sums(sums), kicp.unpack_term_sums(sums, 1)
    np.testing.assert_allclose(AtA, s["AtA"] + 0.5 * c["AtA"])
    np.testing.assert_allclose(Atb, s["Atb"] + 0.5 * c["Atb"])
    assert kicp.unpack_term_sums(sums[:kicp.N_SUMS], 1) is None
    # the batched form (ICP's replay of the kernel's records): row by row the same, joint and depth-only
    for batch in (rng.normal(size=(4, kicp.n_sums(2))), rng.normal(size=(3, kicp.N_SUMS))):
        AtAs, Atbs = kicp.combined_systems(batch, (1.0, 0.5))
        for row, A, b in zip(batch, AtAs, Atbs):
            want = kicp.combined_system(row, (1.0, 0.5))
            np.testing.assert_array_equal(A, want[0])
            np.testing.assert_array_equal(b, want[1])
    geo = np.diag([1.0, 1.0, 1e-6, 1.0, 1e-7, 1.0])  # weak: ω_z and v_y
    color = np.zeros((6, 6))
    color[2, 2] = 1.0  # colour constrains ω_z only
    d = weak_directions(geo, color, 0.1, 1e-3)
    assert d["weak"] == 2 and d["constrained_by_color"] == 1
    assert d["directions"][0]["twist"] == [0, 0, 0, 0, 1, 0] and not d["directions"][0]["color"]
    assert d["directions"][1]["twist"] == [0, 0, 1, 0, 0, 0] and d["directions"][1]["color"]
    assert weak_directions(geo, None, 0.0, 1e-3)["constrained_by_color"] == 0
    # the weakest direction is reported whether weak or not (the slide starts read it), with colour's lift
    assert d["weakest"] == {"twist": [0, 0, 0, 0, 1, 0], "ratio": 1e-7, "joint_ratio": 1e-7}
    mild = np.diag([1.0, 1.0, 1.0, 1.0, 2e-3, 1.0])
    color = np.zeros((6, 6))
    color[4, 4] = 0.5
    d = weak_directions(mild, color, 0.1, 1e-3)
    assert d["weak"] == 0 and d["weakest"]["twist"] == [0, 0, 0, 0, 1, 0]
    assert d["weakest"]["ratio"] == pytest.approx(2e-3) and d["weakest"]["joint_ratio"] == pytest.approx(0.052)


# -- a textured plane: depth sees 3 of the 6 directions ------------------------------------------------
K_PLANE = Intrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)


def texture(X, Y):
    return 0.5 + 0.2 * np.sin(7.0 * X + 1.0) * np.cos(5.0 * Y) + 0.15 * np.sin(4.0 * X - 6.0 * Y)


def plane_view(pose: np.ndarray, K: Intrinsics = K_PLANE, distance: float = 1.5):
    """Depth and grey image of the plane z = ``distance`` (world) seen from camera-to-world ``pose``."""
    v, u = np.mgrid[0:K.height, 0:K.width]
    d = rays(K, u, v) @ pose[:3, :3].T  # world ray directions (z-component scale per camera z = 1)
    s = (distance - pose[2, 3]) / d[..., 2]  # camera depth along the ray (ray has camera z = 1)
    X = pose[0, 3] + s * d[..., 0]
    Y = pose[1, 3] + s * d[..., 1]
    return s.astype(np.float32), texture(X, Y).astype(np.float32)


def plane_maps(pose, slot):
    depth, grey = plane_view(pose)
    pyramid = FramePyramid(PyramidConfig(depth_smooth_radius=0), K_PLANE.height, K_PLANE.width, 2)
    pyramid.compute(depth, K_PLANE)
    pyramid.compute_intensity(grey)
    return pyramid


@pytest.fixture
def plane_pair(cpu):
    G = make_pose(so3_exp(np.radians([0.3, -0.2, 1.5])), [0.02, -0.015, 0.005])  # p_target = G p_source
    source = plane_maps(np.eye(4), "source")
    target = plane_maps(np.linalg.inv(G), "target")
    return source, target, G


@pytest.mark.slow
def test_color_tracks_what_depth_cannot_see(plane_pair):
    source, target, G = plane_pair
    cfg = ICPConfig(iterations=[10, 10], color_weight=0.0)
    depth_only = ICP(cfg).align(source, target, terms=("photometric",))  # λ = 0: the term stays off
    assert depth_only.color_inliers == 0
    assert depth_only.failure is not None and ("rank" in depth_only.failure or "ill-conditioned" in depth_only.failure)
    joint = ICP(ICPConfig(iterations=[10, 10], color_weight=0.01)).align(source, target, terms=("photometric",))
    rot, trans = pose_error(joint.pose, G)
    assert joint.failure is None and rot < 0.05 and trans < 1e-3, (joint.failure, rot, trans)
    d = joint.degeneracy
    assert d["weak"] == 3 and d["constrained_by_color"] == 3, d


def test_joint_solve_in_kernel_matches_numpy(plane_pair, monkeypatch):
    source, target, _ = plane_pair
    cfg = ICPConfig(iterations=[4, 3], color_weight=0.01, stop_update=0.0)
    in_kernel = ICP(cfg).align(source, target, terms=("photometric",))
    monkeypatch.setattr(kicp.PointToPlane, "solves_in_kernel", property(lambda self: False))  # solves in NumPy
    in_numpy = ICP(cfg).align(source, target, terms=("photometric",))
    assert in_kernel.failure is None and in_numpy.failure is None
    assert [(r.level, r.iteration, r.inliers) for r in in_kernel.iterations] == \
        [(r.level, r.iteration, r.inliers) for r in in_numpy.iterations]
    np.testing.assert_allclose(in_kernel.pose, in_numpy.pose, atol=1e-9)
    assert in_kernel.color_inliers == in_numpy.color_inliers > 1000
    assert math.isfinite(in_kernel.color_rms) and in_kernel.color_rms < 0.01


# -- in the SLAM loop ------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("weight", [None, 0.02])
def test_dense_slam_uses_color_only_where_registered(cpu, caplog, weight):
    """Frames with registered colour are tracked with the joint cost (colour residuals, degeneracy
    reported); on frames whose colour is not registered (7-Scenes) the term stays off (the depth-only pass
    runs: no colour residual), said once: a warning where the user set the weight, at info level with the
    default weight (a 7-Scenes run with the defaults is not warned about a setting it never made)."""
    import dataclasses
    import logging

    from ti_fusion.config import Config, SynthConfig
    from ti_fusion.frame import Frame
    from ti_fusion.slam.dense import DenseSLAM
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig(width=160, height=120, fx=131.25, frames=5))
    cfg = Config()
    if weight is not None:
        cfg.icp = dataclasses.replace(cfg.icp, color_weight=weight)
    slam = DenseSLAM(cfg, seq.intrinsics)
    caplog.clear()
    caplog.set_level(logging.INFO, logger="ti_fusion.tracking.terms.photometric")  # the term says it
    results = []
    for i in range(5):
        depth, color = seq.frame(i)
        results.append(slam.register_frame(Frame(i, float(i), depth, seq.intrinsics, color,
                                                 color_registered=i < 3)))
    assert all(r.tracked for r in results)
    assert all(r.icp.color_inliers > 500 and r.icp.degeneracy is not None for r in results[1:3])
    assert all(r.icp.color_inliers == 0 for r in results[3:])
    said = [r for r in caplog.records if "not registered to depth" in r.getMessage()]
    assert len(said) == 1 and f"icp.color_weight = {weight or 0.01:g}" in said[0].getMessage()
    assert "frame 3" in said[0].getMessage() and said[0].levelno == (logging.WARNING if weight else logging.INFO)


# -- the finest level's colour weight (icp.color_finest_scale on JPEG colour) ------------------------------
def test_the_finest_scale_follows_the_frames_blockiness():
    """The whole weight at and below CLEAN_BLOCKINESS, icp.color_finest_scale at and above JPEG_BLOCKINESS,
    linear between; the configured scale where the frame's blockiness is unknown."""
    from ti_fusion.tracking.terms.photometric import finest_scale

    assert finest_scale(0.4, 1.0) == finest_scale(0.4, CLEAN_BLOCKINESS) == 1.0
    assert finest_scale(0.4, JPEG_BLOCKINESS) == pytest.approx(0.4) and finest_scale(0.4, 9.0) == pytest.approx(0.4)
    assert finest_scale(0.4, (CLEAN_BLOCKINESS + JPEG_BLOCKINESS) / 2) == pytest.approx(0.7)
    assert finest_scale(0.4, float("nan")) == 0.4 and finest_scale(1.0, 9.0) == 1.0


def test_the_finest_level_weighs_colour_by_its_scale(plane_pair, monkeypatch):
    """λ is icp.color_weight at the coarse levels and, on JPEG colour (the live frame's blockiness), color_weight
    × color_finest_scale at the finest; on clean colour the whole weight there too. In the kernel's solve and in
    NumPy's alike (the replay checks the kernel's records with the same systems)."""
    source, target, _ = plane_pair
    from ti_fusion.tracking.terms.photometric import PhotometricTerm

    cfg = ICPConfig(iterations=[4, 3], color_weight=0.01, color_finest_scale=0.3, stop_update=0.0)
    term = PhotometricTerm(cfg)
    assert term.weight() == term.level_weight(1) == 0.01 and term.level_weight(0) == pytest.approx(0.003)
    assert target.blockiness == 1.0  # the plane's smooth texture, too small to tell: clean
    clean = ICP(cfg).align(source, target, terms=("photometric",))
    assert clean.weights == pytest.approx((1.0, 0.01))  # the last iteration's: the finest level's
    target.blockiness = 3.0  # as the real keyframes' JPEG
    in_kernel = ICP(cfg).align(source, target, terms=("photometric",))
    assert in_kernel.weights == pytest.approx((1.0, 0.003))
    whole = ICP(ICPConfig(iterations=[4, 3], color_weight=0.01, color_finest_scale=1.0, stop_update=0.0)) \
        .align(source, target, terms=("photometric",))
    np.testing.assert_array_equal(whole.pose, clean.pose)  # clean colour: as with the whole weight
    assert np.abs(whole.pose - in_kernel.pose).max() > 1e-9  # the scale reached the kernel
    monkeypatch.setattr(kicp.PointToPlane, "solves_in_kernel", property(lambda self: False))  # solves in NumPy
    in_numpy = ICP(cfg).align(source, target, terms=("photometric",))
    assert in_kernel.failure is None and in_numpy.failure is None
    np.testing.assert_allclose(in_kernel.pose, in_numpy.pose, atol=1e-9)
    assert in_numpy.weights == in_kernel.weights


def _synthetic_pair_error(finest_scale: float, source: int, **synth) -> tuple[float, float]:
    """Translation error (m) of the synthetic cabinet's pair ``source`` → ``source`` − 1 aligned jointly from the
    identity at the resolution SLAM tracks at (as scripts/bench_real.py's pairwise table), and the live (target)
    frame's JPEG blockiness."""
    from ti_fusion.config import Config
    from ti_fusion.geometry import invert
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.kernels.pyramid import grey_image

    cfg = Config()
    cfg.synth.scene, cfg.synth.frames = "cabinet", 29
    for key, value in synth.items():
        setattr(cfg.synth, key, value)
    cfg.icp.color_finest_scale = finest_scale
    dataset = open_dataset(cfg.dataset, cfg.synth)
    K = dataset.intrinsics
    maps = []
    for frame in (dataset[source], dataset[source - 1]):
        pyramid = FramePyramid(cfg.pyramid, K.height, K.width, len(cfg.icp.iterations),
                               input_level=cfg.frame_input_level(K.width))
        pyramid.compute(frame.depth, frame.intrinsics, grey_image(frame.color))
        maps.append((pyramid, frame.gt_pose))
    (src, src_pose), (tgt, tgt_pose) = maps
    result = ICP(cfg.icp).align(src, tgt, None, terms=("photometric",))
    return pose_error(result.pose, invert(tgt_pose) @ src_pose)[1], tgt.blockiness


@pytest.mark.slow
def test_a_lighter_finest_level_keeps_jpeg_colour_from_pulling_a_pair_off(cpu):
    """Colour as the real keyframes' (synth.jpeg_quality 75, exposure changes, colour 20 ms after depth): the
    synthetic cabinet's pair 24 → 23 aligned jointly from the identity ends about 42 mm off with the whole colour
    weight at the finest level, and about 18 mm with the defaults, which read the frame's JPEG blocks and weigh
    the finest level by icp.color_finest_scale; clean colour keeps the whole weight (docs/PHOTOMETRIC.md, real
    colour)."""
    real_like = dict(jpeg_quality=75, exposure=0.035, color_offset_ms=20.0)
    whole, _ = _synthetic_pair_error(1.0, 24, **real_like)
    default, blockiness = _synthetic_pair_error(ICPConfig().color_finest_scale, 24, **real_like)
    assert blockiness > JPEG_BLOCKINESS and whole > 0.03 and default < 0.025, (blockiness, whole, default)
    from ti_fusion.config import SynthConfig
    from ti_fusion.kernels.pyramid import grey_image, jpeg_blockiness
    from ti_fusion.synthetic.scene import SyntheticSequence

    clean = SyntheticSequence(SynthConfig(scene="cabinet", frames=29)).frame(23)[1]
    assert jpeg_blockiness(grey_image(clean)) < CLEAN_BLOCKINESS  # clean colour: the whole weight
