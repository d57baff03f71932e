"""Place recognition and verification on rendered views of the synthetic room (320×240): the same place
seen on two passes is found and verified with the right relative pose; other places, and a view of the same
place whose geometry is wrong, are rejected with a reason."""

import dataclasses

import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.geometry import invert, pose_error
from ti_fusion.loop.place_recognition import FIRST_VOCABULARY, PlaceDatabase, k_majority, precheck
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
