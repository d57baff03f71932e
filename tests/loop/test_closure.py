"""Loop closure in the run: poses and map corrected by anchor, the summary's counts, the log's loop edges;
end to end on a short out-and-back path through the synthetic room (320×240) whose return is closed onto
its start."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.geometry import make_pose, se3_exp
from ti_fusion.io.datasets.arrays import FrameList
from ti_fusion.io.mcap_log import read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.loop.closure import LoopClosure
from ti_fusion.slam.pipeline import SLAMPipeline
from tests.conftest import _use
from tests.loop.scenes import sequence, view


class _FakeMapper:
    anchor = 0

    def __init__(self):
        self.calls = []

    def apply_corrections(self, corrections):
        self.calls.append(np.array(corrections))
        return len(corrections)


def test_corrections_move_each_pose_with_its_keyframe():
    """Frames anchored to keyframe k (it and the frames after it) move by C_k, each pose once, in place."""
    slam = SimpleNamespace(mapper=_FakeMapper())
    loop = LoopClosure(Config(), slam)
    poses = [np.eye(4) for _ in range(5)]
    loop._posed = [(poses[0], 0), (poses[1], 0), (poses[2], 1), (poses[3], 1), (poses[3], 1), (poses[4], 2)]
    C = np.stack([np.eye(4), make_pose(np.eye(3), [0.1, 0, 0]),
                  make_pose(se3_exp(np.r_[0, 0.1, 0, 0, 0, 0])[:3, :3], [0, 0.2, 0])])
    kept = [p for p in poses]
    loop._apply(C)
    assert all(p is q for p, q in zip(poses, kept))  # in place: slam.poses and the run's results see it
    for p, k in zip(poses, (0, 0, 1, 1, 2)):
        assert np.allclose(p, C[k])
    assert len(slam.mapper.calls) == 1 and np.allclose(slam.mapper.calls[0], C)


def test_edges_are_green_only_for_loops_applied():
    """A candidate verification accepted but the pose graph refused (a look-alike place) is drawn as not
    applied, like one verification rejected: green in trajectory.png and /loop_closures means the map moved."""
    loop = LoopClosure(Config(), SimpleNamespace(mapper=_FakeMapper()))
    loop.keyframes = [SimpleNamespace(centre=np.array([k, 0.0, 0.0])) for k in range(4)]
    loop.candidates = [SimpleNamespace(match=0, query=3, accepted=True),
                       SimpleNamespace(match=1, query=3, accepted=True),
                       SimpleNamespace(match=2, query=3, accepted=False)]
    loop.closures = [(0, 3)]
    loop.refused = [(1, 3, "an outlier of the robust kernel")]
    edges = loop.edges()
    assert [e[2] for e in edges] == [True, False, False]
    assert np.array_equal(edges[0][0], [0.0, 0.0, 0.0]) and np.array_equal(edges[0][1], [3.0, 0.0, 0.0])


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
    cfg.loop.odometry_from_icp = True  # the odometry edges' covariances from ICP's AᵀA (the constant ones: test_pose_graph)
    out = tmp_path_factory.mktemp("loop") / "run"
    frames = FrameList(_out_and_back(), name="out-and-back")
    pipeline = SLAMPipeline(frames, cfg, RunDir("slam", out), None, show_progress=False)
    summary = pipeline.run()
    return SimpleNamespace(summary=summary, out=out, pipeline=pipeline)


def test_the_return_is_closed_onto_the_start(run):
    s = run.summary
    assert s["keyframes"] >= 4
    assert s["loop_candidates"] >= 1 and s["loop_closures"] >= 1
    assert s["loops"][0]["frames"][1] >= 15  # on the way back
    assert s["tracking_failures"] == 0
    assert s["ate_rmse_m"] < 0.01  # the correction did not disturb a well-tracked path
    for name in ("detect", "verify", "optimise", "correct"):
        assert s["loop_ms"][name]["calls"] >= 1, name
    assert all({"query", "match", "accepted", "reason"} <= set(c) for c in s["loop_candidates_log"])
    odometry = [e for e in run.pipeline.step.loop.graph.edges if not e.loop]
    assert odometry and all(e.covariance is not None and np.all(np.linalg.eigvalsh(e.covariance) > 0)
                            for e in odometry)


def test_surfels_carry_keyframe_anchors(run):
    anchors = run.pipeline.step.slam.mapper.anchors()
    assert anchors.min() >= 0 and anchors.max() < run.summary["keyframes"]
    assert len(np.unique(anchors)) > 1


def test_loop_stats_and_edges_in_the_log(run):
    log = read_log(run.out / "log.mcap")
    loops = [m["loop"] for m in log.stats if "loop" in m]
    assert len(loops) == run.summary["keyframes"]
    assert any(entry["closed"] for entry in loops)
    assert all("loop" in m["ms"] for m in log.stats)
    assert log.channels["/loop_closures"].count >= 1


def test_summary_counts_without_loop_closure(run):
    step = run.pipeline.step
    loop, step.loop = step.loop, None
    try:
        assert step.loop_summary() == {"keyframes": 0, "loop_candidates": 0, "loop_closures": 0}
    finally:
        step.loop = loop


def test_config_defaults():
    cfg = Config()
    assert isinstance(cfg.slam.loop_closure, bool)
    assert cfg.loop.robust == "gnc"
    assert cfg.loop.min_pnp_inliers >= 6
