"""The keyframe pose graph (GTSAM): a known loop corrects a drifted chain; a false loop edge is an outlier
of the robust kernel and leaves the trajectory as odometry had it."""

import numpy as np
import pytest

from ti_fusion.config import LoopConfig
from ti_fusion.geometry import invert, se3_exp
from ti_fusion.loop.pose_graph import ODOMETRY_MAX_SCALE, PoseGraph, adjoint, edge_covariance, frame_covariance

K = 40  # keyframes around a circle of 2 m radius


def _truth(k: int) -> np.ndarray:
    a = 2 * np.pi * k / K
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [2 * np.sin(a), 0, 2 * np.cos(a)]
    return T


def _drifted(rng) -> tuple[list, list]:
    """Ground truth and a chain whose every step has a bias (drift) and noise."""
    truth = [_truth(k) for k in range(K)]
    chain = [truth[0]]
    for k in range(1, K):
        error = se3_exp(np.r_[0.0, 0.006, 0.0, 0.006, 0.0, 0.0] + rng.normal(0, 1e-3, 6))
        chain.append(chain[-1] @ invert(truth[k - 1]) @ truth[k] @ error)
    return truth, chain


def _worst(poses, truth) -> float:
    return max(float(np.linalg.norm(p[:3, 3] - t[:3, 3])) for p, t in zip(poses, truth))


def _graph(chain, config=None) -> PoseGraph:
    graph = PoseGraph(config or LoopConfig())
    for pose in chain:
        graph.add_keyframe(pose)
    return graph


def test_true_loop_corrects_a_drifted_chain(rng):
    truth, chain = _drifted(rng)
    graph = _graph(chain)
    graph.add_loop(0, K - 1, invert(truth[0]) @ truth[K - 1])
    out = graph.optimise()
    before, after = _worst(chain, truth), _worst(out.poses, truth)
    assert before > 0.3  # the chain has drifted by decimetres
    assert after < before / 3
    assert out.outliers == []
    assert out.loop_errors[(0, K - 1)] < LoopConfig().max_loop_error
    assert np.allclose(out.poses[0], chain[0], atol=1e-6)  # the first keyframe holds the map's frame


def test_false_loop_is_an_outlier_and_leaves_the_trajectory_intact(rng):
    truth, chain = _drifted(rng)
    graph = _graph(chain)
    graph.add_loop(5, 25, np.eye(4))  # claims keyframe 25 (across the circle) is where keyframe 5 is
    out = graph.optimise()
    assert out.outliers == [(5, 25)]
    assert max(float(np.linalg.norm(p[:3, 3] - c[:3, 3])) for p, c in zip(out.poses, chain)) < 0.01


def test_false_loop_beside_a_true_one(rng):
    truth, chain = _drifted(rng)
    graph = _graph(chain)
    graph.add_loop(0, K - 1, invert(truth[0]) @ truth[K - 1])
    graph.add_loop(5, 25, np.eye(4))
    out = graph.optimise()
    assert out.outliers == [(5, 25)]
    assert _worst(out.poses, truth) < _worst(chain, truth) / 3


def test_without_a_robust_kernel_the_false_loop_wrecks_the_map(rng):
    """Why the kernel is there: least squares pulls the chain onto the false loop."""
    truth, chain = _drifted(rng)
    graph = _graph(chain, LoopConfig(robust="none"))
    graph.add_loop(5, 25, np.eye(4))
    out = graph.optimise()
    assert _worst(out.poses, truth) > 1.0


@pytest.mark.parametrize("robust", ["cauchy", "huber"])
def test_plain_kernels_run(rng, robust):
    truth, chain = _drifted(rng)
    graph = _graph(chain, LoopConfig(robust=robust))
    graph.add_loop(0, K - 1, invert(truth[0]) @ truth[K - 1])
    out = graph.optimise()
    assert out.poses.shape == (K, 4, 4) and np.isfinite(out.poses).all()
    assert out.error_after <= out.error_before


def test_adjoint_moves_a_twist_between_frames(rng):
    T = se3_exp(rng.normal(0, 0.5, 6))
    xi = rng.normal(0, 0.1, 6)
    assert np.allclose(T @ se3_exp(xi) @ invert(T), se3_exp(adjoint(T) @ xi), atol=1e-9)


