"""A saved map: written and read back exactly (saved, loaded and saved again: the same bytes), every bad input
one line (truncated, corrupted, another format version, a run folder without a map, another camera), and a
DenseSLAM run saved, loaded into a fresh one and compared array by array."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.map_files import DATA, HEADER, VERSION, find_map_folder, map_folder, write_map_folder
from ti_fusion.io.outputs import RunDir
from ti_fusion.loop.keyframes import Keyframe, grid_points
from ti_fusion.loop.pose_graph import Edge
from ti_fusion.slam.saved_map import MapTrajectory, PlaceState, SavedMap, check_camera, load_map
from ti_fusion.tracking.features import FrameFeatures

K = Intrinsics(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


def _keyframe(i: int, rng, n: int) -> Keyframe:
    keypoints = tuple(cv2.KeyPoint(float(x), float(y), 31.0, float(a), float(r), int(o), -1)
                      for x, y, a, r, o in zip(rng.uniform(0, 320, n), rng.uniform(0, 240, n), rng.uniform(0, 360, n),
                                               rng.uniform(0, 1e-3, n), rng.integers(0, 8, n)))
    pixels = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    points = rng.normal(size=(n, 3))
    points[::3] = np.nan  # keypoints without depth
    features = FrameFeatures(keypoints, rng.integers(0, 256, (n, 32), dtype=np.uint8) if n else None, pixels, points) \
        if n else FrameFeatures((), None, np.zeros((0, 2)), np.zeros((0, 3)))
    depth = rng.uniform(0.5, 3.0, (240, 320)).astype(np.float32)
    depth[:10] = 0
    pose = np.eye(4)
    pose[:3, 3] = rng.normal(size=3)
    return Keyframe(i, 5 * i, 0.2 * i + 1e-7, pose, features, K, depth, K, grid_points(depth, K))


def small_map(rng, surfels: int = 500) -> SavedMap:
    """A map made by hand (no Taichi): random surfels, three keyframes (one without features), a vocabulary,
    a pose graph with an odometry, a PnP and a loop edge."""
    s = {"position": rng.normal(size=(surfels, 3)).astype(np.float32),
         "normal": rng.normal(size=(surfels, 3)).astype(np.float32),
         "color": rng.uniform(0, 255, (surfels, 3)).astype(np.float32),
         "weight": rng.uniform(0, 10, surfels).astype(np.float32),
         "radius": rng.uniform(0, 0.01, surfels).astype(np.float32),
         "t_created": rng.integers(0, 40, surfels, dtype=np.int32),
         "t_updated": rng.integers(0, 40, surfels, dtype=np.int32),
         "anchor": rng.integers(0, 3, surfels, dtype=np.int32)}
    kfs = [_keyframe(0, rng, 40), _keyframe(1, rng, 0), _keyframe(2, rng, 25)]
    generator = np.random.default_rng(7)
    generator.random(3)
    places = PlaceState(rng.integers(0, 256, (16, 32), dtype=np.uint8), rng.integers(0, 5, (3, 16)).astype(np.float32),
                        1, generator.bit_generator.state)
    edges = [Edge(0, 1, np.eye(4), False), Edge(1, 2, np.eye(4), False, np.diag(rng.uniform(1, 2, 6)), robust=True),
             Edge(0, 2, kfs[2].pose, True, np.diag(rng.uniform(1, 2, 6)))]
    config = Config()
    config.fusion.capacity = 1000
    # two sessions' frames: the first's anchored to keyframes 0 and 1, the second's to 2, one in the world frame
    relative = np.tile(np.eye(4), (6, 1, 1))
    relative[:, :3, 3] = rng.normal(size=(6, 3))
    trajectory = MapTrajectory(np.array([0, 0, 0, 1, 1, 1], np.int32), np.array([0, 1, 5, 0, 1, 2], np.int32),
                               np.array([1e-7, 0.2, 1.0, 10.0, 10.2, 10.4]), np.array([0, 0, 1, 2, 2, -1], np.int32),
                               relative, sessions=2)
    return SavedMap(K, 1, config.to_dict(), s, 40, 2, 39, kfs, places, [kf.pose for kf in kfs], edges,
                    {"applied": [[0, 2]], "refused": [[1, 2, "an outlier of the robust kernel"]], "kept": []},
                    trajectory)


def _same(a: SavedMap, b: SavedMap) -> None:
    """Every header field and array of the two maps equal (NaN where NaN)."""
    (ha, aa), (hb, ab) = a.to_arrays(), b.to_arrays()
    assert ha == hb
    assert list(aa) == list(ab)
    for name in aa:
        assert aa[name].dtype == ab[name].dtype and aa[name].shape == ab[name].shape, name
        np.testing.assert_array_equal(aa[name], ab[name], err_msg=name)


# --------------------------------------------------------------------------------------------------
# The files (no Taichi)
# --------------------------------------------------------------------------------------------------
def test_saved_loaded_and_saved_again_is_the_same_bytes(tmp_path, rng):
    saved = small_map(rng)
    saved.write(tmp_path / "a")
    loaded = load_map(tmp_path / "a")
    _same(saved, loaded)
    loaded.write(tmp_path / "b")
    for name in (HEADER, DATA):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    kf = loaded.keyframes[0]
    assert isinstance(kf.features.keypoints[0], cv2.KeyPoint) and len(kf.features) == 40
    assert loaded.keyframes[1].features.descriptors is None
    np.testing.assert_array_equal(kf.samples, saved.keyframes[0].samples)
    assert loaded.places.rng == saved.places.rng
    assert loaded.make_config().fusion.capacity == 1000
    header = json.loads((tmp_path / "a" / HEADER).read_text())
    assert header["version"] == VERSION == 2 and header["surfels"] == 500 and header["camera"]["width"] == 320
    assert header["trajectory"] == {"frames": 6, "sessions": 2}


def test_loading_reads_each_array_once_into_its_own_memory(tmp_path, rng):
    """A load holds the map once: each array read straight into its own (no buffer of the whole file beside
    copies of it: the peak was twice the map), and the SavedMap takes them as they are."""
    import tracemalloc

    small_map(rng, surfels=200_000).write(tmp_path / "a")
    size = (tmp_path / "a" / DATA).stat().st_size
    tracemalloc.start()
    try:
        loaded = load_map(tmp_path / "a")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert size > 8e6 and peak < 1.25 * size, (peak, size)
    assert all(a.base is None for a in loaded.surfels.values())  # each its own array, not a view of another's
    assert loaded.keyframes[2].depth.base is not None  # a keyframe's depth: a view of the loaded stack, not a copy


def test_the_map_trajectory_moves_with_its_keyframes(tmp_path, rng):
    saved = load_map(small_map(rng).write(tmp_path / "m"))
    stamps, poses = saved.trajectory_poses()
    t = saved.trajectory
    np.testing.assert_array_equal(stamps, t.timestamp)
    np.testing.assert_allclose(poses[2], saved.keyframes[1].pose @ t.relative[2], atol=1e-12)
    np.testing.assert_array_equal(poses[5], t.relative[5])  # anchor -1: in the world frame
    C = np.eye(4)
    C[:3, 3] = (0.1, -0.2, 0.3)
    saved.keyframes[2].pose = C @ saved.keyframes[2].pose  # a loop moved keyframe 2 by C
    moved = saved.trajectory_poses()[1]
    np.testing.assert_allclose(moved[3:5], C @ poses[3:5], atol=1e-12)
    np.testing.assert_array_equal(moved[[0, 1, 2, 5]], poses[[0, 1, 2, 5]])
    # the next session's frames go on after these, relative to the keyframes they were anchored to
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    after = saved.trajectory.then([(7, 20.0, pose, 1), (8, 20.2, pose, 9)], saved.keyframes)
    assert after.sessions == 3 and list(after.session[-2:]) == [2, 2] and list(after.anchor[-2:]) == [1, -1]
    np.testing.assert_allclose(after.poses(saved.keyframes)[-2:], [pose, pose], atol=1e-12)
    assert saved.trajectory.then([], saved.keyframes) is saved.trajectory  # a session without poses adds nothing


def _as_version_1(folder) -> None:
    """The map in ``folder`` rewritten as format version 1 wrote it: no trajectory."""
    saved = load_map(folder)
    header, arrays = saved.to_arrays()
    del header["trajectory"]
    arrays = {name: a for name, a in arrays.items() if not name.startswith("trajectory/")}
    write_map_folder(folder, header, arrays)
    full = json.loads((folder / HEADER).read_text())
    full["version"] = 1
    (folder / HEADER).write_text(json.dumps(full, indent=1) + "\n")


def test_a_version_1_map_loads_without_a_trajectory_and_saves_as_version_2(tmp_path, rng):
    saved = small_map(rng)
    folder = saved.write(tmp_path / "v1")
    _as_version_1(folder)
    loaded = load_map(folder)
    assert loaded.version == 1 and len(loaded.trajectory) == 0 and loaded.trajectory.sessions == 1
    saved.trajectory = MapTrajectory.empty(sessions=1)
    _same(saved, loaded)
    loaded.write(tmp_path / "v2")
    header = json.loads((tmp_path / "v2" / HEADER).read_text())
    assert header["version"] == 2 and header["trajectory"] == {"frames": 0, "sessions": 1}
    # its next session's frames are session 1
    assert loaded.trajectory.then([(0, 5.0, np.eye(4), 0)], loaded.keyframes).session.tolist() == [1]

def test_a_map_is_found_from_its_folder_its_header_or_its_run(tmp_path, rng):
    small_map(rng).write(tmp_path / "run" / "map")
    for given in (tmp_path / "run", tmp_path / "run" / "map", tmp_path / "run" / "map" / HEADER):
        assert map_folder(given) == find_map_folder(given) == tmp_path / "run" / "map"
        assert load_map(given).count == 500
    # what is no saved map: None from the lookup that ti-fusion mesh and inspect make, one line from map_folder
    (tmp_path / "run" / "notes.txt").write_text("mine")
    for given in (tmp_path, tmp_path / "run" / "notes.txt", tmp_path / "missing", tmp_path / "run" / "map" / DATA):
        assert find_map_folder(given) is None
        with pytest.raises(InputError):
            map_folder(given)


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_a_truncated_map_is_refused(tmp_path, rng):
    folder = small_map(rng).write(tmp_path / "m")
    data = (folder / DATA).read_bytes()
    (folder / DATA).write_bytes(data[:len(data) // 2])
    with pytest.raises(InputError, match="map.bin: is truncated") as exc:
        load_map(folder)
    _one_line(exc)
    (folder / HEADER).write_text((folder / HEADER).read_text()[:200])
    with pytest.raises(InputError, match="map.json: is damaged or truncated: not JSON"):
        load_map(folder)
    (folder / DATA).unlink()
    (folder / HEADER).unlink()
    with pytest.raises(InputError, match="holds no saved map"):
        load_map(folder)


def test_a_corrupted_map_fails_its_checksum(tmp_path, rng):
    folder = small_map(rng).write(tmp_path / "m")
    data = bytearray((folder / DATA).read_bytes())
    header = json.loads((folder / HEADER).read_text())
    at = header["arrays"]["surfels/weight"]["offset"] + 17
    data[at] ^= 0x40
    (folder / DATA).write_bytes(bytes(data))
    with pytest.raises(InputError, match="map.bin: is corrupted: array 'surfels/weight' fails its checksum") as exc:
        load_map(folder)
    _one_line(exc)


def test_another_format_version_is_refused(tmp_path, rng):
    folder = small_map(rng).write(tmp_path / "m")
    header = json.loads((folder / HEADER).read_text())
    header["version"] = VERSION + 1
    (folder / HEADER).write_text(json.dumps(header))
    with pytest.raises(InputError, match=f"format version {VERSION + 1}; this ti-fusion reads versions 1 and 2 "
                                         "\\(a newer ti-fusion wrote it\\)") as exc:
        load_map(folder)
    _one_line(exc)
    for version in (0, "2", True, None):
        header["version"] = version
        (folder / HEADER).write_text(json.dumps(header))
        with pytest.raises(InputError, match=f"format version {version!r}; this ti-fusion reads versions 1 and 2$"):
            load_map(folder)
    header["format"] = "something else"
    (folder / HEADER).write_text(json.dumps(header))
    with pytest.raises(InputError, match="is not a ti-fusion saved map"):
        load_map(folder)


def test_a_run_folder_without_a_saved_map_is_refused(tmp_path):
    with RunDir("slam", tmp_path / "run") as out:
        out.file("trajectory.tum").write_text("")
    with pytest.raises(InputError, match="a ti-fusion run folder without a saved map") as exc:
        load_map(tmp_path / "run")
    _one_line(exc)
    with pytest.raises(InputError, match="no such file or folder"):
        load_map(tmp_path / "nowhere")


def test_a_map_of_another_camera_is_refused_naming_both(rng):
    saved = small_map(rng)
    check_camera(saved, K)  # its own camera
    half = K.downsampled(2)
    with pytest.raises(InputError, match=r"run/map: a map of camera fx=262.5 fy=262.5 cx=159.5 cy=119.5 at 320x240; "
                                         r"the frames are of camera fx=131.25 fy=131.25 cx=79.75 cy=59.75 at "
                                         r"160x120") as exc:
        check_camera(saved, half, "run/map")
    _one_line(exc)
    other = Intrinsics(fx=525.0, fy=525.0, cx=159.5, cy=119.5, width=320, height=240)
    with pytest.raises(InputError, match="fx=525 fy=525"):
        check_camera(saved, other)
    config = Config()
    config.fusion.level = 0
    with pytest.raises(InputError, match="a map fused at pyramid level 1; fusion.level = 0"):
        check_camera(saved, K, config=config)


# --------------------------------------------------------------------------------------------------
# DenseSLAM: map_state, save_map, from_map
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """DenseSLAM over the loop tests' out-and-back path (keyframes, a vocabulary, a loop applied), saved."""
    from tests.conftest import _use
    from tests.loop.test_closure import _out_and_back

    from ti_fusion.slam.dense import DenseSLAM

    _use("cpu")
    cfg = Config()
    cfg.loop.keyframe_translation = 0.1
    cfg.loop.min_frame_gap = 15
    cfg.slam.active_window = 15
    cfg.loop.odometry_from_icp = True
    cfg.loop.min_loop_error = 0.0
    frames = _out_and_back()
    slam = DenseSLAM(cfg, frames[0].intrinsics)
    for frame in frames:
        slam.register_frame(frame)
    folder = slam.save_map(tmp_path_factory.mktemp("mapped") / "map")
    return slam, folder


