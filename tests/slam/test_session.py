"""A session against a map (``DenseSLAM.start_session``, ti_fusion/slam/session.py): the pose unknown until a frame
finds itself among the map's keyframes (place recognition, PnP, dense verification, then tracking against the
map), no pose before that, never a start at the identity; then extending the map, or with ``localize`` tracking
against it without changing it; a session that never sees the mapped place stays unlocalised, or with
``map.unfound = map-anyway`` maps on in its own frame. The map is handed over in the process (the same
DenseSLAM), as a loaded one is. Synthetic room at 320×240."""

import numpy as np
import pytest

from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.geometry import pose_error
from ti_fusion.io.datasets import open_dataset
from ti_fusion.slam.dense import DenseSLAM
from ti_fusion.slam.slam_step import STATS_SCHEMA, SLAMStep
from ti_fusion.status import Tracking

MAPPED = 40  # frames of the room mapped before the session


def _mapped(scene: str = "room", **session):
    """A DenseSLAM that mapped the room's first frames, the config, and the frames of ``scene`` (same camera)."""
    cfg = Config()
    cfg.dataset.downsample = 2
    for key, value in session.items():
        setattr(cfg.map, key, value)
    room = open_dataset(cfg.dataset, cfg.synth)
    system = DenseSLAM(cfg, room.intrinsics)
    for i in range(MAPPED):
        system.register_frame(room[i])
    if scene == "room":
        return system, room
    cfg.synth.scene = scene
    return system, open_dataset(cfg.dataset, cfg.synth)


def _step(system: DenseSLAM) -> SLAMStep:
    step = SLAMStep.__new__(SLAMStep)  # the stats and summary of the step around this system
    step.slam, step.config, step.dataset_name = system, system.config, "room"
    return step


def test_a_session_finds_itself_in_the_map_and_extends_it(cpu, monkeypatch):
    import ti_fusion.loop.closure as closure

    system, room = _mapped()
    keyframes = len(system.loop.keyframes)
    system.start_session()
    extracted = []  # the frames whose ORB features were extracted, once each
    extract = closure.extract_features
    monkeypatch.setattr(closure, "extract_features", lambda frame, *a: extracted.append(frame.index) or extract(
        frame, *a))
    assert len(system.poses) == 0 and system.session.whole_map
    results = [system.register_frame(room[i]) for i in range(15, 21)]
    first = results[0]
    # the first frame sees mapped space: it finds itself there, in the map's frame (the room's ground truth)
    assert first.tracking is Tracking.RELOCALISED, (first.status, first.tried)
    assert first.tried[0].startswith("place: keyframe ") and first.tried[0].endswith(": verified")
    assert first.found["frame"] == 15 and first.found["unlocalised_before"] == 0
    for r, i in zip(results, range(15, 21)):
        rot, trans = pose_error(r.pose, room[i].gt_pose)
        assert r.tracked and rot < 0.5 and trans < 0.01, (i, r.status, rot, trans)
    assert sorted(system.poses.by_frame()) == list(range(15, 21))  # the session's own trajectory
    # extended: the frame that found itself is a keyframe tied to the one it matched, its surfels fused
    assert first.fusion is not None and not system.session.whole_map
    assert len(system.loop.keyframes) > keyframes and first.loop.why == "found"
    ties = [e.i for e in system.loop.graph.edges if e.j == keyframes and not e.loop]
    assert ties == [first.found["keyframe"]]  # no odometry edge from the map's last keyframe
    assert extracted.count(15) == 1  # its keyframe took the features that found it
    step = _step(system)
    stats = step.stats(first)
    assert stats["localised"] and stats["found"] == first.found and stats["status"] == "relocalised"
    assert {"localised", "found"} <= set(STATS_SCHEMA["properties"])
    assert step.stats(results[1])["localised"] and "found" not in step.stats(results[1])


def test_the_frames_after_a_small_maps_end_find_themselves(cpu):
    """A scan finished in two sessions: the frames right after the map's last one see what the map's few keyframes
    saw, but in a map of three keyframes tf-idf scores every keyframe low (a word that all of them hold weighs
    nothing), so place recognition is a shortlist there and verification decides (5 frames after the last)."""
    system, room = _mapped()
    assert len(system.loop.keyframes) <= 3
    system.start_session()
    first = system.register_frame(room[MAPPED + 5])
    assert first.tracking is Tracking.RELOCALISED, (first.status, first.tried)
    rot, trans = pose_error(first.pose, room[MAPPED + 5].gt_pose)
    assert rot < 0.5 and trans < 0.01, (rot, trans)