def _corridor_chain(slide: float):
    """Keyframes every 0.25 m along world x (the corridor), the camera turned to look across it (camera z =
    world y) so the corridor axis is the camera's x; odometry right except the middle edge, which slid by
    ``slide`` metres along the corridor."""
    look = np.eye(4)
    look[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    truth = []
    for k in range(11):
        T = look.copy()
        T[0, 3] = 0.25 * k
        truth.append(T)
    chain = [truth[0]]
    for k in range(1, 11):
        step = invert(truth[k - 1]) @ truth[k]
        if k == 6:
            step = step @ se3_exp(np.r_[0, 0, 0, slide, 0, 0])
        chain.append(chain[-1] @ step)
    return truth, chain


def test_weak_direction_of_an_odometry_edge_takes_the_loop_correction():
    """A corridor chain whose middle edge slid along the corridor axis, where its frames' AᵀA is weak:
    with edge covariances from ICP's information the loop puts the correction on that edge and the other
    keyframes stay right; with the constant sigmas it is spread over every edge."""
    truth, chain = _corridor_chain(0.1)
    AtA_strong = np.eye(6) * 1e4
    AtA_weak = np.diag([1e4, 1e4, 1e4, 1e-2, 1e4, 1e4])  # camera x (the corridor) unobserved
    config = LoopConfig(odometry_from_icp=True)
    errors = {}
    for informed in (False, True):
        graph = PoseGraph(config)
        for k, pose in enumerate(chain):
            frames = [(pose, frame_covariance(AtA_weak if k == 6 else AtA_strong, config))]
            graph.add_keyframe(pose, edge_covariance(frames, pose) if informed and k else None)
        graph.add_loop(0, 10, invert(truth[0]) @ truth[10])
        out = graph.optimise()
        assert out.outliers == []
        errors[informed] = _worst(out.poses, truth)
    assert _worst(chain, truth) > 0.08
    assert errors[False] > 0.03  # spread: keyframe 5 is off by about half the slide
    assert errors[True] < 0.01


def test_frame_covariance_is_the_constant_sigmas_where_observed_and_large_where_not():
    config = LoopConfig()
    D2 = np.diag([np.radians(config.odometry_sigma_deg)] * 3 + [config.odometry_sigma_m] * 3) ** 2
    strong = np.linalg.inv(D2) * 1e3  # every direction observed equally well (in the sigmas' units)
    assert np.allclose(frame_covariance(strong, config), D2)
    strong[3, 3] = 0.0
    weak = frame_covariance(strong, config)
    assert np.isclose(weak[3, 3], ODOMETRY_MAX_SCALE * config.odometry_sigma_m ** 2)
    assert np.allclose(frame_covariance(None, config), D2 * ODOMETRY_MAX_SCALE)


def test_relative_edges_place_two_opposite_slides_that_one_loop_sees_as_their_net(rng):
    """loop.keyframe_pnp: a corridor chain whose edges 3 and 7 slid +10 cm and −6 cm along the corridor (the
    depth-only loop scene's two legs), where ICP's information is weak on both: one loop sees only the net
    4 cm and splits it; relative edges from another sensor (here the truth with 5 mm / 0.2° noise, as PnP
    would give) tell which edges slid."""
    look = np.eye(4)
    look[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    truth = [look @ se3_exp(np.r_[0, 0, 0, 0.25 * k, 0, 0]) for k in range(11)]
    chain = [truth[0]]
    for k in range(1, 11):
        step = invert(truth[k - 1]) @ truth[k]
        slide = {3: 0.10, 7: -0.06}.get(k, 0.0)
        chain.append(chain[-1] @ step @ se3_exp(np.r_[0, 0, 0, slide, 0, 0]))
    config = LoopConfig(odometry_from_icp=True)
    AtA_weak = np.diag([1e4, 1e4, 1e4, 1e-2, 1e4, 1e4])  # camera x (the corridor) unobserved
    errors = {}
    for relative in (False, True):
        graph = PoseGraph(config)
        for k, pose in enumerate(chain):
            frames = [(pose, frame_covariance(AtA_weak, config))]
            graph.add_keyframe(pose, edge_covariance(frames, pose) if k else None)
        if relative:
            for k in range(1, 11):
                noise = np.r_[rng.normal(0, np.radians(0.2), 3), rng.normal(0, 0.005, 3)]
                graph.add_relative(k - 1, k, invert(truth[k - 1]) @ truth[k] @ se3_exp(noise))
        graph.add_loop(0, 10, invert(truth[0]) @ truth[10])
        out = graph.optimise()
        assert out.outliers == []
        errors[relative] = _worst(out.poses, truth)
    assert _worst(chain, truth) > 0.09
    assert errors[False] > 0.08  # the loop's 4 cm spread over both: keyframes 3–6 stay 8.8 cm off
    assert errors[True] < 0.045  # 0.7–2.4 cm over five seeds


def test_a_loop_leaves_the_directions_its_measurement_does_not_fix_to_odometry():
    """A straight pass along a plain wall, exact odometry, and a loop whose relative pose is 5 cm off along
    the wall, as verification's depth-only ICP leaves it (it slides there freely): with that direction free,
    the graph keeps odometry's, without, the loop pulls the chain by centimetres."""
    truth = []
    for k in range(10):
        T = np.eye(4)
        T[0, 3] = 0.1 * k
        truth.append(T)
    measured = invert(truth[0]) @ truth[9] @ se3_exp(np.r_[0.0, 0.0, 0.0, 0.05, 0.0, 0.0])
    along_the_wall = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    graph = _graph(truth)
    graph.add_loop(0, 9, measured, free=[along_the_wall])
    free = graph.optimise()
    assert _worst(free.poses, truth) < 1e-3
    assert free.outliers == [] and free.loop_errors[(0, 9)] < 0.1  # 5 cm against a free sigma of 1 m
    graph = _graph(truth)
    graph.add_loop(0, 9, measured)
    fixed = graph.optimise()
    assert fixed.outliers == [] and _worst(fixed.poses, truth) > 0.01
