"""The scene catalogue (``ti_fusion.synthetic.scenes``): every scene renders valid, textured frames that lie
on its true surfaces, every path stays in free space and is smooth, the loop returns to its start, the
twins look alike, ``--trajectory`` renders any TUM file (and refuses a bad one in one line), and the room
is what it was. Small images (80×60) and a few frames per scene.
"""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.geometry import rigidity_error, rotation_angle_deg
from ti_fusion.synthetic import scenes
from ti_fusion.synthetic.scene import (FPS, T0, SyntheticSequence, camera_path, default_scene, look_at,
                                       read_trajectory)
from ti_fusion.synthetic.scenes import SCENES

from .test_scene import backproject_world

TINY = SynthConfig(width=80, height=60, fx=65.625)
NEW = ("loop", "twins", "wall", "corridor", "jerky", "cabinet")
TEXTURED = ("loop", "twins", "wall", "corridor", "jerky")
# least valid-depth fraction (noise on) of any sampled view: the loop and the corridor look down
# corridors whose far part lies beyond the sensor's 4 m, as the cabinet's views do at the room's far corners
MIN_VALID = {"room": 0.85, "loop": 0.45, "twins": 0.45, "wall": 0.95, "corridor": 0.45, "jerky": 0.85,
             "cabinet": 0.6}


def sampled(n: int, k: int = 6) -> list[int]:
    return [int(i) for i in np.linspace(0, n - 1, k)]


@pytest.fixture(scope="module")
def paths():
    """Each scene's default poses (computed once)."""
    return {name: spec.path(spec.times(spec.frames)) for name, spec in SCENES.items()}


@pytest.mark.slow
@pytest.mark.parametrize("name", NEW)
def test_scene_renders_valid_textured_depth_on_its_surfaces(cpu, name):
    seq = SyntheticSequence(replace(TINY, scene=name))
    assert len(seq) == SCENES[name].frames
    ideal = SyntheticSequence(replace(TINY, scene=name, noise=False))
    for i in sampled(len(seq)):
        depth, color = seq.frame(i)
        assert depth.dtype == np.float32 and color.dtype == np.uint8 and color.shape == (60, 80, 3)
        valid = depth > 0
        assert valid.mean() >= MIN_VALID[name], (i, valid.mean())
        assert np.all(depth[valid] >= seq.cfg.min_range) and np.all(depth[valid] <= seq.cfg.max_range * 1.05)
        # texture everywhere: photometric gradients and corners for ORB
        grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY).astype(np.float64)
        assert grey.std() > 4, (i, grey.std())
        # exact geometry: ideal depth back-projects onto the scene's true surfaces
        d0, _ = ideal.frame(i)
        points, _ = backproject_world(d0, ideal.intrinsics, ideal.poses[i])
        assert len(points) > 0.4 * d0.size
        assert np.abs(ideal.surface_distance(points)).max() < 2e-3


@pytest.mark.parametrize("name", TEXTURED)
def test_orb_finds_keypoints_along_the_path(cpu, name):
    """ORB (the re-localiser's and place recognition's features) finds corners in every sampled view."""
    seq = SyntheticSequence(replace(TINY, scene=name, width=320, height=240, fx=262.5))
    orb = cv2.ORB_create(1000)
    counts = [len(orb.detect(cv2.cvtColor(seq.frame(i)[1], cv2.COLOR_RGB2GRAY), None)) for i in sampled(len(seq), 5)]
    assert min(counts) >= 100 and np.median(counts) >= 300, counts


@pytest.mark.parametrize("name", list(SCENES))
def test_path_is_rigid_smooth_and_stays_in_free_space(name, paths):
    spec = SCENES[name]
    poses = paths[name]
    assert poses.shape == (spec.frames, 4, 4)
    assert all(rigidity_error(T) is None for T in poses[::25])
    dt = np.diff(spec.times(spec.frames))
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / dt
    turns = np.array([rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) for a, b in zip(poses[:-1], poses[1:])]) / dt
    assert steps.max() < 1.2 and turns.max() < 120  # m/s, deg/s: walking, hand-held
    assert np.all(steps > 0.01)  # always moving
    # never inside a primitive nor on the back of a plane, never within 0.4 m of a surface
    scene = spec.build()
    from ti_fusion.synthetic.scene import _signed_distance

    signed = np.stack([_signed_distance(p, poses[:, :3, 3]) for p in scene.primitives], axis=1)
    assert signed.min() > 0.4