@pytest.mark.slow
def test_localize_tracks_against_the_map_without_changing_it(cpu):
    system, room = _mapped()
    before = {k: v.copy() for k, v in system.mapper.to_numpy().items()}
    keyframes, edges = len(system.loop.keyframes), len(system.loop.graph.edges)
    system.start_session(localize=True)
    results = [system.register_frame(room[i]) for i in range(25, 31)]
    assert results[0].tracking is Tracking.RELOCALISED, (results[0].status, results[0].tried)
    for r, i in zip(results, range(25, 31)):
        rot, trans = pose_error(r.pose, room[i].gt_pose)
        assert r.tracked and r.fusion is None and r.loop is None and trans < 0.01, (i, r.status, trans)
    after = system.mapper.to_numpy()
    assert before.keys() == after.keys() and all(np.array_equal(before[k], after[k]) for k in before)
    assert (len(system.loop.keyframes), len(system.loop.graph.edges)) == (keyframes, edges)
    assert system.session.whole_map  # nothing is fused: the whole map is rendered, not an active window
    # three frames lost in a row (no depth): off the map, it looks for itself again, then finds itself again
    blank = [room[i] for i in range(31, 35)]
    for frame in blank:
        frame.depth[:] = 0
    lost = [system.register_frame(frame) for frame in blank]
    assert [r.tracking for r in lost] == [Tracking.LOST] * 3 + [Tracking.UNLOCALISED], [r.status for r in lost]
    assert lost[3].pose is None and system.session.searches == [34]
    again = system.register_frame(room[35])
    assert again.tracking is Tracking.RELOCALISED and again.found["frame"] == 35, (again.status, again.tried)
    assert system.session.found["frame"] == 25  # the first time stays the session's event
    assert pose_error(again.pose, room[35].gt_pose)[1] < 0.01
    summary = _step(system).summary(type("Run", (), {"results": results + lost + [again]})())
    assert summary["searches_again"] == [34] and summary["unlocalised_frames"] == 1


@pytest.mark.slow
def test_a_localisation_off_the_map_is_posed_by_odometry_until_it_tracks_against_the_map_again(cpu, monkeypatch):
    """Where the map is out of view (here: its surfels hidden), a localisation poses each frame by frame-to-frame
    odometry from the last posed one, reported as such ("odometry: off the map", not localised on /slam/stats),
    instead of searching the map every frame (only every SEARCH_EVERY-th); where the map rendered at its pose
    covers the frame again, it tracks against the map again, and where odometry drifted too far for that, the
    bounded search finds it."""
    import ti_fusion.slam.session as session_module

    monkeypatch.setattr(session_module, "SEARCH_EVERY", 3)
    system, room = _mapped()
    before = {k: v.copy() for k, v in system.mapper.to_numpy().items()}
    system.start_session(localize=True)
    found = system.register_frame(room[25])
    assert found.tracking is Tracking.RELOCALISED, (found.status, found.tried)
    count = system.mapper.map.count
    system.mapper.map.count = 0  # nothing of the map in view
    off = [system.register_frame(room[i]) for i in range(26, 31)]
    for r, i in zip(off, range(26, 31)):
        assert r.tracking is Tracking.ODOMETRY and r.status.startswith("odometry: off the map"), (i, r.status, r.tried)
        assert pose_error(r.pose, room[i].gt_pose)[1] < 0.01, (i, pose_error(r.pose, room[i].gt_pose))
    # no search of the map off it but every third frame's (the 3rd by odometry): its keyframes verify, the map does not
    assert [any(t.startswith("place:") for t in r.tried) for r in off] == [False, False, True, False, False]
    assert system.session.searched_off_map == [28]
    assert off[1].tried[-1] == "map: covers 0% of the frame < 30%"  # the cheap test: no ICP against the map
    system.mapper.map.count = count  # the map in view again
    back = [system.register_frame(room[i]) for i in range(31, 34)]
    assert [r.tracking for r in back] == [Tracking.OK] * 3, [(r.status, r.tried) for r in back]
    assert all(pose_error(r.pose, room[i].gt_pose)[1] < 0.01 for r, i in zip(back, range(31, 34)))
    assert system.session.odometry == list(range(26, 31)) and system.session.back_on_map == [31]
    assert system.session.searches == [] and len(system.poses) == 9
    step = _step(system)
    assert [step.stats(r)["localised"] for r in [found, off[0], back[0]]] == [True, False, True]
    summary = step.summary(type("Run", (), {"results": [found, *off, *back]})())
    assert summary["odometry_frames"] == 5 and summary["odometry"] == [[26, 30]] and summary["back_on_map"] == [31]
    # off the map again, and odometry 1 m off: the map rendered there does not bring it back; the search does
    system.mapper.map.count = 0
    assert system.register_frame(room[34]).tracking is Tracking.ODOMETRY
    frame, pose = system.last_good
    shifted = pose.copy()
    shifted[:3, 3] += [1.0, 0.0, 0.0]
    system.last_good = (frame, shifted)
    system.mapper.map.count = count
    drifted = system.register_frame(room[35])
    assert drifted.tracking is Tracking.ODOMETRY and "map: " in drifted.tried[-1], drifted.tried
    found = system.register_frame(room[36])
    assert found.tracking is Tracking.RELOCALISED and found.found["frame"] == 36, (found.status, found.tried)
    assert pose_error(found.pose, room[36].gt_pose)[1] < 0.01
    assert system.session.searched_off_map == [28, 36] and system.session.back_on_map == [31, 36]
    after = system.mapper.to_numpy()
    assert all(np.array_equal(before[k], after[k]) for k in before)


