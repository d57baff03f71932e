"""Loop closure in the run: poses and map corrected by anchor, the summary's counts, the log's loop edges;
end to end on a short out-and-back path through the synthetic room (320×240) whose return is closed onto
its start."""

from types import SimpleNamespace

import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.geometry import make_pose, se3_exp
from ti_fusion.io.datasets.arrays import FrameList
from ti_fusion.io.mcap_log import LOOP_REFUSED_TOPIC, LOOP_TOPIC, loop_edges_from_msg, read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.io.trajectory import read_tum
from ti_fusion.loop.closure import LoopClosure, candidate_gap
from ti_fusion.slam.dense import DenseSLAM
from ti_fusion.slam.pipeline import SLAMPipeline
from ti_fusion.slam.poses import PoseStore
from tests.conftest import _use
from tests.loop.scenes import sequence, view


def test_corrections_move_each_pose_with_its_keyframe():
    """Frames anchored to keyframe k (it and the frames after it) move by C_k; the store moves its own
    copies, never an array it was given, and gives the current poses by frame."""
    store = PoseStore()
    poses = [np.eye(4) for _ in range(5)]
    for i, k in enumerate((None, None, 1, None, 2)):  # keyframe 1 at frame 2, keyframe 2 at frame 4
        store.append(poses[i], frame=10 + i)
        if k is not None:
            store.start_keyframe(k)
    store.append(None, frame=15)  # a frame without a pose stays without one
    assert store.anchors == [0, 0, 1, 1, 2, 2]
    C = np.stack([np.eye(4), make_pose(np.eye(3), [0.1, 0, 0]),
                  make_pose(se3_exp(np.r_[0, 0.1, 0, 0, 0, 0])[:3, :3], [0, 0.2, 0])])
    assert store.correct(C) == 5
    assert all(np.array_equal(p, np.eye(4)) for p in poses)  # the caller's arrays are untouched
    current = store.by_frame()
    assert sorted(current) == [10, 11, 12, 13, 14]
    for i, k in enumerate((0, 0, 1, 1, 2)):
        assert np.allclose(current[10 + i], C[k]) and np.allclose(store.pose_of(10 + i), C[k])
    current[10][0, 3] = 5.0  # a copy: the store is not changed through it
    assert store.pose_of(10)[0, 3] == 0.0 and store.pose_of(15) is None


@pytest.mark.slow
def test_a_correction_reaches_the_poses_results_and_map(cpu):
    """What DenseSLAM does with loop closure's report: start_keyframe anchors the poses and the surfels fused
    after it; apply_corrections moves the trajectory (DenseSLAM.poses), the pose re-localisation starts from and the surfels; the
    results keep the poses as registered."""
    seq = sequence()
    cfg = Config()
    cfg.slam.loop_closure = False  # the keyframes are the test's
    slam = DenseSLAM(cfg, seq.intrinsics)
    results = [slam.register_frame(view(seq, seq.poses[0], 0, seed=1))]
    slam.start_keyframe(0)
    results.append(slam.register_frame(view(seq, seq.poses[2], 1, seed=2)))
    slam.start_keyframe(1)
    results.append(slam.register_frame(view(seq, seq.poses[4], 2, seed=3)))  # its surfels: anchor 1
    assert slam.poses.anchors == [0, 1, 1] and all(r.tracked for r in results)
    before = slam.mapper.map.to_numpy(("position", "anchor"))
    C = np.stack([np.eye(4), make_pose(np.eye(3), [0.0, 0.0, 0.05])])  # keyframe 1 moves 5 cm
    kept = [r.pose.copy() for r in results]
    slam.apply_corrections(C)
    current = slam.poses.by_frame()
    assert np.allclose(current[0], kept[0])
    assert all(np.allclose(current[r.index], C[1] @ k, atol=1e-9) for r, k in zip(results[1:], kept[1:]))
    assert all(np.array_equal(r.pose, k) for r, k in zip(results, kept))  # as registered
    assert np.allclose(slam.last_good[1], current[2])
    after = slam.mapper.map.to_numpy(("position", "anchor"))
    moved = before["anchor"] == 1
    assert moved.any() and not moved.all()
    assert np.array_equal(after["anchor"], before["anchor"])
    np.testing.assert_allclose(after["position"][~moved], before["position"][~moved])
    np.testing.assert_allclose(after["position"][moved], before["position"][moved] + [0, 0, 0.05], atol=1e-5)