@pytest.mark.parametrize("name", NEW)
def test_the_camera_never_faces_a_surface_nearer_than_the_sensor_sees(cpu, name, paths):
    """At most a few per cent of any view (ideal depth, 32×24) nearer than min_range, over the whole path."""
    seq = SyntheticSequence(replace(TINY, scene=name, width=32, height=24, fx=26.25, noise=False))
    near = []
    for T in paths[name][::40]:
        depth, _ = seq.render(T)
        near.append(np.mean((depth > 0) & (depth < seq.cfg.min_range)))
    assert max(near) < 0.05


def test_loop_goes_round_once_and_back_over_its_first_views(paths):
    poses = paths["loop"]
    length = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    assert length > scenes.LOOP_LENGTH + 2.0  # once round the 30 m centre line and on past the start
    # it walks round the block: the direction from the centre turns by a full turn, counter-clockwise
    rel = poses[:, :2, 3] - scenes.LOOP_CENTER
    turned = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    assert turned[-1] - turned[0] > 2 * np.pi
    # the last 3 m stand and look as the first 2.5 m did
    start = poses[: int(2.5 / scenes.LOOP_SPEED * FPS)]
    tail = poses[-int(3.5 / scenes.LOOP_SPEED * FPS):]
    for T in start[::10]:
        dist = np.linalg.norm(tail[:, :3, 3] - T[:3, 3], axis=1)
        j = int(np.argmin(dist))
        assert dist[j] < 0.05 and rotation_angle_deg(T[:3, :3].T @ tail[j, :3, :3]) < 5.0
    # every corridor is walked: the centre line passes through each of the four
    x, y = rel[:, 0], rel[:, 1]
    for inside in (y < -2, y > 2, x < -4, x > 4):
        assert inside.sum() > 100


def test_twin_sections_look_the_same_from_half_a_turn_round(cpu):
    """A view of the south twin section and the same view turned half a turn about the centre (the north
    one) render the same depth and colour; the plain loop's two views differ."""
    c = np.array([*scenes.LOOP_CENTER, 0.0])
    half_turn = np.diag([-1.0, -1.0, 1.0])
    seq = SyntheticSequence(replace(TINY, scene="twins", noise=False))
    loop = SyntheticSequence(replace(TINY, scene="loop", noise=False))
    for position, target in (((0.3, -3.1, 1.5), (-0.4, -4.0, 1.0)), ((-0.5, -3.2, 1.4), (0.3, -2.0, 1.1))):
        a = look_at(c + position, c + np.array(target), roll=0.05)
        b = a.copy()
        b[:3, :3] = half_turn @ a[:3, :3]
        b[:3, 3] = c + half_turn @ (a[:3, 3] - c)
        da, ca = seq.render(a)
        db, cb = seq.render(b)
        assert (da > 0).all() and np.abs(da - db).max() < 1e-3
        assert np.mean(np.abs(ca.astype(int) - cb.astype(int)) <= 2) > 0.99
        la, lb = loop.render(a)[1], loop.render(b)[1]
        assert np.mean(np.abs(la.astype(int) - lb.astype(int)) <= 2) < 0.5


def test_the_walk_passes_the_north_twin_as_it_passed_the_south_one(paths):
    """Half a lap on, the walker stands and looks as before turned half a turn about the centre."""
    poses = paths["twins"]
    c = np.array([*scenes.LOOP_CENTER, 0.0])
    half_turn = np.diag([-1.0, -1.0, 1.0])
    rel = poses[:, :2, 3] - scenes.LOOP_CENTER
    south = np.flatnonzero((np.abs(rel[:, 0]) < 1.5) & (rel[:, 1] < -2) & (np.arange(len(poses)) < 700))
    north = np.flatnonzero((np.abs(rel[:, 0]) < 2.0) & (rel[:, 1] > 2))
    assert len(south) > 60 and len(north) > 60
    for i in south[::10]:
        position = c + half_turn @ (poses[i, :3, 3] - c)
        dist = np.linalg.norm(poses[north, :3, 3] - position, axis=1)
        j = north[np.argmin(dist)]
        assert dist.min() < 0.05
        assert rotation_angle_deg((half_turn @ poses[i, :3, :3]).T @ poses[j, :3, :3]) < 5.0


def test_room_is_unchanged(cpu):
    seq = SyntheticSequence(TINY)
    assert TINY.scene == "room" and TINY.frames == 0 and len(seq) == 120
    np.testing.assert_array_equal(seq.timestamps, T0 + np.arange(120) / FPS)
    np.testing.assert_allclose(seq.poses, camera_path(np.arange(120) / FPS), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(seq.scene.table(), default_scene().table())
    assert len(SyntheticSequence(replace(TINY, frames=7))) == 7


def test_frames_beyond_the_default_go_on_along_the_path(paths):
    seq = SyntheticSequence(replace(TINY, scene="loop", frames=2 * SCENES["loop"].frames))
    np.testing.assert_allclose(seq.poses[: len(paths["loop"])], paths["loop"], atol=1e-12)
    assert np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1).sum() > 2 * scenes.LOOP_LENGTH