@pytest.mark.slow
def test_a_session_that_never_sees_the_map_gets_no_pose_or_maps_in_its_own_frame(cpu):
    system, wall = _mapped("wall", find_frames=3)
    system.start_session()
    results = [system.register_frame(wall[i]) for i in range(3)]
    for r in results:  # never a silent start at the identity
        assert r.tracking is Tracking.UNLOCALISED and r.pose is None and r.status.startswith("unlocalised: "), r.status
    summary = _step(system).summary(type("Run", (), {"results": results})())
    assert summary["unlocalised_frames"] == 3 and summary["localised_at"] is None
    assert summary["tracking_failures"] == 0 and len(system.poses.by_frame()) == 0

    system, wall = _mapped("wall", find_frames=2, unfound="map-anyway")
    loaded, fields = system.surfels, system.mapper.map
    system.start_session()
    results = [system.register_frame(wall[i]) for i in range(3)]
    assert system.surfels < loaded  # the loaded map set aside: only the third frame's surfels
    results.append(system.register_frame(wall[3]))
    assert system.mapper.map is fields  # emptied in place: no second map's fields
    assert [r.tracking for r in results[:2]] == [Tracking.UNLOCALISED] * 2
    assert results[2].tracking is Tracking.INIT and results[3].tracked  # a map of its own from the third frame
    assert system.session.own_map_at == 2 and system.surfels > 0 and len(system.loop.keyframes) == 1


def test_a_map_without_keyframes_has_nothing_to_find_a_session_in(cpu):
    cfg = Config()
    cfg.dataset.downsample = 2
    room = open_dataset(cfg.dataset, cfg.synth)
    with pytest.raises(InputError, match="the map has no keyframes"):
        DenseSLAM(cfg, room.intrinsics).start_session()
    cfg.map.unfound = "map-anyway"
    with pytest.raises(InputError, match="--localize changes no map and --unfound map-anyway maps"):
        DenseSLAM(cfg, room.intrinsics).start_session(localize=True)
    cfg.slam.loop_closure = False
    with pytest.raises(InputError, match="finds itself among the map's keyframes: it needs slam.loop_closure = true"):
        DenseSLAM(cfg, room.intrinsics).start_session()