def test_edges_are_green_only_for_loops_applied():
    """A candidate verification accepted but the pose graph refused (a look-alike place) is drawn as not
    applied, like one verification rejected: green in trajectory.png and /loop_closures means the map moved."""
    loop = LoopClosure(Config())
    loop.keyframes = [SimpleNamespace(centre=np.array([k, 0.0, 0.0])) for k in range(4)]
    loop.candidates = [SimpleNamespace(match=0, query=3, verified=True),
                       SimpleNamespace(match=1, query=3, verified=True),
                       SimpleNamespace(match=2, query=3, verified=False)]
    loop.applied = [(0, 3)]
    loop.refused = [(1, 3, "an outlier of the robust kernel")]
    edges = loop.edges()
    assert [e[2] for e in edges] == [True, False, False]
    assert np.array_equal(edges[0][0], [0.0, 0.0, 0.0]) and np.array_equal(edges[0][1], [3.0, 0.0, 0.0])


def test_a_loop_the_poses_already_agree_with_moves_nothing():
    """A verified loop within loop.min_loop_error of the current poses stays in the graph and moves nothing
    (solving would only add the loop's own measurement error); one further off is applied."""
    loop = LoopClosure(Config())
    poses = [make_pose(np.eye(3), [0.1 * k, 0.0, 0.0]) for k in range(6)]
    loop.keyframes = [SimpleNamespace(pose=T.copy()) for T in poses]
    for T in poses:
        loop.graph.add_keyframe(T)
    # c.T: keyframe 0's camera coordinates into keyframe 5's, 3 mm off (a few tenths of the loop's sigma)
    agrees = SimpleNamespace(match=0, query=5, free=[],
                             T=np.linalg.inv(poses[5]) @ poses[0] @ se3_exp(np.r_[0, 0, 0, 0.003, 0, 0]))
    report = SimpleNamespace(ms={}, outcome="", applied=None, corrections=None)
    loop._close(agrees, report)
    assert report.outcome.startswith("kept in the graph") and loop.kept == [(0, 5)] and report.corrections is None
    assert loop.summary()["loops_kept"] == 1 and loop.summary()["loops_applied"] == 0
    far = SimpleNamespace(match=1, query=5, T=np.linalg.inv(poses[5]) @ poses[1] @ se3_exp(np.r_[0, 0, 0, 0.05, 0, 0]),
                          free=[])
    loop._close(far, report)
    assert report.outcome == "applied" and loop.applied == [(1, 5)] and report.corrections.shape == (6, 4, 4)