def test_trajectory_file_round_trip(cpu, tmp_path):
    """The room's path written as TUM and rendered from the file: the same frames, at the file's stamps."""
    from ti_fusion.io.trajectory import write_tum

    cfg = replace(TINY, frames=5)
    room = SyntheticSequence(cfg)
    path = write_tum(tmp_path / "room.tum", room.timestamps, room.poses)
    again = SyntheticSequence(replace(cfg, frames=0, trajectory=str(path)))
    assert len(again) == 5
    np.testing.assert_allclose(again.timestamps, room.timestamps, atol=1e-6)
    np.testing.assert_allclose(again.poses, room.poses, atol=1e-7)
    for i in range(5):
        (d0, c0), (d1, c1) = room.frame(i), again.frame(i)
        same = d0 == d1
        assert same.mean() > 0.99 and np.abs(d0 - d1)[same & (d0 > 0)].max(initial=0) == 0
        assert np.abs(d0.astype(np.float64) - d1)[(d0 > 0) & (d1 > 0)].max() < 0.05
        assert np.mean(np.abs(c0.astype(int) - c1.astype(int)) <= 1) > 0.99
    # frames cut a trajectory short; a file's poses render in any scene
    assert len(SyntheticSequence(replace(cfg, frames=3, trajectory=str(path)))) == 3
    assert len(SyntheticSequence(replace(cfg, frames=50, trajectory=str(path)))) == 5
    wall = SyntheticSequence(replace(cfg, scene="wall", trajectory=str(path)))
    np.testing.assert_allclose(wall.poses, room.poses, atol=1e-7)