def test_a_localisation_frame_mostly_off_the_map_is_lost():
    """With localize, a frame whose correspondences cover less than ON_MAP of its depth is off the map: lost (its
    pose would rest on the little of the map it sees); extending, the same frame stays tracked."""
    from types import SimpleNamespace

    from ti_fusion.slam.dense import FrameResult
    from ti_fusion.slam.session import ON_MAP, check_on_map

    frame = SimpleNamespace(depth=np.ones((480, 640), np.float32))  # 320x240 = 76800 pixels at map level 1
    for localize, inliers in ((True, 0.2 * 76800), (False, 0.2 * 76800), (True, (ON_MAP + 0.05) * 76800)):
        slam = SimpleNamespace(session=SimpleNamespace(localize=localize), map_level=1)
        result = FrameResult(0, 0.0, np.eye(4), Tracking.OK, icp=SimpleNamespace(inliers=int(inliers)))
        check_on_map(slam, frame, result)
        assert result.lost == (localize and inliers < ON_MAP * 76800), (localize, inliers, result.status)
    slam = SimpleNamespace(session=SimpleNamespace(localize=True), map_level=1)
    result = FrameResult(0, 0.0, np.eye(4), Tracking.OK, icp=SimpleNamespace(inliers=15360))
    check_on_map(slam, frame, result)
    assert result.status == "lost: off the map: its correspondences cover 20% of the frame's depth < 30%"


def test_odometry_near_a_localisations_alignment_settles_its_weak_direction(monkeypatch):
    """A localisation's frame whose alignment against the map has a weak direction (where the slide starts would
    be tried) is settled by odometry from the last frame when the two land within SETTLED of each other; odometry
    farther off, lost, or not there (no kept maps) settles nothing, and the slide starts are tried."""
    import ti_fusion.slam.session as session_module
    from ti_fusion.geometry import se3_exp
    from ti_fusion.slam.dense import FrameResult

    alignment = se3_exp(np.array([0.1, 0.2, 0.0, 0.5, 0.0, 1.0]))
    near = alignment @ se3_exp(np.array([0.0, 0.0, 0.0, 0.002, 0.0, 0.0]))  # 2 mm off
    far = alignment @ se3_exp(np.array([0.0, 0.0, 0.0, 0.04, 0.0, 0.0]))  # one slide step off
    for moved, settles in ((FrameResult(1, 0.0, near, Tracking.ODOMETRY), True),
                           (FrameResult(1, 0.0, far, Tracking.ODOMETRY), False),
                           (FrameResult(1, 0.0, near, Tracking.LOST, "odometry: few inliers"), False), (None, False)):
        monkeypatch.setattr(session_module, "odometry", lambda slam, frame, why, moved=moved: moved)
        assert session_module.odometry_settles(None, None, alignment) is settles, (moved and moved.status)


@pytest.mark.parametrize("paired", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_kept_maps_go_into_the_model_pyramid(arch, rng, paired):
    """``KeptMaps``: the maps of the frame kept (every level the model has) are the model pyramid's after
    ``into_model``, bit for bit, though the frame pyramid was built again since; the frame's own maps are left
    as they are. In a pair (one set of fields) and in two pyramids of their own."""
    from ti_fusion.camera import Intrinsics
    from ti_fusion.config import PyramidConfig
    from ti_fusion.kernels.pyramid import FramePyramid
    from ti_fusion.slam.session import KeptMaps

    H, W = 40, 48
    K = Intrinsics(60.0, 60.0, 24.0, 20.0, W, H)
    if paired:
        frame, model = FramePyramid.pair(PyramidConfig(), (H, W, 3), (H, W, 3))
        assert model.vertex[0].field is frame.vertex[0].field
    else:
        frame, model = FramePyramid(PyramidConfig(), H, W, 3), FramePyramid(PyramidConfig(), H, W, 3)
    v, u = np.mgrid[0:H, 0:W]
    depth = lambda: (1.0 + rng.uniform(0.0, 0.5) + rng.uniform(-0.01, 0.01) * u + rng.uniform(-0.01, 0.01) * v
                     ).astype(np.float32)  # a plane at random: maps and normals differ from one to the next
    frame.compute(depth(), K)
    kept_maps = KeptMaps(frame, model)
    assert kept_maps.usable and kept_maps.shared == paired
    kept_maps.keep(7)
    kept = [(frame.vertex[l].to_numpy(), frame.normal[l].to_numpy()) for l in range(3)]
    frame.compute(depth(), K)  # the next frame
    now = [(frame.vertex[l].to_numpy(), frame.normal[l].to_numpy()) for l in range(3)]
    assert kept_maps.into_model() is model and kept_maps.index == 7
    for l in range(3):
        np.testing.assert_array_equal(model.vertex[l].to_numpy(), kept[l][0])
        np.testing.assert_array_equal(model.normal[l].to_numpy(), kept[l][1])
        np.testing.assert_array_equal(frame.vertex[l].to_numpy(), now[l][0])
        np.testing.assert_array_equal(frame.normal[l].to_numpy(), now[l][1])