def test_a_sessions_first_keyframe_tries_the_maps_keyframes_near_it_densely():
    """When ORB verifies none of its candidates, the keyframe tied to the map tries the map's keyframes within
    DENSE_TIE_M / DENSE_TIE_DEG of it by the estimates, nearest first, at most DENSE_TRIES, not those of its tie's
    own visit, and stops at the first verified; the candidates are recorded with the reason."""
    from ti_fusion.loop.closure import DENSE_TIE_DEG, DENSE_TIE_M, DENSE_TRIES
    from ti_fusion.loop.verification import LoopCandidate

    loop = LoopClosure(Config())
    here = make_pose(np.eye(3), [0.0, 0.0, 0.0])
    turned = make_pose(se3_exp(np.r_[0, np.radians(DENSE_TIE_DEG + 5), 0, 0, 0, 0])[:3, :3], [0.0, 0.0, 0.0])
    shifts = [0.02, 0.25, 0.05, 0.1, DENSE_TIE_M + 0.05, None, 0.15]  # None: turned away, at the same spot
    loop.keyframes = [SimpleNamespace(id=k, frame=10 * k,
                                      pose=turned if d is None else make_pose(np.eye(3), [d, 0, 0]))
                      for k, d in enumerate(shifts)]
    loop.session_start = len(shifts)
    kf = SimpleNamespace(id=len(shifts), frame=9999, pose=here)
    tried = []

    def verify_dense(query, match, init, source, target, verified=()):
        tried.append(match.id)
        np.testing.assert_allclose(init, np.linalg.inv(query.pose) @ match.pose)
        c = LoopCandidate(query.id, match.id, 0.0)
        c.verified, c.reason = match.id in verified, "stub"
        return c

    loop.verifier = SimpleNamespace(verify_dense=verify_dense)
    report = SimpleNamespace(candidates=[])
    maps = SimpleNamespace(scratch=None, frame=None)
    assert loop._dense_tie(kf, {0}, report, maps) is None  # keyframe 0: the tie's own visit
    assert tried == [2, 3, 6][:DENSE_TRIES] and len(report.candidates) == len(tried) == len(loop.candidates)
    tried.clear()
    loop.verifier = SimpleNamespace(verify_dense=lambda *a: verify_dense(*a, verified=(3,)))
    assert loop._dense_tie(kf, set(), report, maps).match == 3 and tried == [0, 2, 3]


def test_a_loop_candidate_is_older_than_the_active_window():
    """Tracking aligns to the active window's surfels already, so a loop to a keyframe inside it repeats
    odometry with the loop's own error added (the loop scene driven backwards, seed 11: one such loop, frames
    1196 and 1259, took the ATE from 2.01 to 2.49 cm); with the whole map tracked, the loop's own gap."""
    cfg = Config()
    cfg.loop.min_frame_gap, cfg.slam.active_window = 60, 200
    assert candidate_gap(cfg) == 200
    assert LoopClosure(cfg).database.config.min_frame_gap == 200
    cfg.slam.active_window = 30
    assert candidate_gap(cfg) == 60
    cfg.slam.active_window = 0
    assert candidate_gap(cfg) == 60


def _out_and_back():
    """Frames along the room's path and back again (other noise on the way back): 30 frames."""
    seq = sequence()
    path = list(range(0, 60, 4))
    indices = path + path[::-1]
    return [view(seq, seq.poses[i], k, seed=1000 + k) for k, i in enumerate(indices)]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    _use("cpu")
    cfg = Config()
    cfg.log.progress = False
    cfg.slam.loop_closure = True
    cfg.loop.keyframe_translation = 0.1
    cfg.loop.min_frame_gap = 15
    cfg.slam.active_window = 15  # shorter than the run: the return finds the start outside the window
    cfg.loop.odometry_from_icp = True  # the odometry edges' covariances from ICP's AᵀA (constant: test_pose_graph)
    cfg.loop.min_loop_error = 0.0  # apply the loop however well tracking agrees with it: the correction is tested
    out = tmp_path_factory.mktemp("loop") / "run"
    frames = FrameList(_out_and_back(), name="out-and-back")
    pipeline = SLAMPipeline(frames, cfg, RunDir("slam", out), None, show_progress=False)
    summary = pipeline.run()
    return SimpleNamespace(summary=summary, out=out, pipeline=pipeline)


