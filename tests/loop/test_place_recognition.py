"""Place recognition and verification on rendered views of the synthetic room (320×240): the same place
seen on two passes is found and verified with the right relative pose; other places, and a view of the same
place whose geometry is wrong, are rejected with a reason."""

import dataclasses

import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.geometry import invert, pose_error
from ti_fusion.loop.place_recognition import FIRST_VOCABULARY, PlaceDatabase, k_majority, pairwise_distances, precheck
from ti_fusion.loop.verification import LoopVerifier
from tests.conftest import _use
from tests.loop.scenes import HEIGHT, WIDTH, keyframe, moved, sequence, view

# Two passes of one place (5 cm and 4 degrees apart, their own sensor noise), and three other places.
POSES = {"first": (0, (0, 0, 0)), "far": (180, (0, 0, 0)), "left": (90, (0, 0, 0)), "right": (-90, (0, 0, 0)),
         "again": (4, (0.05, 0.0, -0.03))}


@pytest.fixture(scope="module")
def views():
    _use("cpu")
    seq = sequence()
    out = {}
    for i, (name, (yaw, shift)) in enumerate(POSES.items()):
        pose = moved(seq.poses[0], yaw, shift)
        out[name] = (pose, keyframe(i, view(seq, pose, 100 * i, seed=i), pose))
    return out


def _database(views, names, config=None):
    config = config or Config().loop
    db = PlaceDatabase(dataclasses.replace(config, min_frame_gap=1, min_score=0.0, candidates=len(names)))
    for k, name in enumerate(names):
        kf = dataclasses.replace(views[name][1], id=k)
        db.add(kf)
    return db


def test_same_place_from_two_passes_is_found(views):
    names = ["first", "far", "left", "right"]
    db = _database(views, names)
    assert len(names) >= FIRST_VOCABULARY and db.vocabulary is not None  # scored by the bag of words
    places = db.query(views["again"][1])
    assert names[places[0].keyframe] == "first"
    assert places[0].score > Config().loop.min_score
    assert all(p.score < 0.5 * places[0].score for p in places[1:])


def test_before_the_vocabulary_keyframes_are_compared_by_votes(views):
    db = _database(views, ["far", "first"])
    assert db.vocabulary is None
    places = db.query(views["again"][1])
    assert places[0].keyframe == 1 and places[0].score > 3 * places[1].score


def test_precheck_passes_the_same_place_and_not_another(views):
    cfg = Config()
    first, again, far = views["first"][1], views["again"][1], views["far"][1]
    assert precheck(first, again, cfg.vo, cfg.loop.consistent_m) >= 3 * cfg.loop.min_consistent
    assert precheck(far, again, cfg.vo, cfg.loop.consistent_m) < cfg.loop.min_consistent


def test_k_majority_words_are_members_majorities(rng):
    base = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    # four clusters: each member differs from its centre in a few bits
    members = np.repeat(base, 50, axis=0)
    flips = rng.integers(0, 8, (len(members), 32)) == 0
    noisy = members ^ (flips * rng.integers(1, 256, (len(members), 32))).astype(np.uint8)
    words = k_majority(noisy, 32, 5, rng)  # more words than clusters: every cluster gets a start
    for centre in base:
        bits = np.unpackbits(words ^ centre, axis=1).sum(axis=1)
        assert bits.min() <= 16  # some word lies near each centre (random members differ by ~128 bits)


@pytest.fixture(scope="module")
def verifier():
    _use("cpu")
    from ti_fusion.kernels.pyramid import FramePyramid

    cfg = Config()
    cfg.icp.iterations = [10]  # one level: one ICP kernel to compile for these maps, not three (the test's cost)
    return LoopVerifier(cfg), FramePyramid(cfg.pyramid, HEIGHT, WIDTH, 1), FramePyramid(cfg.pyramid, HEIGHT, WIDTH, 1)


@pytest.mark.slow
def test_verification_accepts_the_same_place_with_its_relative_pose(views, verifier):
    ver, source, target = verifier
    (pose_a, first), (pose_b, again) = views["first"], views["again"]
    c = ver.verify(again, first, 0.5, source, target)
    assert c.verified, c.reason
    truth = invert(pose_b) @ pose_a  # p_again = T p_first
    rot_deg, trans_m = pose_error(c.T, truth)
    assert rot_deg < 1.0 and trans_m < 0.02
    assert c.record()["reason"] == "verified"


def test_verification_rejects_another_place(views, verifier):
    ver, source, target = verifier
    c = ver.verify(views["again"][1], views["far"][1], 0.5, source, target)
    assert not c.verified and c.reason.startswith("pre-check")


def test_verification_rejects_a_look_alike_with_the_wrong_geometry(views, verifier):
    """The same image with depth 25% too far: appearance says yes, 3D distances and ICP say no."""
    ver, source, target = verifier
    first = views["first"][1]
    wrong = dataclasses.replace(first, depth=first.depth * 1.25,
                                features=dataclasses.replace(first.features, points=first.features.points * 1.25))
    c = ver.verify(views["again"][1], wrong, 0.5, source, target)
    assert not c.verified and c.reason


# -- dense verification from the estimated poses (a session's tie to keyframes ORB cannot match) -----------------
@pytest.fixture(scope="module")
def dense_verifier():
    """The run's own ICP (every pyramid level): how far off a start it converges from is what is tested."""
    _use("cpu")
    from ti_fusion.kernels.pyramid import FramePyramid

    cfg = Config()
    levels = len(cfg.icp.iterations)
    return LoopVerifier(cfg), FramePyramid(cfg.pyramid, HEIGHT, WIDTH, levels), FramePyramid(cfg.pyramid, HEIGHT,
                                                                                            WIDTH, levels)