@pytest.mark.slow
def test_a_run_saved_and_loaded_into_a_fresh_slam_is_the_same_map(mapped, tmp_path):
    from ti_fusion.slam.dense import DenseSLAM

    slam, folder = mapped
    state = slam.map_state()
    assert state.count == slam.surfels > 0 and len(state.keyframes) >= 4 and state.places.vocabulary is not None
    assert state.loops["applied"] and any(e.loop for e in state.graph_edges)
    # the trajectory: every posed frame, relative to its keyframe, at the poses the run's loops left
    posed = slam.poses.posed()
    assert len(state.trajectory) == len(posed) and state.trajectory.sessions == 1
    np.testing.assert_allclose(state.trajectory_poses()[1], [p for _, _, p, _ in posed], atol=1e-9)
    np.testing.assert_allclose(slam.map_trajectory()[1], state.trajectory_poses()[1], atol=1e-12)
    loaded = DenseSLAM.from_map(folder)
    _same(state, loaded.map_state())
    assert loaded.surfels == slam.surfels and loaded.loaded_map.count == 0 and loaded.loaded_map.keyframes
    # the surfels set aside are arrays of their own: nothing holds the loaded surfels once they are in the fields
    assert all(a.base is None for a in loaded.loaded_map.surfels.values())
    loaded.save_map(tmp_path / "again")
    for name in (HEADER, DATA):
        assert (folder / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name
    # what the next frame tracks against: the map rendered at the last pose, the same pixels
    pose = slam.poses[-1]
    for by_normal in (False, True):
        np.testing.assert_array_equal(slam.mapper.render_image(pose, slam.model_intrinsics, by_normal),
                                      loaded.mapper.render_image(pose, slam.model_intrinsics, by_normal))
    # loop closure off in the loaded run: its keyframes are kept for the next save
    config = loaded.map_state().make_config()
    config.slam.loop_closure = False
    without = DenseSLAM.from_map(folder, config=config)
    assert without.loop is None
    kept = without.map_state()
    assert len(kept.keyframes) == len(state.keyframes) and kept.places.trainings == state.places.trainings


@pytest.mark.slow
def test_a_map_loaded_for_another_camera_is_refused(mapped):
    from ti_fusion.slam.dense import DenseSLAM

    slam, folder = mapped
    with pytest.raises(InputError, match="a map of camera .* at 320x240; the frames are of camera .* at 160x120"):
        DenseSLAM.from_map(folder, intrinsics=slam.intrinsics.downsampled(2))


# --------------------------------------------------------------------------------------------------
# ti-fusion inspect and mesh read a saved map
# --------------------------------------------------------------------------------------------------
def test_inspect_says_what_a_saved_map_holds(tmp_path, rng, capsys):
    from ti_fusion.cli.main import main

    saved = small_map(rng)
    folder = saved.write(tmp_path / "m")
    assert main(["inspect", str(folder), "--out", str(tmp_path / "i")]) == 0
    out = capsys.readouterr().out
    assert f"saved map: {folder} (format version {VERSION}" in out and "every checksum verified" in out
    assert "surfels   500 (" in out and "keyframes 3, 40 frames fused (the last frame 39), 1 loops applied" in out
    assert "trajectory 6 posed frames of 2 session(s)" in out
    summary = json.loads((tmp_path / "i" / "summary.json").read_text())["saved_map"]
    assert summary["surfels"] == 500 and summary["confirmed_surfels"] == int((saved.surfels["weight"] >= 3).sum())
    assert main(["inspect", str(folder / HEADER)]) == 0
    assert main(["inspect", str(folder), "--plot"]) == 2
    assert "--plot draws a log's stats: this holds a saved map and no log.mcap" in capsys.readouterr().err
    data = bytearray((folder / DATA).read_bytes())
    data[100] ^= 1
    (folder / DATA).write_bytes(bytes(data))
    assert main(["inspect", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ti-fusion inspect: error: {folder / DATA}: is corrupted: array") and "\n" not in err
    # a header that parses but lacks a field: one line from inspect and from mesh, as from a session
    folder = saved.write(tmp_path / "n")
    header = json.loads((folder / HEADER).read_text())
    del header["camera"]
    (folder / HEADER).write_text(json.dumps(header))
    assert main(["inspect", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ti-fusion inspect: error: {folder}") and "\n" not in err, err
    from ti_fusion.cli.mesh import saved_surfels  # what `ti-fusion mesh` reads (the command would restart Taichi)

    with pytest.raises(InputError, match="camera"):
        saved_surfels(folder / HEADER)


@pytest.mark.slow
def test_mesh_of_a_saved_map_is_the_mesh_of_its_map_ply(mapped, tmp_path):
    from ti_fusion.cli.main import main

    slam, folder = mapped
    slam.mapper.export_ply(tmp_path / "map.ply")
    assert main(["mesh", str(folder), "--out", str(tmp_path / "from_map"), "--quiet"]) == 0
    assert main(["mesh", str(tmp_path / "map.ply"), "--out", str(tmp_path / "from_ply"), "--quiet"]) == 0
    a, b = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("from_map", "from_ply"))
    assert a["triangles"] == b["triangles"] > 0 and a["surfels_meshed"] == b["surfels_meshed"]
    assert a["map"] == str(folder / HEADER)
