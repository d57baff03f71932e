"""The MCAP run log: written, read back with the mcap reader, every channel decoded; crash safety;
the stats schemas declared complete (every message of a slam, vo and fuse run validates against them,
and docs/LOGS.md names their fields); ``ti-fusion inspect`` on it."""

from __future__ import annotations

import os
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from ti_fusion.camera import Intrinsics
from ti_fusion.cli.main import main
from ti_fusion.errors import InputError
from ti_fusion.geometry import se3_exp
from ti_fusion.io.mcap_log import (LOOP_REFUSED_TOPIC, LOOP_TOPIC, RunLogger, depth_from_msg, loop_edges_from_msg,
                                points_from_msg, pose_from_msg, read_log, software_versions)

T0 = 1305031102.175304  # a TUM-style unix timestamp: the ns conversion must keep µs
N_FRAMES = 6


def _trajectory(rng, n=N_FRAMES):
    poses, T = [], np.eye(4)
    for _ in range(n):
        T = T @ se3_exp(np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 3)]))
        poses.append(T)
    return np.array(poses)


def _stats(i: int) -> dict:
    return {
        "frame": i,
        "status": "ok" if i != 3 else "low_inliers",
        "ms": {"load": 1.0 + i, "pyramid": 2.0, "track": 10.0 + 2 * i, "fuse": 5.0, "log": np.float32(0.5)},
        "icp": {"iterations": [10, 5, 3], "residual": 0.01 * (i + 1), "inliers": 1000 + i,
                "inlier_ratio": 0.9, "cond": float("nan")},
        "surfels": np.int64(5000 * (i + 1)),
    }


def _write_log(path: Path, rng) -> dict:
    """A short log with every channel; returns what was written, for the checks."""
    poses = _trajectory(rng)
    gt = np.array([p @ se3_exp(rng.normal(0, 0.002, 6)) for p in poses])
    times = T0 + 0.033 * np.arange(N_FRAMES)
    xyz = rng.normal(0, 1, (500, 3)).astype(np.float32)
    xyz[7] = np.nan  # dropped
    rgb = rng.integers(0, 256, (500, 3), dtype=np.uint8)
    depth = rng.uniform(0.4, 4.0, (12, 16)).astype(np.float32)
    depth[0, :4] = [0.0, np.nan, -1.0, 70.0]  # invalid / out of 16-bit mm range → 0
    color = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    meta = {"config": {"icp": {"levels": 3}, "log": {"map_every": 30}},
            "dataset": {"path": "/data/x", "frames": N_FRAMES},
            "backend": {"arch": "cpu"}, "versions": software_versions()}
    with RunLogger(path, meta) as log:
        log.log_calibration(times[0], Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480))
        for i in range(N_FRAMES):
            log.log_pose(times[i], poses[i], gt[i])
            log.log_stats(times[i], _stats(i))
            if i % 2 == 0:
                log.log_depth(times[i], depth)
                log.log_image(times[i], color, fmt="png")
        n_kept = log.log_points(times[-1], xyz, rgb, max_points=300)
    return dict(poses=poses, gt=gt, times=times, xyz=xyz, rgb=rgb, depth=depth, color=color,
                meta=meta, n_kept=n_kept)


@pytest.fixture
def written(tmp_path, rng):
    path = tmp_path / "log.mcap"
    return path, _write_log(path, rng)