def _off(T: np.ndarray, yaw_deg: float, shift) -> np.ndarray:
    """``T`` (p_query = T p_match) as estimates that drifted by ``yaw_deg`` and ``shift`` (metres) would give it."""
    return moved(np.eye(4), yaw_deg, shift) @ T


@pytest.mark.slow
def test_dense_verification_takes_the_same_place_from_drifted_estimates(views, dense_verifier):
    ver, source, target = dense_verifier
    (pose_a, first), (pose_b, again) = views["first"], views["again"]
    truth = invert(pose_b) @ pose_a
    fill_target(target, again)
    c = ver.verify_dense(again, first, _off(truth, 3.0, (0.05, -0.02, 0.04)), source, target)
    assert c.verified, c.reason
    rot_deg, trans_m = pose_error(c.T, truth)
    assert rot_deg < 1.0 and trans_m < 0.02
    assert c.reason == "verified (dense, from the estimated poses)" and c.score == 0.0 and not c.free


@pytest.mark.slow
@pytest.mark.parametrize("other", ["far", "left"])
def test_dense_verification_refuses_another_place_the_estimates_put_near(views, dense_verifier, other):
    """The estimates say the two keyframes are 6 cm apart; the match saw another wall of the room."""
    ver, source, target = dense_verifier
    (pose_a, first), (pose_b, again) = views["first"], views["again"]
    fill_target(target, again)
    c = ver.verify_dense(again, views[other][1], invert(pose_b) @ pose_a, source, target)
    assert not c.verified and c.reason.startswith("dense: ICP"), c.reason


@pytest.mark.slow
def test_dense_verification_refuses_a_look_alike_with_the_wrong_geometry(views, dense_verifier):
    ver, source, target = dense_verifier
    (pose_a, first), (pose_b, again) = views["first"], views["again"]
    wrong = dataclasses.replace(first, depth=first.depth * 1.25)
    fill_target(target, again)
    c = ver.verify_dense(again, wrong, invert(pose_b) @ pose_a, source, target)
    assert not c.verified and c.reason.startswith("dense: ICP"), c.reason


@pytest.mark.slow
def test_dense_verification_refuses_estimates_further_off_than_icp_may_move_them(views, dense_verifier):
    """The right place, but the estimates 25 cm off (more than loop.max_icp_change_m): not taken on ICP's word."""
    ver, source, target = dense_verifier
    (pose_a, first), (pose_b, again) = views["first"], views["again"]
    fill_target(target, again)
    c = ver.verify_dense(again, first, _off(invert(pose_b) @ pose_a, 0.0, (0.25, 0.0, 0.0)), source, target)
    assert not c.verified and c.reason.startswith("dense: ICP"), c.reason


@pytest.mark.slow
def test_dense_verification_refuses_a_corridor_where_the_estimates_would_be_the_measurement(dense_verifier):
    """Down a corridor of plain walls two places 20 cm apart look the same to depth: ICP from the estimates (which
    say they are one place) stays where it starts, with an inlier ratio, residual and even weak-direction test
    that pass; from starts around the estimate it ends as far apart as they are, so it is refused."""
    from ti_fusion.config import SynthConfig
    from ti_fusion.synthetic.scene import SyntheticSequence
    from ti_fusion.synthetic.scenes import CORRIDOR_Y
    from ti_fusion.synthetic.shapes import look_at

    ver, source, target = dense_verifier
    seq = SyntheticSequence(SynthConfig(scene="corridor", width=WIDTH, height=HEIGHT, fx=262.5))
    mid = 0.5 * (CORRIDOR_Y[0] + CORRIDOR_Y[1])
    poses = [look_at(np.array([x, mid, 1.5]), np.array([x + 3.0, mid, 1.4]), 0.0) for x in (-3.0, -2.8)]
    a, b = (keyframe(i, view(seq, p, i, seed=i), p) for i, p in enumerate(poses))
    fill_target(target, b)
    c = ver.verify_dense(b, a, np.eye(4), source, target)
    assert not c.verified and c.reason.endswith("the place does not fix the pose"), c.reason
    assert c.icp_inlier_ratio >= Config().loop.min_inlier_ratio  # the single ICP alone would have passed


def fill_target(target, keyframe) -> None:
    """The query keyframe's maps, as the SLAM loop hands over the frame's (verify_dense's target is ready)."""
    from ti_fusion.loop.verification import fill

    fill(target, keyframe)


@pytest.mark.parametrize("n", [2, 3, 7, 8, 33, 300])
def test_pairwise_distances_are_numpys_norm(n):
    """The same sums as NumPy's norm over the axis of three; compared to within 2 ulps, not bit for bit, since
    how NumPy orders a reduction is its own (the bits are checked where they matter: whole runs' outputs)."""
    rng = np.random.default_rng(n)
    for scale in (1e-3, 1.0, 1e8):
        p = rng.normal(size=(n, 3)) * scale * 10.0 ** rng.uniform(-3, 3, size=(n, 1))
        p[0] = (scale * 1e8, 0.5, 0.5)  # where the order of the three squares' sum shows
        expected = np.linalg.norm(p[:, None] - p[None], axis=2)
        np.testing.assert_array_max_ulp(pairwise_distances(p), expected, maxulp=2)
        p32 = p.astype(np.float32)
        got32 = pairwise_distances(p32)
        assert got32.dtype == np.float32
        np.testing.assert_array_max_ulp(got32, np.linalg.norm(p32[:, None] - p32[None], axis=2), maxulp=2)