@pytest.mark.slow
def test_the_return_is_closed_onto_the_start(run):
    s = run.summary
    assert s["keyframes"] >= 4
    assert s["loop_candidates"] >= 1 and s["loops_applied"] >= 1
    assert s["loops"][0]["frames"][1] >= 15  # on the way back
    assert s["tracking_failures"] == 0
    assert s["ate_rmse_m"] < 0.01  # the correction did not disturb a well-tracked path
    for name in ("detect", "verify", "optimise", "correct"):
        assert s["loop_ms"][name]["calls"] >= 1, name
    assert all({"query", "match", "verified", "reason"} <= set(c) for c in s["loop_candidates_log"])
    odometry = [e for e in run.pipeline.step.slam.loop.graph.edges if not e.loop]
    assert odometry and all(e.covariance is not None and np.all(np.linalg.eigvalsh(e.covariance) > 0)
                            for e in odometry)


def test_the_corrected_trajectory_is_written(run):
    """trajectory.tum holds the poses as loop closure corrected them, not as they were tracked (and logged as
    /camera/pose at their frame): the frames before the closed loop moved."""
    stamps, written = read_tum(run.out / "trajectory.tum")
    store = run.pipeline.step.slam.poses
    np.testing.assert_allclose(written, np.stack([p for p in store if p is not None]), atol=1e-6)
    logged = read_log(run.out / "log.mcap").est_poses
    shift = np.linalg.norm(written[:, :3, 3] - logged[:, :3, 3], axis=1)
    assert shift.max() > 1e-4, "no pose moved with the loop's correction"
    # the log ends with the trajectory as written: /trajectory, corrections included
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with open(run.out / "log.mcap", "rb") as f:
        ends = [m for _, _, _, m in make_reader(f, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages(topics=["/trajectory"])]
    assert len(ends) == 1 and len(ends[0].poses) == len(written)
    centres = np.array([[p.position.x, p.position.y, p.position.z] for p in ends[0].poses])
    np.testing.assert_allclose(centres, written[:, :3, 3], atol=1e-9)
    # the results and the keyframes took the corrections too
    results = [r.pose for r in run.pipeline.results if r.pose is not None]
    np.testing.assert_allclose(np.stack(results), written, atol=1e-6)
    for kf in run.pipeline.step.slam.loop.keyframes:
        np.testing.assert_allclose(kf.pose, store.pose_of(kf.frame), atol=1e-9)


def test_surfels_carry_keyframe_anchors(run):
    anchors = run.pipeline.step.slam.mapper.anchors()
    assert anchors.min() >= 0 and anchors.max() < run.summary["keyframes"]
    assert len(np.unique(anchors)) > 1


def test_loop_stats_and_edges_in_the_log(run):
    log = read_log(run.out / "log.mcap")
    loops = [m["loop"] for m in log.stats if "loop" in m]
    assert len(loops) == run.summary["keyframes"]
    assert any(entry["applied"] for entry in loops)
    assert all("loop" in m["ms"] for m in log.stats)
    assert log.channels[LOOP_TOPIC].count >= 1
    # the loops applied on /loop_closures, the candidates not applied on the topic the layout hides
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    last = {}
    with open(run.out / "log.mcap", "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=[LOOP_TOPIC, LOOP_REFUSED_TOPIC]):
            last[channel.topic] = loop_edges_from_msg(msg)
    edges = run.pipeline.step.loop_edges()
    assert len(last[LOOP_TOPIC]) == sum(e[2] for e in edges) >= 1 and all(e[2] for e in last[LOOP_TOPIC])
    assert len(last[LOOP_REFUSED_TOPIC]) == sum(not e[2] for e in edges)
    assert not any(e[2] for e in last[LOOP_REFUSED_TOPIC])


def test_summary_counts_without_loop_closure(run):
    step = run.pipeline.step
    loop, step.slam.loop = step.slam.loop, None
    try:
        assert step.loop_summary() == {"keyframes": 0, "loop_candidates": 0, "loops_applied": 0}
    finally:
        step.slam.loop = loop


def test_config_defaults():
    cfg = Config()
    assert isinstance(cfg.slam.loop_closure, bool)
    assert cfg.loop.robust == "gnc"
    assert cfg.loop.min_pnp_inliers >= 6