def _decode_all(path: Path) -> dict[str, list]:
    """Every message of every channel, decoded with the protobuf decoder factory or json."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema"
                assert json.loads(schema.data)["type"] == "object"
                decoded = json.loads(message.data)
            else:
                assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
                decoded = DecoderFactory().decoder_for(channel.message_encoding, schema)(message.data)
            out.setdefault(channel.topic, []).append((message.log_time, schema.name, decoded))
    return out


def test_every_channel_decodes_with_its_values(written):
    path, w = written
    msgs = _decode_all(path)
    schemas = {topic: {s for _, s, _ in m} for topic, m in msgs.items()}
    assert schemas == {
        "/tf": {"foxglove.FrameTransforms"}, "/camera/pose": {"foxglove.PoseInFrame"},
        "/gt/pose": {"foxglove.PoseInFrame"}, "/slam/stats": {"ti_fusion.SlamStats"},
        "/map/points": {"foxglove.PointCloud"}, "/camera/depth": {"foxglove.RawImage"},
        "/camera/color": {"foxglove.CompressedImage"}, "/camera/calibration": {"foxglove.CameraCalibration"},
    }
    expected_ns = [int(round(t * 1e9)) for t in w["times"]]

    assert [t for t, _, _ in msgs["/tf"]] == expected_ns
    for (_, _, tf), (_, _, pose), (_, _, gt), T, G in zip(msgs["/tf"], msgs["/camera/pose"], msgs["/gt/pose"],
                                                        w["poses"], w["gt"]):
        (tr,) = tf.transforms
        assert (tr.parent_frame_id, tr.child_frame_id) == ("world", "camera")
        np.testing.assert_allclose([tr.translation.x, tr.translation.y, tr.translation.z], T[:3, 3], atol=1e-12)
        assert pose.frame_id == gt.frame_id == "world"
        np.testing.assert_allclose(pose_from_msg(pose), T, atol=1e-9)
        np.testing.assert_allclose(pose_from_msg(gt), G, atol=1e-9)
        assert pose.timestamp.seconds == int(T0)

    stats = [m for _, _, m in msgs["/slam/stats"]]
    assert [s["frame"] for s in stats] == list(range(N_FRAMES))
    assert stats[3]["status"] == "low_inliers"
    assert stats[2]["ms"]["log"] == 0.5 and stats[1]["surfels"] == 10000
    assert "cond" not in stats[0]["icp"]  # NaN is not JSON, and Foxglove reads no null: left out
    assert stats[0]["icp"]["iterations"] == [10, 5, 3]

    ((_, _, cloud),) = msgs["/map/points"]
    assert cloud.frame_id == "world" and cloud.point_stride == 16
    assert [(f.name, f.offset) for f in cloud.fields] == [
        ("x", 0), ("y", 4), ("z", 8), ("red", 12), ("green", 13), ("blue", 14), ("alpha", 15)]
    xyz, rgba = points_from_msg(cloud)
    assert len(xyz) == w["n_kept"] == 300
    finite = np.all(np.isfinite(w["xyz"]), axis=1)
    source = {tuple(p): tuple(c) for p, c in zip(w["xyz"][finite], w["rgb"][finite])}
    assert all(source[tuple(p)] == tuple(c[:3]) for p, c in zip(xyz, rgba))  # a subset, colours kept
    assert np.all(rgba[:, 3] == 255)
    assert cloud.pose.HasField("position") and cloud.pose.HasField("orientation")  # the full identity pose
    assert cloud.pose.orientation.w == 1.0

    depths = [m for _, _, m in msgs["/camera/depth"]]
    assert len(depths) == 3 and depths[0].encoding == "16UC1" and depths[0].frame_id == "camera"
    d = depth_from_msg(depths[0])
    assert d.shape == w["depth"].shape
    assert np.all(d[0, :4] == 0)
    np.testing.assert_allclose(d[1:], w["depth"][1:], atol=0.0005 + 1e-6)  # millimetre rounding

    import cv2

    png = msgs["/camera/color"][0][2]
    assert png.format == "png"
    bgr = cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(bgr[..., ::-1], w["color"])

    calib = msgs["/camera/calibration"][0][2]
    assert list(calib.K) == [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1] and calib.width == 640


def test_loop_edges_read_back(tmp_path, rng):
    """Loop edges: foxglove.SceneUpdate messages in the world frame, the loops applied on /loop_closures (one
    entity, one thick green LINE_LIST, a sphere at each end) and the candidates not applied on a topic of their
    own (one thin, faint, red LINE_LIST), which the layout can hide: two points per edge, each entity replaced
    by its topic's next message; non-finite edges are left out."""
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive

    poses = _trajectory(rng)
    p = poses[:, :3, 3]
    first = [(p[4], p[0], True)]
    second = first + [(p[5], p[1], False), (p[5], np.array([np.nan, 0.0, 0.0]), True), (p[3], p[2], True)]
    path = tmp_path / "loops.mcap"
    with RunLogger(path) as log:
        log.log_pose(T0, poses[0])
        assert log.log_loop_edges(T0 + 0.1, first) == 1
        assert log.log_loop_edges(T0 + 0.2, second) == 3
        assert log.log_loop_edges(T0 + 0.3, []) == 0  # clears them
    decoded = _decode_all(path)
    stamps = [(int(round((T0 + d) * 1e9)), "foxglove.SceneUpdate") for d in (0.1, 0.2, 0.3)]
    for topic, entity_id, kind in ((LOOP_TOPIC, "loop_closures", "applied"),
                                   (LOOP_REFUSED_TOPIC, "loop_closures_refused", "refused")):
        assert [(t, s) for t, s, _ in decoded[topic]] == stamps, topic
        for _, _, msg in decoded[topic]:
            (entity,) = msg.entities
            assert entity.frame_id == "world" and entity.id == entity_id  # the poses' frame; one entity
            (line,) = entity.lines
            assert line.type == LinePrimitive.LINE_LIST
            if kind == "applied":  # thick, opaque and green
                assert line.thickness == 3 and line.color.a == 1 and line.color.g > line.color.r
            else:  # thin, faint and red, and no spheres
                assert line.thickness == 1 and line.color.a < 1 and line.color.r > line.color.g
                assert len(entity.spheres) == 0
    one, two, none = (m for _, _, m in decoded[LOOP_TOPIC])
    r_one, r_two, r_none = (m for _, _, m in decoded[LOOP_REFUSED_TOPIC])
    # each applied loop's ends are marked too (its two keyframes are close: the line alone is a few pixels)
    assert [len(m.entities[0].spheres) for m in (one, two, none)] == [2, 4, 0]
    ends = [(s.pose.position.x, s.pose.position.y, s.pose.position.z) for s in two.entities[0].spheres]
    np.testing.assert_allclose(ends, [second[0][0], second[0][1], second[3][0], second[3][1]], atol=1e-12)
    assert all(s.color.g > s.color.r and s.color.a == 1 and s.size.x > 0 for s in two.entities[0].spheres)
    got, refused = loop_edges_from_msg(two), loop_edges_from_msg(r_two)
    assert [ok for _, _, ok in got] == [True, True] and [ok for _, _, ok in refused] == [False]
    for (a, b, _), (c, d, _) in zip(got + refused, [second[0], second[3], second[1]]):
        np.testing.assert_allclose(a, c, atol=1e-12)
        np.testing.assert_allclose(b, d, atol=1e-12)
    assert len(loop_edges_from_msg(one)) == 1 and loop_edges_from_msg(r_one) == []
    assert loop_edges_from_msg(none) == loop_edges_from_msg(r_none) == []
    contents = read_log(path)
    assert contents.channels[LOOP_TOPIC].count == contents.channels[LOOP_REFUSED_TOPIC].count == 3
    assert contents.complete


