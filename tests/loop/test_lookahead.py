"""Loop closure's work beside the loop (``ti_fusion/loop/lookahead.py``): the run's end waits for it and raises a
failed addition, and a frame's look ahead equals what the loop closer computes of it itself; end to end, a run with
looks ahead gives the run without them. (The queue it runs on: tests/loop/test_in_order.py.)"""

import dataclasses
import threading

import cv2
import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.io.datasets.arrays import FrameList
from ti_fusion.io.outputs import RunDir
from ti_fusion.loop.closure import LoopClosure
from ti_fusion.loop.lookahead import look_ahead
from ti_fusion.loop.place_recognition import PlaceDatabase
from ti_fusion.loop.verification import LoopVerifier
from ti_fusion.slam.pipeline import SLAMPipeline
from tests.conftest import _use
from tests.loop.scenes import keyframe, moved, sequence, view


def test_the_summary_waits_for_the_threads_and_raises_a_failed_addition():
    """At a run's end (summary.json's loop closure fields) nothing handed to a thread is left running or lost: a
    look ahead not taken is dropped, and a database addition that failed raises there."""
    closer, gate = LoopClosure(Config()), threading.Event()
    job = closer._beside.submit(lambda: gate.wait() and "ahead", quiet=True)
    closer._ahead = 7, job
    gate.set()
    assert closer.summary()["keyframes"] == 0
    assert closer._ahead is None and job.result is None and closer._beside._jobs == []

    def fails():
        raise RuntimeError("the vocabulary")

    closer._beside.submit(fails)
    with pytest.raises(RuntimeError, match="the vocabulary"):
        closer.summary()
    assert closer._beside._jobs == []


@pytest.fixture(scope="module")
def place():
    """Five keyframes of the room in a database, and a frame of the first place seen again."""
    _use("cpu")
    seq = sequence()
    cfg = Config()
    cfg.loop = dataclasses.replace(cfg.loop, min_frame_gap=1, min_score=0.0)
    database = PlaceDatabase(cfg.loop)
    keyframes = []
    for k, yaw in enumerate((0, 180, 90, -90, 45)):
        pose = moved(seq.poses[0], yaw)
        keyframes.append(keyframe(k, view(seq, pose, 10 * k, seed=k), pose))
        database.add(keyframes[-1])
    again = view(seq, moved(seq.poses[0], 4, (0.05, 0.0, -0.03)), 100, seed=9)
    return cfg, database, keyframes, again


def test_a_look_ahead_is_what_the_loop_closer_computes_of_the_frame(place):
    cfg, database, keyframes, frame = place
    verifier = LoopVerifier(cfg)
    vo = dataclasses.replace(cfg.vo, n_features=cfg.loop.n_features)
    ahead = look_ahead(frame, len(keyframes), vo, cv2.ORB_create(cfg.loop.n_features), database, keyframes, verifier)
    kf = keyframe(len(keyframes), frame, np.eye(4), cfg.loop.n_features)  # as LoopClosure._make_keyframe makes it
    assert np.array_equal(ahead.features.descriptors, kf.features.descriptors)
    assert np.array_equal(ahead.features.points, kf.features.points, equal_nan=True)
    assert ahead.places == database.query(kf) and ahead.places[0].keyframe == 0
    for place_, check in zip(ahead.places, ahead.checks):
        own = verifier.check_features(kf, keyframes[place_.keyframe])
        assert check.consistent == own.consistent
        assert (check.pnp is None) == (own.pnp is None)
        if own.pnp is not None:
            assert check.pnp.inliers == own.pnp.inliers and np.array_equal(check.pnp.T, own.pnp.T)
    assert ahead.checks[0].pnp is not None and ahead.checks[0].pnp.inliers >= cfg.loop.min_pnp_inliers


def _slam_run(out, look_ahead_on: bool):
    """A 30-frame out-and-back run with loop closure (tests/loop/test_closure.py's), with or without looks ahead."""
    seq = sequence()
    path = list(range(0, 60, 4))
    frames = [view(seq, seq.poses[i], k, seed=1000 + k) for k, i in enumerate(path + path[::-1])]
    cfg = Config()
    cfg.log.progress = False
    cfg.loop.keyframe_translation = 0.1
    cfg.loop.min_frame_gap = 15
    cfg.slam.active_window = 15
    cfg.loop.min_loop_error = 0.0
    pipeline = SLAMPipeline(FrameList(frames, name="out-and-back"), cfg, RunDir("slam", out), None,
                            show_progress=False)
    taken = []
    loop = pipeline.step.slam.loop
    if look_ahead_on:
        take = loop._beside.take
        loop._beside.take = lambda job: taken.append(take(job)) or taken[-1]
    else:
        loop.look_ahead = lambda frame, guess: None
    summary = pipeline.run()
    return summary, (out / "trajectory.tum").read_bytes(), taken


@pytest.mark.slow
def test_a_run_with_looks_ahead_is_the_run_without_them(cpu, tmp_path):
    with_, trajectory, taken = _slam_run(tmp_path / "with", True)
    without, trajectory_without, _ = _slam_run(tmp_path / "without", False)
    assert any(a is not None for a in taken)  # the keyframes' work was done beside the frame
    assert trajectory == trajectory_without
    strip = lambda log: [{k: v for k, v in c.items() if k != "ms"} for c in log]
    assert strip(with_["loop_candidates_log"]) == strip(without["loop_candidates_log"])
    assert with_["loops"] == without["loops"] and with_["loops_applied"] >= 1
