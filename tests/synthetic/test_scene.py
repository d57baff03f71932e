"""The synthetic RGB-D renderer: ray caster against a NumPy float64 reference, geometry of the rendered
depth, camera path, sensor noise model, determinism, texture richness, dataset and ``synth`` command.

Small images (≤ 160×120) wherever the property does not depend on resolution, so the file stays fast.
"""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.geometry import invert, rigidity_error, rotation_angle_deg, so3_log
from ti_fusion.synthetic.scene import (ROOM_MAX, ROOM_MIN, Box, Cylinder, Material, Plane, Scene, Sphere,
                                 SyntheticSequence, default_scene, look_at)

SMALL = SynthConfig(frames=120, width=160, height=120, fx=131.25)


def backproject_world(depth: np.ndarray, K: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 world points of the valid pixels, their flat indices), in float64."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3], v * depth.shape[1] + u


# --------------------------------------------------------------------------------------------------
# NumPy float64 reference ray caster (noise off): depth and hit primitive per pixel
# --------------------------------------------------------------------------------------------------
def reference_cast(scene: Scene, pose: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    ray = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    length = np.linalg.norm(ray, axis=1)
    d = (ray / length[:, None]) @ pose[:3, :3].T
    o = pose[:3, 3]
    ts = np.stack([_ref_intersect(p, o, d) for p in scene.primitives], axis=1)
    label = np.argmin(ts, axis=1)
    best = ts[np.arange(len(ts)), label]
    hit = np.isfinite(best)
    depth = np.where(hit, best / length, 0.0)
    return depth.reshape(K.height, K.width), np.where(hit, label, -1).reshape(K.height, K.width)


def _ref_intersect(prim, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    t = np.full(len(d), np.inf)
    eps = 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        if isinstance(prim, Plane):
            n = np.asarray(prim.normal, float) / np.linalg.norm(prim.normal)
            denom = d @ n
            s = (np.asarray(prim.point) - o) @ n / denom
            ok = (denom < -1e-8) & (s > eps)
            t[ok] = s[ok]
        elif isinstance(prim, Box):
            c, sn = np.cos(prim.yaw), np.sin(prim.yaw)
            Rl = np.array([[c, sn, 0], [-sn, c, 0], [0, 0, 1]])
            ol = Rl @ (o - prim.center)
            dl = d @ Rl.T
            h = np.asarray(prim.half)
            t1 = (-h - ol) / dl
            t2 = (h - ol) / dl
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            ok = (near <= far) & (near > eps)
            t[ok] = near[ok]
        elif isinstance(prim, Sphere):
            oc = o - np.asarray(prim.center)
            b = d @ oc
            disc = b * b - (oc @ oc - prim.radius**2)
            s = -b - np.sqrt(disc)
            ok = (disc >= 0) & (s > eps)
            t[ok] = s[ok]
        elif isinstance(prim, Cylinder):
            oc = o - np.asarray(prim.center)
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = d[:, 0] * oc[0] + d[:, 1] * oc[1]
            disc = b * b - a * (oc[0] ** 2 + oc[1] ** 2 - prim.radius**2)
            s = (-b - np.sqrt(disc)) / a
            ok = (a > 1e-12) & (disc >= 0) & (s > eps) & (np.abs(oc[2] + s * d[:, 2]) <= prim.half_height)
            t[ok] = s[ok]
            zc = np.where(oc[2] > 0, prim.half_height, -prim.half_height)
            s = (zc - oc[2]) / d[:, 2]
            q = oc[:2] + s[:, None] * d[:, :2]
            ok = (np.abs(d[:, 2]) > 1e-12) & (s > eps) & ((q**2).sum(1) <= prim.radius**2) & (s < t)
            t[ok] = s[ok]
    return t


def random_scene(rng: np.random.Generator) -> Scene:
    """Three of the room's planes (floor, walls x = −2.5 and y = −2: rays going up, +x and +y hit nothing)
    and a random set of rotated boxes, spheres and cylinders inside the room."""
    mat = Material("tiles", 0.1, (0.2, 0.3, 0.4), (0.9, 0.8, 0.7))
    lo, hi = ROOM_MIN, ROOM_MAX
    prims = [Plane((0, 0, lo[2]), (0, 0, 1), mat), Plane((lo[0], 0, 0), (1, 0, 0), mat),
             Plane((0, lo[1], 0), (0, 1, 0), mat)]
    for _ in range(12):
        c = tuple(rng.uniform(lo + 0.3, hi - 0.3))
        kind = rng.integers(3)
        if kind == 0:
            prims.append(Box(c, tuple(rng.uniform(0.05, 0.5, 3)), mat, yaw=float(rng.uniform(-np.pi, np.pi))))
        elif kind == 1:
            prims.append(Sphere(c, float(rng.uniform(0.05, 0.4)), mat))
        else:
            prims.append(Cylinder(c, float(rng.uniform(0.05, 0.3)), float(rng.uniform(0.05, 0.6)), mat))
    return Scene(prims)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    position = rng.uniform(ROOM_MIN + 0.5, ROOM_MAX - 0.5)
    target = rng.uniform(ROOM_MIN + 0.2, ROOM_MAX - 0.2)
    return look_at(position, target, roll=float(rng.uniform(-0.5, 0.5)))


def test_scene_render_kernel_matches_reference(arch, rng):
    scene = random_scene(rng)
    cfg = SynthConfig(frames=1, width=64, height=48, fx=50.0, noise=False)
    seq = SyntheticSequence(cfg, scene=scene)
    up = look_at(np.array([0.5, 0.3, 1.2]), np.array([1.5, 0.6, 2.6]))  # up, into the open
    missed = 0
    for pose in [random_pose(rng), random_pose(rng), random_pose(rng), up]:
        depth, color = seq.render(pose)
        labels = seq.last_labels
        ref_depth, ref_labels = reference_cast(scene, pose, seq.intrinsics)
        assert depth.dtype == np.float32 and depth.shape == (48, 64)
        assert color.dtype == np.uint8 and color.shape == (48, 64, 3)
        # Labels differ only at rare float32 ties on silhouettes, where both depths are true hits.
        same = labels == ref_labels
        assert same.mean() > 0.98
        near = same & (ref_depth < 10)
        np.testing.assert_allclose(depth[near], ref_depth[near], rtol=2e-5, atol=2e-5)
        # Beyond, rays graze the room's planes (hits km away): the kernel's float32 ray direction is within about
        # 21u of the unit ray (u = 2⁻²⁴: the pixel's ray, its norm, the float32 rotation), its dot with the
        # normal within 27u, so the distance (stored distance over that dot) and the depth are within
        # 27u/|cos| + 8u of the exact ones, cos the ray's with the plane's normal: 32u/|cos| + 8u here.
        far = same & (ref_depth >= 10)
        assert all(isinstance(scene.primitives[k], Plane) for k in np.unique(ref_labels[far]))
        v, u = np.nonzero(far)
        ray = np.stack([(u - seq.intrinsics.cx) / seq.intrinsics.fx, (v - seq.intrinsics.cy) / seq.intrinsics.fy,
                        np.ones(len(u))], axis=1) @ pose[:3, :3].T
        normal = np.array([scene.primitives[k].normal for k in ref_labels[far]], float)
        cos = np.abs((ray * normal).sum(1)) / np.linalg.norm(ray, axis=1) / np.linalg.norm(normal, axis=1)
        u32 = 2.0 ** -24  # float32's unit roundoff, u above
        assert np.all(np.abs(depth[far] - ref_depth[far]) <= ref_depth[far] * (32 * u32 / cos + 8 * u32))
        np.testing.assert_array_equal(depth == 0, ref_labels == -1)  # a ray that hits nothing: invalid
        np.testing.assert_array_equal(color[depth == 0], 0)
        assert color[depth > 0].max(axis=1).min() > 0  # every hit is lit (ambient)
        missed += (ref_labels == -1).sum()
    assert missed > 0
    # every-other-pixel rendering is exactly the subsampled full render, noise included
    for noise in (False, True):
        full, full_color = seq.render(pose, noise=noise, seed=5)
        half, half_color = seq.render(pose, noise=noise, seed=5, downsample=2)
        np.testing.assert_array_equal(half, full[::2, ::2])
        np.testing.assert_array_equal(half_color, full_color[::2, ::2])


# --------------------------------------------------------------------------------------------------
# The default scene and path
# --------------------------------------------------------------------------------------------------
def every_primitive(caster, pose, K, step, H, W):
    """Tile lists holding every primitive (planes first, then near to far, as the renderer orders them)."""
    from ti_fusion.kernels import scene_render as rc

    table = caster.table.astype(np.float64)
    bound = table[:, rc.BOUND]
    dist = np.linalg.norm(table[:, rc.CENTER:rc.CENTER + 3] - pose[:3, 3], axis=1) - bound
    dist[bound < 0] = -np.inf
    order = np.argsort(dist, kind="stable").astype(np.int32)
    TH, TW = -(-H // rc.TILE), -(-W // rc.TILE)
    return (np.ascontiguousarray(np.broadcast_to(order, (TH, TW, len(order)))),
            np.full((TH, TW), len(order), np.int32))


def test_tile_lists_leave_out_only_primitives_that_cannot_be_nearest(arch, rng, monkeypatch):
    """The renderer's tile lists drop a bounded primitive whose bounding sphere misses the tile and a plane
    that another plane hides along every ray of the tile: frames are the same, bit for bit, as with every
    primitive in every list (odd sizes and --downsample 3 give tiles cut by the image's edge)."""
    cfg = SynthConfig(frames=120, width=150, height=110, fx=123.0)
    cases = [(SyntheticSequence(cfg), SyntheticSequence(cfg).poses[::23])]
    scene = random_scene(rng)
    cases.append((SyntheticSequence(cfg, scene=scene), [random_pose(rng) for _ in range(4)]))
    for seq, poses in cases:
        lists, _ = seq._caster._tile_lists(poses[0], seq.intrinsics, 1, cfg.height, cfg.width)
        for pose in poses:
            for step, noise in ((1, True), (1, False), (3, True)):
                culled = seq.render(pose, noise=noise, seed=3, downsample=step) + (seq.last_labels,)
                with monkeypatch.context() as m:
                    m.setattr(seq._caster, "_tile_lists", lambda *a: every_primitive(seq._caster, *a))
                    full = seq.render(pose, noise=noise, seed=3, downsample=step) + (seq.last_labels,)
                for a, b in zip(culled, full):
                    np.testing.assert_array_equal(a, b)
    counts = [seq._caster._tile_lists(p, seq.intrinsics, 1, cfg.height, cfg.width)[1].mean()
              for seq, poses in cases[:1] for p in poses]
    assert np.mean(counts) < len(default_scene()) / 2  # the lists are short: the test is not vacuous


def test_log_and_cos_of_the_noise_match_float64(arch):
    """The depth noise's inline ln and cos (vectorised with the pixels) against NumPy in float64, over
    the inputs Box–Muller gives them: u1 in (0, 1] and u2 in [0, 1) in steps of 2⁻²⁴."""
    import taichi as ti

    from ti_fusion.kernels.scene_render import cos_turns, log_unit

    def evaluate(x, ln, cos):
        for i in x:
            ln[i] = log_unit(x[i])
            cos[i] = cos_turns(x[i])

    column = ti.types.ndarray(dtype=ti.f32, ndim=1)  # set here: this file's annotations are strings
    evaluate.__annotations__ = {"x": column, "ln": column, "cos": column}
    evaluate = ti.kernel(evaluate)
    x = np.concatenate([np.arange(1, 2**24 + 1, 251), [2**23 - 1, 2**23, 2**23 + 1, 2**22, 3 * 2**22, 11863283]])
    x = (x / 2**24).astype(np.float32)
    ln, cos = np.empty_like(x), np.empty_like(x)
    evaluate(x, ln, cos)
    x64 = x.astype(np.float64)
    np.testing.assert_allclose(ln, np.log(x64), rtol=3e-7, atol=1e-7)
    np.testing.assert_allclose(cos, np.cos(2 * np.pi * x64), rtol=0, atol=5e-7)


def test_depth_backprojects_onto_the_primitive_it_hit(cpu, rng):
    seq = SyntheticSequence(replace(SMALL, noise=False))
    poses = [seq.poses[0], seq.poses[70], seq.poses[119], random_pose(rng)]
    for pose in poses:
        depth, _ = seq.render(pose)
        assert (depth > 0).all()  # closed room, no sensor: every pixel sees a surface
        points, flat = backproject_world(depth, seq.intrinsics, pose)
        hit = seq.last_labels.reshape(-1)[flat]
        to_hit = seq.scene.distances(points)[np.arange(len(points)), hit]
        assert to_hit.max() < 1e-4, to_hit.max()
        assert seq.surface_distance(points).max() < 1e-4


def test_camera_path_is_rigid_smooth_and_hand_held(cpu):
    seq = SyntheticSequence(replace(SMALL, frames=300))
    P = seq.poses
    assert P.shape == (300, 4, 4) and P.dtype == np.float64 and len(seq) == 300
    for T in P:
        assert rigidity_error(T) is None
        assert np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-12
        assert abs(np.linalg.det(T[:3, :3]) - 1.0) < 1e-12
    np.testing.assert_allclose(np.diff(seq.timestamps), 1.0 / 30.0, atol=1e-12)
    step = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    turn = np.array([rotation_angle_deg((invert(a) @ b)[:3, :3]) for a, b in zip(P[:-1], P[1:])])
    assert 0.007 < step.mean() < 0.015 and step.max() < 0.02  # ≈ 1 cm per frame
    assert 0.5 < turn.mean() < 1.5 and turn.max() < 4.0      # ≈ 1° per frame
    # smooth: per-frame change of the velocity is a small fraction of the velocity
    assert np.linalg.norm(np.diff(P[:, :3, 3], n=2, axis=0), axis=1).max() < 0.1 * step.mean()
    # rotation about all three camera axes
    w = np.abs([so3_log((invert(a) @ b)[:3, :3]) for a, b in zip(P[:-1], P[1:])]).mean(axis=0)
    assert (np.degrees(w) > 0.1).all(), np.degrees(w)
    # inside the room, never closer than the sensor's minimum range to a surface
    assert (P[:, :3, 3] > ROOM_MIN).all() and (P[:, :3, 3] < ROOM_MAX).all()
    assert seq.surface_distance(P[:, :3, 3]).min() > 0.45


def test_every_view_sees_structure(cpu):
    """Mostly valid depth and surface normals in three independent directions (ICP well constrained)."""
    seq = SyntheticSequence(replace(SMALL, frames=300, noise=True))
    for i in range(0, 300, 25):
        depth, _ = seq.frame(i)
        assert (depth > 0).mean() > 0.8
        labels = seq.last_labels[depth > 0]
        points, _ = backproject_world(depth, seq.intrinsics, seq.poses[i])
        normals = []
        for k in np.unique(labels):
            prim = seq.scene.primitives[k]
            if isinstance(prim, (Plane, Box)) and (labels == k).mean() > 0.02:
                normals += _visible_face_normals(prim, points[labels == k])
        singular = np.linalg.svd(np.array(normals), compute_uv=False)
        assert singular[-1] > 0.3, (i, singular)


def _visible_face_normals(prim, points: np.ndarray) -> list[np.ndarray]:
    if isinstance(prim, Plane):
        return [np.asarray(prim.normal, float)]
    c, s = np.cos(prim.yaw), np.sin(prim.yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    local = (points - prim.center) @ R / prim.half
    axis = np.abs(local).argmax(axis=1)
    return [R[:, a] for a in np.unique(axis) if (axis == a).sum() > 50]


# --------------------------------------------------------------------------------------------------
# Sensor model
# --------------------------------------------------------------------------------------------------
def test_same_seed_same_frames_different_seed_differs(cpu):
    a = SyntheticSequence(replace(SMALL, seed=3))
    b = SyntheticSequence(replace(SMALL, seed=3))
    c = SyntheticSequence(replace(SMALL, seed=4))
    da, ca = a.frame(7)
    db, cb = b.frame(7)
    dc, cc = c.frame(7)
    np.testing.assert_array_equal(da, db)
    np.testing.assert_array_equal(ca, cb)
    assert (da != dc).mean() > 0.3 and (ca != cc).mean() > 0.3
    # the same pose rendered twice (seed from the pose) is the same frame; other seeds other noise
    pose = a.poses[7]
    np.testing.assert_array_equal(a.render(pose)[0], a.render(pose)[0])
    assert (a.render(pose, seed=1)[0] != a.render(pose, seed=2)[0]).mean() > 0.3
    assert (a.frame(7)[0] != a.render(pose)[0]).mean() > 0.3


def _wall_sequence(distance: float, **cfg) -> tuple[SyntheticSequence, np.ndarray]:
    """A single textured wall at x = 2.5 and a camera looking straight at it from ``distance``."""
    wall = Scene([Plane((2.5, 0, 0), (-1, 0, 0), Material("tiles", 0.1, (0.2, 0.2, 0.2), (0.9, 0.9, 0.9)))])
    seq = SyntheticSequence(SynthConfig(frames=1, width=160, height=120, fx=131.25, **cfg), scene=wall)
    pose = look_at(np.array([2.5 - distance, 0.0, 1.3]), np.array([2.5, 0.0, 1.3]))
    return seq, pose


@pytest.mark.parametrize("distance, scale", [(0.8, 1.0), (1.6, 1.0), (2.4, 1.0), (3.2, 1.0), (2.4, 3.0)])
def test_axial_noise_matches_the_kinect_model(cpu, distance, scale):
    """σ(z) of ti_fusion.sensor, × synth.depth_noise_scale, then quantised to the disparity grid."""
    seq, pose = _wall_sequence(distance, depth_noise_scale=scale)
    clean, _ = seq.render(pose, noise=False)
    np.testing.assert_allclose(clean, distance, atol=1e-5)
    errors = np.concatenate([(seq.render(pose, seed=s)[0] - clean).ravel() for s in range(4)])
    c = seq.cfg
    sigma = scale * (0.0012 + 0.0019 * (distance - 0.4) ** 2)
    fx_sensor = c.fx * c.sensor_width / c.width  # quantisation is the 640-pixel sensor's
    step = distance**2 / (fx_sensor * c.baseline * c.subpixel)  # depth step of one disparity quantum
    expected = np.sqrt(sigma**2 + step**2 / 12)  # Gaussian then uniform quantisation error
    assert abs(errors.std() / expected - 1) < 0.15, (errors.std(), expected)
    assert abs(errors.mean()) < 0.1 * expected
    # every noisy depth sits on the disparity grid
    noisy = seq.render(pose, seed=9)[0]
    quanta = fx_sensor * c.baseline * c.subpixel / noisy[noisy > 0]
    np.testing.assert_allclose(quanta, np.round(quanta), atol=2e-3 * quanta.max())


def test_drop_outs_beyond_range_and_at_grazing_angles(cpu):
    seq, pose = _wall_sequence(4.3)
    assert (seq.render(pose)[0] == 0).all()
    assert (seq.render(pose, noise=False)[0] > 0).all()
    seq, pose = _wall_sequence(0.3)
    assert (seq.render(pose)[0] == 0).all()
    # a floor seen at a grazing angle: depth only where the ray is within 80° of the normal
    floor = Scene([Plane((0, 0, 0), (0, 0, 1), Material("tiles", 0.1, (0.2, 0.2, 0.2), (0.9, 0.9, 0.9)))])
    seq = SyntheticSequence(SynthConfig(frames=1, width=160, height=120, fx=131.25, max_range=100.0), scene=floor)
    pose = look_at(np.array([0.0, 0.0, 0.3]), np.array([3.0, 0.0, 0.1]))
    depth, _ = seq.render(pose)
    clean, _ = seq.render(pose, noise=False)
    points, flat = backproject_world(clean, seq.intrinsics, pose)
    rays = points - pose[:3, 3]
    incidence = np.degrees(np.arccos(np.abs(rays[:, 2]) / np.linalg.norm(rays, axis=1)))
    valid = depth.reshape(-1)[flat] > 0
    margin = np.abs(incidence - 80.0) > 0.05
    np.testing.assert_array_equal(valid[margin], (incidence < 80.0)[margin])
    assert valid.any() and (~valid).any()


# --------------------------------------------------------------------------------------------------
# Colour
# --------------------------------------------------------------------------------------------------
def test_orb_finds_hundreds_of_keypoints(cpu):
    seq = SyntheticSequence(SynthConfig(frames=120))
    orb = cv2.ORB_create(1000)
    for i in (0, 60, 119):
        _, color = seq.frame(i)
        keypoints = orb.detect(cv2.cvtColor(color, cv2.COLOR_RGB2GRAY), None)
        assert len(keypoints) > 300, (i, len(keypoints))


def test_color_is_shaded_by_geometry_not_viewpoint(cpu):
    """A surface point has the same colour from two viewpoints (Lambert, no specular), noise off."""
    seq = SyntheticSequence(replace(SMALL, noise=False))
    a, b = seq.poses[0], seq.poses[6]
    depth_a, color_a = seq.render(a)
    _, color_b = seq.render(b)
    points, flat = backproject_world(depth_a, seq.intrinsics, a)
    cam_b = (points - b[:3, 3]) @ b[:3, :3]
    K = seq.intrinsics
    u = np.round(K.fx * cam_b[:, 0] / cam_b[:, 2] + K.cx).astype(int)
    v = np.round(K.fy * cam_b[:, 1] / cam_b[:, 2] + K.cy).astype(int)
    inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    depth_b, _ = seq.render(b)
    seen = inside.copy()
    seen[inside] = np.abs(depth_b[v[inside], u[inside]] - cam_b[inside, 2]) < 0.01
    diff = np.abs(color_a.reshape(-1, 3)[flat][seen].astype(int) - color_b[v[seen], u[seen]].astype(int))
    # nearest-pixel lookup on a textured image: most pixels agree closely, texture edges do not
    assert seen.mean() > 0.7 and np.median(diff) <= 6


# --------------------------------------------------------------------------------------------------
# Dataset and command
# --------------------------------------------------------------------------------------------------
def test_synthetic_dataset(cpu, tmp_path):
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.datasets.synthetic import SyntheticDataset

    cfg = replace(SMALL, frames=12)
    ds = SyntheticDataset.from_config(cfg, downsample=2, start=2, stride=3)
    assert ds.name == "synthetic" and ds.format == "synthetic" and ds.has_ground_truth
    assert not SyntheticDataset.detect(tmp_path)
    assert len(ds) == 4 and ds.indices == [2, 5, 8, 11]
    assert ds.intrinsics == ds.sequence.intrinsics.downsampled(2)
    frame = ds[1]
    assert frame.index == 5 and frame.depth.shape == (60, 80) and frame.color.shape == (60, 80, 3)
    assert frame.intrinsics == ds.intrinsics
    np.testing.assert_array_equal(frame.gt_pose, ds.sequence.poses[5])
    assert frame.timestamp == pytest.approx(1.0 + 5 / 30)
    full_depth, full_color = ds.sequence.frame(5)
    np.testing.assert_array_equal(frame.depth, full_depth[::2, ::2])
    np.testing.assert_array_equal(frame.color, full_color[::2, ::2])
    assert isinstance(open_dataset(DatasetConfig(), cfg), SyntheticDataset)


def test_synth_command_writes_a_tum_folder(cpu, tmp_path):
    from ti_fusion.cli.main import main
    from ti_fusion.io.trajectory import read_tum

    out = tmp_path / "seq"
    assert main(["synth", str(out), "--frames", "3", "--width", "160", "--seed", "2", "--quiet"]) == 0
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "associations.txt", "intrinsics.txt", "summary.json"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["command"] == "synth" and summary["frames"] == 3 and summary["width"] == 160
    assert summary["height"] == 120 and summary["noise"] is True
    seq = SyntheticSequence(replace(SMALL, frames=3, seed=2))
    lines = [l.split() for l in (out / "depth.txt").read_text().splitlines() if not l.startswith("#")]
    assert len((out / "depth.txt").read_text().splitlines()) == 6
    assert [l[0] for l in lines] == ["1.000000", "1.033333", "1.066667"]
    for i, (stamp, name) in enumerate(lines):
        raw = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (120, 160)
        depth, color = seq.frame(i)
        np.testing.assert_allclose(raw / 5000.0, depth, atol=0.5 / 5000 + 1e-12)  # the file's rounding (float64 here)
        rgb = cv2.imread(str(out / f"rgb/{stamp}.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
        np.testing.assert_array_equal(rgb, color)
    stamps, poses = read_tum(out / "groundtruth.txt")
    np.testing.assert_allclose(stamps, seq.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses, seq.poses, atol=1e-8)
    assert np.loadtxt(out / "intrinsics.txt") == pytest.approx([131.25, 131.25, 79.5, 59.5])
    # the project's TUM loader reads the folder back: same depth, colour, intrinsics and poses
    from ti_fusion.io.datasets import open_dataset

    ds = open_dataset(DatasetConfig(path=str(out), depth_max=0.0))
    assert ds.format == "tum" and len(ds) == 3
    f = ds[2]
    assert f.intrinsics.as_tuple() == pytest.approx(seq.intrinsics.as_tuple())
    # half a unit of the file's rounding, and the loader's float32 raw / 5000 correctly rounded: half an ulp, 2⁻²⁴ × d
    # (2.4e-7 at 4 m, above the 1e-7 this allowed)
    np.testing.assert_allclose(f.depth, seq.frame(2)[0], atol=0.5 / 5000 + 1e-12, rtol=2.0 ** -24)
    np.testing.assert_allclose(f.gt_pose, seq.poses[2], atol=1e-6)