def test_metadata_records(written):
    path, w = written
    with open(path, "rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert set(records) == {"config", "dataset", "backend", "versions"}
    assert json.loads(records["config"]["icp"]) == {"levels": 3}
    assert records["backend"]["arch"] == "cpu"  # strings stay readable, not JSON-quoted
    assert records["versions"]["mcap"]


def test_read_log(written):
    path, w = written
    log = read_log(path)
    assert log.complete
    assert log.channels["/tf"].count == N_FRAMES and log.channels["/camera/depth"].count == 3
    assert log.channels["/slam/stats"].schema_name == "ti_fusion.SlamStats"
    assert log.start_s == pytest.approx(T0, abs=1e-6) and log.end_s == pytest.approx(w["times"][-1], abs=1e-6)
    np.testing.assert_allclose(log.est_poses, w["poses"], atol=1e-9)
    np.testing.assert_allclose(log.gt_poses, w["gt"], atol=1e-9)
    np.testing.assert_allclose(log.est_times, w["times"], atol=1e-6)
    assert log.stats_topic == "/slam/stats" and [s["frame"] for s in log.stats] == list(range(N_FRAMES))
    assert log.metadata_value("dataset", "frames") == N_FRAMES
    assert log.metadata_value("dataset", "path") == "/data/x"


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_log_is_finalised_when_the_run_is_interrupted(tmp_path, error):
    path = tmp_path / "log.mcap"
    with pytest.raises(error):
        with RunLogger(path, {"backend": {"arch": "cpu"}}) as log:
            for i in range(3):
                log.log_pose(i, np.eye(4), np.eye(4))
                log.log_stats(i, {"frame": i, "status": "ok", "ms": {"track": 1.0}})
                log.log_depth(i, np.ones((4, 5), np.float32))
            log.log_points(2, np.zeros((10, 3)))
            raise error()
    msgs = _decode_all(path)  # the footer-indexed reader: needs the finalised file
    assert {t: len(m) for t, m in msgs.items()} == {
        "/tf": 3, "/camera/pose": 3, "/gt/pose": 3, "/slam/stats": 3, "/camera/depth": 3, "/map/points": 1}
    assert read_log(path).complete


def test_unclosed_logger_is_finalised_when_collected(tmp_path):
    path = tmp_path / "log.mcap"
    log = RunLogger(path)
    log.log_stats(0.0, {"frame": 0})
    del log
    assert len(_decode_all(path)["/slam/stats"]) == 1


def test_hard_kill_recovers_whole_chunks(tmp_path):
    """No footer (SIGKILL): the indexed reader gives up, read_log keeps every whole chunk."""
    path = tmp_path / "log.mcap"
    with RunLogger(path, chunk_size=2048) as log:
        for i in range(200):
            log.log_stats(i * 0.1, {"frame": i, "status": "ok", "ms": {"track": float(i)}})
    data = path.read_bytes()
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(data[: len(data) * 2 // 3])
    with open(torn, "rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())
    log = read_log(torn)
    assert not log.complete
    frames = [s["frame"] for s in log.stats]
    assert 20 < len(frames) < 200 and frames == list(range(len(frames)))


# --------------------------------------------------------------------------------------------------
# The writer thread: order kept, the caller's arrays its own again at once, errors raised in the caller
# --------------------------------------------------------------------------------------------------
def _log_threads() -> list:
    import threading

    return [t for t in threading.enumerate() if t.name == "ti-fusion-log"]


@pytest.mark.parametrize("threaded", [True, False], ids=["thread", "caller"])
def test_messages_keep_their_order_and_the_callers_arrays_are_copied(tmp_path, threaded):
    """Messages of every kind written by the writer thread in call order (as the caller's own thread writes
    them); an array the caller changes right after the call is logged as it was at the call."""
    path = tmp_path / "log.mcap"
    depth = np.ones((6, 8), np.float32)
    xyz = np.zeros((20, 3))
    with RunLogger(path, threaded=threaded) as log:
        assert len(_log_threads()) == (1 if threaded else 0)
        for i in range(60):
            depth[:] = 1.0 + i / 100
            xyz[:] = i
            log.log_pose(i, se3_exp(np.full(6, 0.01 * i)))
            log.log_stats(i, {"frame": i})
            log.log_depth(i, depth)
            log.log_points(i, xyz)
            depth[:] = 0.0  # changed at once: the message has the values of the call
            xyz[:] = -1.0
        log.flush()
        assert path.stat().st_size > 0
    assert not _log_threads()
    with open(path, "rb") as f:
        records = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    topics = [t for t, _, _ in records]
    assert topics == ["/tf", "/camera/pose", "/slam/stats", "/camera/depth", "/map/points"] * 60
    times = [ns for _, ns, _ in records]
    assert times == sorted(times)
    msgs = _decode_all(path)
    for i, (_, _, msg) in enumerate(msgs["/camera/depth"]):
        np.testing.assert_allclose(depth_from_msg(msg), round(1.0 + i / 100, 3), atol=5e-4)
    for i, (_, _, msg) in enumerate(msgs["/map/points"]):
        assert np.all(points_from_msg(msg)[0] == i)


def test_a_write_error_on_the_writer_thread_reaches_the_caller(tmp_path, monkeypatch):
    """A full disk while the writer thread writes: the next call (or close) raises the ``OutputError`` that
    names the log, once; nothing more is written, and the thread ends."""
    import errno
    import os

    from ti_fusion.errors import OutputError
    from ti_fusion.io import mcap_log

    written = {"bytes": 0}
    real_write = mcap_log._LogFile.write

    def write(self, data):
        written["bytes"] += len(data)
        if written["bytes"] > 4096:
            raise OutputError(self.path, f"cannot be written: {os.strerror(errno.ENOSPC)}")
        return real_write(self, data)

    monkeypatch.setattr(mcap_log._LogFile, "write", write)
    path = tmp_path / "log.mcap"
    with pytest.raises(OutputError, match="No space left on device") as caught:
        with RunLogger(path, chunk_size=256) as log:
            for i in range(10_000):
                log.log_stats(i, {"frame": i, "padding": "x" * 100})
    assert str(path) in str(caught.value) and i < 10_000 - 1
    assert not _log_threads()


def test_a_killed_run_keeps_what_its_writer_had_written(tmp_path):
    """SIGKILL after ``flush``: every whole chunk is on disk and replays (read_log, no footer)."""
    import subprocess
    import sys

    path = tmp_path / "log.mcap"
    code = (f"import os, signal\nfrom ti_fusion.io.mcap_log import RunLogger\nlog = RunLogger({str(path)!r}, "
            "chunk_size=512)\nfor i in range(300):\n    log.log_stats(i * 0.1, {'frame': i, 'padding': 'x' * 40})\n"
            "log.flush()\nos.kill(os.getpid(), signal.SIGKILL)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == -9, done.stderr
    log = read_log(path)
    frames = [s["frame"] for s in log.stats]
    assert not log.complete and 250 < len(frames) <= 300 and frames == list(range(len(frames)))


def test_time_guards(tmp_path):
    path = tmp_path / "log.mcap"
    with pytest.warns(UserWarning, match="timestamp"):
        with RunLogger(path) as log:
            log.log_stats(0, {"frame": 0})          # 7-Scenes: timestamps are frame indices
            log.log_stats(2.5, {"frame": 1})
            log.log_stats(float("nan"), {"frame": 2})
            log.log_stats(-1.0, {"frame": 3})
    times = [t for t, _, _ in _decode_all(path)["/slam/stats"]]
    assert times == [0, 2_500_000_000, 2_500_000_000, 2_500_000_000]


def test_points_downsampling_is_deterministic_and_float_colors(tmp_path, rng):
    xyz = rng.normal(size=(1000, 3))
    rgb = rng.uniform(0, 1, (1000, 3))
    clouds = []
    for name in ("a.mcap", "b.mcap"):
        with RunLogger(tmp_path / name) as log:
            log.log_points(0, xyz, rgb, max_points=100)
            log.log_points(1, xyz[:50], topic="/map/plain")
        clouds.append(_decode_all(tmp_path / name))
    a, b = (points_from_msg(c["/map/points"][0][2]) for c in clouds)
    np.testing.assert_array_equal(a[0], b[0])
    idx = [int(np.flatnonzero(np.all(xyz.astype(np.float32) == p, axis=1))[0]) for p in a[0]]
    np.testing.assert_array_equal(a[1][:, :3], np.round(rgb[idx] * 255).astype(np.uint8))
    plain_xyz, plain_rgba = points_from_msg(clouds[0]["/map/plain"][0][2])
    assert plain_rgba is None and len(plain_xyz) == 50


def test_inspect_prints_the_summary(written, tmp_path, capsys):
    path, w = written
    out = tmp_path / "inspect"
    assert main(["inspect", str(path), "--out", str(out), "--quiet", "--plot"]) == 0
    text = capsys.readouterr().out
    for needle in ("/tf", "foxglove.FrameTransforms", "/slam/stats", "ti_fusion.SlamStats", "json",
                   "time range: 1305031102.175304", "track", "tracking failures: 1: 3 (low_inliers)",
                   "ATE RMSE:", "metadata: backend, config, dataset, versions"):
        assert needle in text, needle
    summary = json.loads((out / "summary.json").read_text())
    assert summary["command"] == "inspect" and summary["frames"] == N_FRAMES
    assert summary["channels"]["/camera/depth"]["count"] == 3
    assert summary["tracking_failures"] == 1
    track = [10.0 + 2 * i for i in range(N_FRAMES)]
    assert summary["ms_per_stage"]["track"] == {"median": float(np.median(track)), "max": max(track)}
    assert 0 < summary["ate_rmse_m"] < 0.01 and summary["ate_poses"] == N_FRAMES
    png = out / "stats.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert summary["plot"] == str(png)


def test_inspect_ate_matches_a_known_offset(tmp_path, rng):
    """GT = estimate rigidly moved, plus a known error on one axis: the aligned ATE sees only the error."""
    poses = _trajectory(rng, 20)
    offset = se3_exp([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])
    path = tmp_path / "log.mcap"
    with RunLogger(path) as log:
        for i, T in enumerate(poses):
            G = offset @ T
            G[:3, 3] += offset[:3, :3] @ [0.01 * (-1) ** i, 0, 0]  # ±1 cm, zero mean
            log.log_pose(i, T, G)
    from ti_fusion.cli.inspect import _ate_rmse

    rmse, n = _ate_rmse(read_log(path))
    assert n == 20 and rmse == pytest.approx(0.01, abs=2e-3)


def test_inspect_ate_needs_three_poses(tmp_path, rng):
    """One or two poses fit any ground truth exactly after a rigid alignment: no ATE, and inspect says why
    (the log of a run stopped after its first frames)."""
    poses = _trajectory(rng, 2)
    path = tmp_path / "log.mcap"
    with RunLogger(path) as log:
        for i, T in enumerate(poses):
            log.log_pose(i, T, se3_exp([0.1, 0, 0, 0, 0, 0.5]) @ T)
    from ti_fusion.cli.inspect import _ate_rmse, format_report, summarise

    contents = read_log(path)
    assert _ate_rmse(contents) == (None, 2)
    summary = summarise(contents)
    assert summary["ate_rmse_m"] is None and summary["ate_poses"] == 2
    assert "ATE: not computed from 2 pose pair(s)" in format_report(contents, summary)


def test_inspect_bad_input(tmp_path, capsys):
    missing = tmp_path / "nope.mcap"
    assert main(["inspect", str(missing), "--out", str(tmp_path / "o")]) == 2
    assert str(missing) in capsys.readouterr().err
    not_mcap = tmp_path / "x.mcap"
    not_mcap.write_text("hello")
    with pytest.raises(InputError, match="not an MCAP file"):
        read_log(not_mcap)
    assert main(["inspect", str(not_mcap), "--out", str(tmp_path / "o")]) == 2
    assert "x.mcap: not an MCAP file" in capsys.readouterr().err


def test_inspect_on_an_unfinalised_log(tmp_path, capsys):
    path = tmp_path / "log.mcap"
    with RunLogger(path, chunk_size=1024) as log:
        for i in range(100):
            log.log_pose(i, np.eye(4))
            log.log_stats(i, {"frame": i, "status": "ok", "ms": {"track": 1.0}})
    torn = tmp_path / "torn.mcap"
    shutil.copy(path, torn)
    with open(torn, "r+b") as f:
        f.truncate(path.stat().st_size // 2)
    assert main(["inspect", str(torn), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert "NOT finalised" in capsys.readouterr().out


def test_inspect_counts_failures_as_the_runs_summary_does(tmp_path, capsys):
    """A relocalised frame was tracked (slam's summary.json does not count it), an accepted vo frame is not a
    failure: inspect's count agrees with the run's own."""
    path = tmp_path / "log.mcap"
    statuses = ["ok", "ok", "relocalised", "lost: too few inliers", "ok"]
    with RunLogger(path) as log:
        for i, status in enumerate(statuses):
            log.log_stats(i, {"frame": i, "status": status, "ms": {"track": 1.0}})
    assert main(["inspect", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert "tracking failures: 1: 3 (lost: too few inliers)" in capsys.readouterr().out
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["tracking_failures"] == 1


def test_inspect_on_a_vo_log(tmp_path, capsys):
    """vo logs its frame time as one number and its status as accepted / rejected: ...: inspect reads both."""
    run = tmp_path / "vo"
    assert main(["vo", "--frames", "4", "--downsample", "4", "--out", str(run), "--quiet"]) == 0
    vo = json.loads((run / "summary.json").read_text())
    out = tmp_path / "inspect"
    assert main(["inspect", str(run / "log.mcap"), "--out", str(out), "--quiet", "--plot"]) == 0
    text = capsys.readouterr().out
    assert "stats (/vo/stats, 4 frames)" in text and "total" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracking_failures"] == vo["rejected_total"] and "total" in summary["ms_per_stage"]
    assert (out / "stats.png").is_file()
    path = tmp_path / "rejected.mcap"
    with RunLogger(path) as log:  # the frame's time as a plain number
        for i, status in enumerate(["accepted", "rejected: few_matches", "accepted"]):
            log.log_stats(i, {"frame": i, "status": status, "ms": 2.0 + i}, channel="/vo/stats")
    assert main(["inspect", str(path), "--out", str(tmp_path / "o2"), "--quiet"]) == 0
    assert "tracking failures: 1: 1 (rejected: few_matches)" in capsys.readouterr().out
    ms = json.loads((tmp_path / "o2" / "summary.json").read_text())["ms_per_stage"]
    assert ms == {"total": {"median": 3.0, "max": 4.0}}


# --------------------------------------------------------------------------------------------------
# Declared stats schemas


DOCS = Path(__file__).resolve().parents[2] / "docs" / "LOGS.md"


def test_declared_schema_is_the_channels_schema(tmp_path):
    from ti_fusion.io.mcap_log import json_field, json_object

    declared = json_object({"frame": json_field("integer", "index"), "late": json_field("number", "seconds")},
                           required=("frame",))
    path = tmp_path / "log.mcap"
    with RunLogger(path) as log:
        log.declare_json("/x/stats", declared)
        log.log_stats(0, {"frame": 0}, "/x/stats")  # the first message lacks "late": the schema still has it
        log.log_stats(1, {"frame": 1, "late": 0.5}, "/x/stats")
        with pytest.raises(ValueError, match="declared already"):
            log.declare_json("/x/stats", declared)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    (schema,) = summary.schemas.values()
    assert schema.name == "ti_fusion.XStats" and schema.encoding == "jsonschema"
    assert json.loads(schema.data) == {"$schema": "https://json-schema.org/draft/2020-12/schema",
                                       "title": "/x/stats", **declared}


def _steps():
    from ti_fusion.slam.fuse_step import STATS_SCHEMA as FUSE
    from ti_fusion.slam.slam_step import STATS_SCHEMA as SLAM
    from ti_fusion.slam.vo_step import STATS_SCHEMA as VO

    return {"/slam/stats": SLAM, "/vo/stats": VO, "/fuse/stats": FUSE}


def _field_names(schema: dict, prefix: str = "") -> list[str]:
    """Every property of a schema as a message path: frame, ms.track, icp.inlier_ratio, ..."""
    names = []
    for name, sub in schema.get("properties", {}).items():
        names.append(prefix + name)
        names += _field_names(sub, prefix + name + ".")
    return names


def test_docs_name_every_stats_field():
    docs = DOCS.read_text()
    for topic, schema in _steps().items():
        assert f"`{topic}`" in docs
        for name in _field_names(schema):
            assert f"`{name}`" in docs, f"docs/LOGS.md does not describe {topic} field {name}"


class _BlankDepth:
    """The dataset with no valid depth in frame ``blank``: a lost frame, with its ICP's nulls."""

    def __init__(self, dataset, blank: int):
        self.dataset, self.blank = dataset, blank

    def __getattr__(self, name):
        return getattr(self.dataset, name)

    def __len__(self):
        return len(self.dataset)

    def __getitem__(self, i):
        frame = self.dataset[i]
        if i == self.blank:
            frame.depth = np.zeros_like(frame.depth)
        return frame


def _run(command: str, out: Path) -> None:
    from ti_fusion.backend import current_backend
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import Pipeline

    cfg = Config()
    cfg.dataset.downsample, cfg.dataset.stop = 4, 7
    cfg.log.progress, cfg.log.depth_every, cfg.log.map_every = False, 3, 4
    dataset = _BlankDepth(open_dataset(cfg.dataset, cfg.synth), blank=5 if command == "slam" else -1)
    if command == "slam":
        from ti_fusion.slam.slam_step import SLAMStep as Step
    elif command == "vo":
        from ti_fusion.slam.vo_step import VOStep as Step
    else:
        from ti_fusion.slam.fuse_step import FuseStep as Step
    backend = None if command == "vo" else current_backend()
    Pipeline(dataset, cfg, RunDir(command, out), Step(cfg, dataset), backend, show_progress=False).run()


@pytest.mark.slow
@pytest.mark.parametrize("command", ["slam", "vo", "fuse"])
def test_every_stats_message_validates_against_the_declared_schema(cpu, tmp_path, command):
    """Every message of a run (a lost frame included for slam) against its channel's schema, which is the
    step's, complete from the first message on; colour and calibration are written beside depth."""
    import cv2
    import jsonschema

    _run(command, tmp_path / command)
    msgs = _decode_all(tmp_path / command / "log.mcap")
    topic = f"/{command}/stats"
    with open(tmp_path / command / "log.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    (schema,) = [json.loads(s.data) for s in summary.schemas.values() if s.encoding == "jsonschema"]
    jsonschema.Draft202012Validator.check_schema(schema)
    declared = _steps()[topic]
    assert {k: v for k, v in schema.items() if k not in ("$schema", "title")} == {
        **declared, "properties": {**declared["properties"], "ms": schema["properties"]["ms"],
                                   "first_launch_ms": schema["properties"]["first_launch_ms"]}}
    assert schema["properties"]["first_launch_ms"]["type"] == "number"  # added by the pipeline, as ms.load
    assert set(declared["properties"]["ms"]["properties"]) | {"load", "log"} == set(
        schema["properties"]["ms"]["properties"])
    validator = jsonschema.Draft202012Validator(schema)
    stats = [m for _, _, m in msgs[topic]]
    assert len(stats) == 7
    for message in stats:
        errors = [f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(message)]
        assert not errors, (message, errors)
    if command == "slam":
        assert stats[5]["status"].startswith("lost") and "icp" in stats[5] and "fuse" not in stats[5]["ms"]
        assert "icp" not in stats[0] and "track" in stats[1]["ms"]

    depth_times = [t for t, _, _ in msgs["/camera/depth"]]
    assert depth_times == [t for t, _, _ in msgs["/camera/color"]] and len(depth_times) == 3
    jpeg = msgs["/camera/color"][0][2]
    assert jpeg.format == "jpeg" and jpeg.frame_id == "camera"
    depth = msgs["/camera/depth"][0][2]
    assert cv2.imdecode(np.frombuffer(jpeg.data, np.uint8), cv2.IMREAD_COLOR).shape == (depth.height,
                                                                                           depth.width, 3)
    ((t_calib, _, calib),) = msgs["/camera/calibration"]  # once: the intrinsics do not change
    assert t_calib == depth_times[0] and (calib.width, calib.height) == (depth.width, depth.height)
    assert calib.frame_id == "camera" and calib.K[0] > 0 and calib.K[8] == 1


def _layout_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("foxglove_layout", DOCS.parents[1] / "scripts" / "foxglove_layout.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_layout_script_takes_options_and_names_an_unwritable_file(tmp_path, monkeypatch, capsys):
    """--help prints the usage (it once wrote the layout into a file named '--help'); a path that cannot be
    written is one line naming it."""
    module = _layout_module()
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as done:
        module.main(["--help"])
    assert done.value.code == 0 and "usage:" in capsys.readouterr().out and not list(tmp_path.iterdir())
    with pytest.raises(SystemExit) as done:
        module.main([str(tmp_path / "missing" / "layout.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert done.value.code == 2 and len(err) == 1 and "missing/layout.json" in err[0], err
    assert module.main([str(tmp_path / "layout.json")]) == 0
    assert (tmp_path / "layout.json").read_text() == (DOCS.parent / "foxglove-layout.json").read_text()


def test_the_foxglove_layout_shows_what_the_logs_have():
    """docs/foxglove-layout.json is what scripts/foxglove_layout.py writes, and every topic and message path
    in it is one the logs have."""
    import re

    text = (DOCS.parent / "foxglove-layout.json").read_text()
    assert json.loads(text) == _layout_module().layout()
    topics = {"/tf", "/camera/pose", "/gt/pose", "/slam/stats", "/map/points", "/camera/depth", "/camera/color",
              "/camera/calibration", LOOP_TOPIC, LOOP_REFUSED_TOPIC,
              "/map/mesh",  # /map/mesh: slam --mesh (tests/mapping/test_mesh.py)
              "/trajectory"}
    slam_fields = set(_field_names(_steps()["/slam/stats"])) | {"ms.load", "ms.log", "first_launch_ms"}
    paths = set(re.findall(r'"(/[a-z/_]+(?:\{[a-z_]+==[0-9]+\})?(?:\.[a-z_.]+)?)"', text))
    assert paths and any("{first_launch_ms==0}" in p for p in paths)  # the ms plot leaves compiling frames out
    for path in paths:
        topic, _, field = path.partition(".")
        topic, _, condition = topic.partition("{")
        assert topic in topics, path
        if condition:
            assert topic == "/slam/stats" and condition.split("==")[0] in slam_fields, path
        if topic == "/slam/stats":
            assert field in slam_fields, path
        elif field:
            assert field in ("pose.position.x", "pose.position.y"), path


def test_the_foxglove_layout_is_in_the_form_every_client_imports():
    """The classic form (Studio fails on the SDK's {version, content} form), panels of types both Studio and
    Lichtblick have, each panel of the tree configured, the map in its RGBA fields with a colour field named
    (else the client colours it by x), and x-y plots with one x path per panel (no per-series x path)."""
    layout = json.loads((DOCS.parent / "foxglove-layout.json").read_text())
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig", "layout"}
    assert layout["playbackConfig"]["speed"] == 1.0

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    def shares(node):
        return [] if isinstance(node, str) else [node["splitPercentage"], *shares(node["first"]),
                                                 *shares(node["second"])]

    panels = leaves(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"]) and len(set(panels)) == len(panels)
    assert all(0 < p < 100 for p in shares(layout["layout"]))
    types = {panel.partition("!")[0] for panel in panels}
    assert types == {"3D", "ImageViewPanel", "Plot"}
    (scene,) = [c for p, c in layout["configById"].items() if p.startswith("3D!")]
    cloud = scene["topics"]["/map/points"]
    assert cloud["colorMode"] == "rgba-fields" and cloud["colorField"] in ("red", "green", "blue", "alpha")
    # the loops applied shown, the hundreds of candidates not applied hidden until the user turns them on
    assert scene["topics"][LOOP_TOPIC]["visible"] and not scene["topics"][LOOP_REFUSED_TOPIC]["visible"]
    plots = [c for p, c in layout["configById"].items() if p.startswith("Plot!")]
    assert not any("xValuePath" in series or "xValue" in series for c in plots for series in c["paths"])
    xy = [c for c in plots if c["xAxisVal"] == "custom"]
    assert len(xy) == 2
    for plot in xy:  # the x and y of one topic, so that their values pair message by message
        ((series,),) = [plot["paths"]]
        assert series["value"].rpartition(".")[0] == plot["xAxisPath"]["value"].rpartition(".")[0]


def test_the_real_client_check_script_parses():
    """scripts/foxglove_client_check.mjs (run by hand: it needs chromium and npm) is valid JavaScript."""
    import subprocess

    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    script = DOCS.parents[1] / "scripts" / "foxglove_client_check.mjs"
    result = subprocess.run([node, "--check", str(script)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def _chunk_ends(path: Path) -> list[int]:
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    ends = []
    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True)
        for record in reader.records:
            if isinstance(record, Chunk):
                ends.append(reader._stream.count)
    return ends


def test_a_damaged_log_is_refused_not_read_as_valid(tmp_path, capsys):
    """A byte changed inside a chunk of a finalised log: inspect said nothing was wrong (it read the log up to
    the damage as if the run had been killed there); now one line says the file is damaged."""
    path = tmp_path / "log.mcap"
    with RunLogger(path, chunk_size=1024) as log:
        for i in range(50):
            log.log_pose(i, np.eye(4))
            log.log_stats(i, {"frame": i, "status": "ok", "ms": {"track": 1.0}})
    data = bytearray(path.read_bytes())
    data[_chunk_ends(path)[2] - 5] ^= 0x10  # in the third chunk's compressed records
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"log.mcap: damaged near byte \d+: .*the file changed after it was written"):
        read_log(path)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ti-fusion inspect: error: {path}: damaged near byte") and "\n" not in err


def test_inspect_reads_only(tmp_path, capsys, monkeypatch):
    """inspect writes nothing unless asked (--out, --plot): no logs/inspect-* folder, so it works in a
    folder it cannot write; it takes a run's folder for its log.mcap."""
    run = tmp_path / "run"
    run.mkdir()
    with RunLogger(run / "log.mcap") as log:
        log.log_stats(0, {"frame": 0, "status": "ok", "ms": {"track": 1.0}})
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    assert main(["inspect", str(run)]) == 0
    assert f"log: {run / 'log.mcap'}\n" in capsys.readouterr().out
    assert os.listdir(cwd) == [] and sorted(os.listdir(run)) == ["log.mcap"]


def test_inspect_tells_a_log_being_written_from_a_killed_runs(tmp_path, capsys):
    from ti_fusion.io.outputs import RunDir

    with RunDir("slam", tmp_path / "run") as out:
        log = RunLogger(out.file("log.mcap"), chunk_size=256)
        for i in range(40):
            log.log_stats(i, {"frame": i, "status": "ok", "ms": {"track": 1.0}})
        assert main(["inspect", str(out.path)]) == 0
        first = capsys.readouterr().out.splitlines()[0]
        assert f"(still being written by a run: slam, process {os.getpid()}" in first
        log.close()
    torn = tmp_path / "torn.mcap"
    data = (out.path / "log.mcap").read_bytes()
    torn.write_bytes(data[:len(data) // 2])
    assert main(["inspect", str(torn)]) == 0
    assert "NOT finalised: the run was killed" in capsys.readouterr().out.splitlines()[0]


def test_the_gil_switch_interval_is_shorter_while_a_writer_thread_runs(tmp_path):
    """The loop's thread waits for the GIL while the writer holds it: at most the shorter interval, and
    the interval is the caller's again once the last writer has closed."""
    import sys

    from ti_fusion.io import mcap_log

    interval = sys.getswitchinterval()
    with RunLogger(tmp_path / "a.mcap"):
        with RunLogger(tmp_path / "b.mcap"):
            assert sys.getswitchinterval() == min(interval, mcap_log._SWITCH_INTERVAL_S)
        assert sys.getswitchinterval() == min(interval, mcap_log._SWITCH_INTERVAL_S)
    assert sys.getswitchinterval() == interval
    with RunLogger(tmp_path / "c.mcap", threaded=False):
        assert sys.getswitchinterval() == interval


def test_json_message_is_the_two_passes_in_one():
    """log_stats's one pass gives what jsonable then without_nulls give, on every kind of value they take."""
    import collections
    import enum
    from pathlib import Path

    from ti_fusion.io.mcap_log import json_message, without_nulls
    from ti_fusion.io.outputs import jsonable

    class Kind(enum.IntEnum):
        A = 3

    value = {
        "frame": 7, "ok": True, "status": "ok", "none": None, "nan": float("nan"), "inf": -float("inf"), "x": 0.25,
        "np": np.float64(1.5), "np_nan": np.float32("nan"), "npi": np.int64(4), "arr": np.array([[1.0, np.nan]]),
        "ms": {"pyramid": 1.25, "gone": None, "nested": [None, float("nan"), {"a": None, "b": 2}]},
        "tuple": (1, None, "x", (2.5, np.inf)), "path": Path("/tmp/x"), "enum": Kind.A,
        "ordered": collections.OrderedDict([("b", None), ("a", 1.0)]), "keys": {1: "one", 2.5: None, "1": 2},
        "empty": {}, "list": [], "deep": {"a": {"b": {"c": [{"d": np.nan, "e": [1, 2]}]}}},
    }
    expected = without_nulls(jsonable(value))
    got = json_message(value)
    assert got == expected and list(got) == list(expected)
    assert json.dumps(got) == json.dumps(expected)
    assert json_message({1: "one", "1": None}) == without_nulls(jsonable({1: "one", "1": None}))
    for scalar in (1, 1.5, float("nan"), None, "s", True, np.float64(2.0), [1, None]):
        assert json_message(scalar) == without_nulls(jsonable(scalar))