BAD_TRAJECTORIES = {
    "missing": (None, "trajectory file not found"),
    "words": ("1.0 0 0 1 0 0 0 1\nthis is not a pose at all ok\n", "line 2: expected numbers"),
    "short": ("1.0 0 0 1 0 0 0 1\n2.0 0 0 1 0 0 1\n", "line 2: expected 8 values"),
    "one": ("# timestamp tx ty tz qx qy qz qw\n1.0 0 0 1 0 0 0 1\n", "only 1 pose, need at least 2"),
    "empty": ("# nothing\n", "no poses"),
    "not_rigid": ("1.0 0 0 1 0 0 0 1\n2.0 0 0 1 0 0 0 2\n", "line 2: quaternion has norm 2"),
    "backwards": ("1.0 0 0 1 0 0 0 1\n0.5 0 0 1 0 0 0 1\n", "timestamps must increase"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(BAD_TRAJECTORIES))
def test_bad_trajectory_file_is_one_line(cpu, tmp_path, capsys, case):
    from ti_fusion.cli.main import main
    from ti_fusion.errors import InputError

    text, problem = BAD_TRAJECTORIES[case]
    path = tmp_path / f"{case}.tum"
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError, match=problem):
        read_trajectory(path)
    assert main(["synth", str(tmp_path / "out"), "--trajectory", str(path), "--quiet"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and str(path) in err[0] and problem in err[0], err
    assert not (tmp_path / "out" / "rgb").exists()
    if case == "not_rigid":  # slam on the embedded sequence reads it the same way
        assert main(["slam", "--set", f"synth.trajectory={path}", "--out", str(tmp_path / "run"), "--quiet"]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and str(path) in err[0] and problem in err[0], err


@pytest.mark.slow
def test_synth_command_scene_and_trajectory(cpu, tmp_path, capsys):
    from ti_fusion.cli.main import main
    from ti_fusion.io.trajectory import read_tum

    out = tmp_path / "wall"
    assert main(["synth", str(out), "--scene", "wall", "--frames", "2", "--width", "80", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "wall" and summary["frames"] == 2 and summary["trajectory"] == ""
    stamps, poses = read_tum(out / "groundtruth.txt")
    wall = SyntheticSequence(replace(TINY, scene="wall", frames=2))
    np.testing.assert_allclose(poses, wall.poses, atol=1e-8)
    # its ground truth is a trajectory: rendered again in the corridor, at the same stamps
    again = tmp_path / "again"
    assert main(["synth", str(again), "--scene", "corridor", "--trajectory", str(out / "groundtruth.txt"),
                 "--width", "80", "--quiet"]) == 0
    stamps2, poses2 = read_tum(again / "groundtruth.txt")
    np.testing.assert_allclose(stamps2, stamps, atol=1e-6)
    np.testing.assert_allclose(poses2, poses, atol=1e-7)
    assert json.loads((again / "summary.json").read_text())["scene"] == "corridor"


def test_dataset_follows_the_scene(cpu):
    from ti_fusion.io.datasets import open_dataset

    ds = open_dataset(DatasetConfig(downsample=2, stop=4), replace(TINY, scene="corridor"))
    assert len(ds) == 4 and ds.describe()["scene"] == "corridor"
    frame = ds[3]
    assert frame.depth.shape == (30, 40)
    np.testing.assert_allclose(frame.gt_pose, SCENES["corridor"].path(np.arange(4) / FPS)[3], rtol=0, atol=1e-12)
    assert len(open_dataset(DatasetConfig(), replace(TINY, scene="loop"))) == scenes.LOOP_FRAMES


def _steps(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(metres, degrees) between consecutive poses."""
    moved = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turned = np.array([rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) for a, b in zip(poses[:-1], poses[1:])])
    return moved, turned


def _constant_velocity_misses(poses: np.ndarray) -> np.ndarray:
    """Per frame from the third: whether the constant-velocity guess is further from the truth (in
    translation) than the last pose is."""
    from ti_fusion.geometry import invert

    guess = [poses[i] @ invert(poses[i - 1]) @ poses[i] for i in range(1, len(poses) - 1)]
    cv = np.array([np.linalg.norm(g[:3, 3] - t[:3, 3]) for g, t in zip(guess, poses[2:])])
    last = np.linalg.norm(poses[2:, :3, 3] - poses[1:-1, :3, 3], axis=1)
    return cv > last


def test_jerky_frames_are_irregular_gaps_of_the_30_hz_path(cpu, paths):
    """Gaps of 0.1 to 0.7 s on the 30 Hz grid, both ends drawn; steps up to about 17 degrees and 20 cm;
    the same gaps on every run; the constant-velocity guess is worse than the last pose on some frames."""
    spec = SCENES["jerky"]
    seq = SyntheticSequence(replace(TINY, scene="jerky"))
    gaps = np.diff(seq.timestamps) * FPS
    np.testing.assert_allclose(gaps, np.round(gaps), atol=1e-9)
    gaps = np.round(gaps)
    assert gaps.min() == 3 and gaps.max() == 21 and len(np.unique(np.round(gaps))) > 10
    np.testing.assert_array_equal(seq.timestamps, T0 + spec.times(spec.frames))
    np.testing.assert_allclose(seq.poses, paths["jerky"], atol=1e-12)
    moved, turned = _steps(paths["jerky"])
    assert 14 < turned.max() < 18 and turned.mean() > 4 and 0.15 < moved.max() < 0.3
    assert 0.1 < _constant_velocity_misses(paths["jerky"]).mean() < 0.5
    # as many frames as asked, on the same gaps: a prefix of the default
    np.testing.assert_array_equal(spec.times(10), spec.times(spec.frames)[:10])


def test_cabinet_is_low_texture_at_wide_baselines(cpu, paths):
    """A frame every 0.67 s, steps of up to about 17 degrees and 27 cm round one plain box; ORB finds a small
    fraction of the keypoints it finds in the room, and the colour's gradients are mild away from edges."""
    seq = SyntheticSequence(replace(TINY, scene="cabinet", width=320, height=240, fx=262.5))
    np.testing.assert_allclose(np.diff(seq.timestamps), scenes.CABINET_STRIDE / FPS, atol=1e-12)
    moved, turned = _steps(paths["cabinet"])
    assert 12 < turned.max() < 18 and 0.2 < moved.max() < 0.3 and 0.1 < moved.mean() < 0.2
    assert _constant_velocity_misses(paths["cabinet"]).mean() > 0.1  # speed changes between frames
    room = SyntheticSequence(replace(TINY, width=320, height=240, fx=262.5))
    orb = cv2.ORB_create(1000)

    def keypoints(s, i):
        return len(orb.detect(cv2.cvtColor(s.frame(i)[1], cv2.COLOR_RGB2GRAY), None))

    for i in sampled(len(seq), 4):
        assert keypoints(seq, i) < 0.25 * keypoints(room, min(i, len(room) - 1)), i
        _, color = seq.render(seq.poses[i], noise=False)
        grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY).astype(np.float64)
        gradient = np.hypot(*np.gradient(grey))
        assert np.median(gradient) < 1.0, i  # grey levels per pixel: flat almost everywhere


def test_every_scene_is_a_choice_of_the_config_and_the_command_line():
    from typing import get_type_hints

    from ti_fusion.cli.main import build_parser
    from ti_fusion.config import OneOf

    rule = next(a for a in get_type_hints(SynthConfig, include_extras=True)["scene"].__metadata__
                if isinstance(a, OneOf))
    assert set(rule.choices) == set(SCENES)
    for name in SCENES:
        assert build_parser()[0].parse_args(["slam", "--scene", name]).scene == name
