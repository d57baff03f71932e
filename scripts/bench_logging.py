"""What logging costs: today's MCAP writer against Foxglove's SDK, and what the live view costs a run.

    .venv/bin/python scripts/bench_logging.py               # both parts, under a minute
    .venv/bin/python scripts/bench_logging.py --part log    # or --part live

Part "log": one run's messages, made from the synthetic sequence's frames at 640×480 (per frame /tf,
/camera/pose, /gt/pose and a /slam/stats message; every 10th frame depth and JPEG colour; every 30th a
200 000-point map), logged by each of
    file               RunLogger: the mcap package's writer, protobuf from foxglove-schemas-protobuf, written
                       by the log's writer thread (today)
    file, caller's thread  the same, written in the caller's thread (``RunLogger(threaded=False)``: before)
    file + live idle   RunLogger with a LiveServer and no client
    file + live client RunLogger with a LiveServer and a client in another process subscribed to everything
    sdk writer         foxglove-sdk's MCAP writer fed RunLogger's messages (same bytes, same schemas)
    sdk messages       foxglove-sdk's own message classes and MCAP writer: the whole SDK route
It prints the file size and milliseconds per frame that the caller spends in the calls (all messages; and per
call of each kind), and what ``close`` took (writing what was still queued, then the footer). The images
and the map are the same for every sink (JPEG encoding, subsampling and packing included in every time).

Part "live": ``slam`` on the synthetic sequence (320×240, frames rendered once beforehand) in this
process: frames per second of processing (the pipeline's fps_processing: its stages and logging, after
the warm-up frames) without a live server, with one and no client, and with a client in another process
subscribed to every channel (the map at most once a second, at most 50 000 points), then without again.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FRAMES = 300
REPEATS = 3
DEPTH_EVERY, MAP_EVERY, MAP_POINTS = 10, 30, 200_000

# A Foxglove WebSocket client in its own process: subscribes to every channel, counts what arrives, and
# prints the counts as JSON when the server closes.
CLIENT = r"""
import json, struct, sys, time
from websockets.sync.client import connect
subs, channels, counts, size = {}, {}, {}, 0
with connect(sys.argv[1], subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"], max_size=None) as ws:
    print("connected", flush=True)
    try:
        for m in ws:
            if isinstance(m, str):
                m = json.loads(m)
                if m["op"] == "advertise":
                    channels.update({c["id"]: c for c in m["channels"]})
                    wanted = m["channels"]
                elif m["op"] == "status" and m["message"].startswith("Unknown channel ID:"):
                    wanted = [channels[int(m["message"].rsplit(":", 1)[1])]]  # refused as it appeared: again
                    time.sleep(0.01)
                else:
                    continue
                new = [{"id": len(subs) + i + 1, "channelId": c["id"]} for i, c in enumerate(wanted)]
                subs.update({s["id"]: c["topic"] for s, c in zip(new, wanted)})
                ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif m[0] == 1:
                topic = subs[struct.unpack_from("<I", m, 1)[0]]
                counts[topic] = counts.get(topic, 0) + 1
                size += len(m)
    except Exception:
        pass
print(json.dumps({"messages": counts, "bytes": size}), flush=True)
"""


def start_client(url: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", CLIENT, url], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "connected"
    return proc


def client_counts(proc: subprocess.Popen) -> dict:
    out, _ = proc.communicate(timeout=30)
    return json.loads(out.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------------
# Part "log"


def workload():
    """The frames (depth, colour, poses) and a 300 000-point coloured cloud, from the synthetic sequence."""
    from ti_fusion.backend import init_backend
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.mapping.pointcloud import backproject

    init_backend("cpu")
    cfg = Config()
    cfg.dataset.stop = 10
    dataset = open_dataset(cfg.dataset, cfg.synth)
    frames = [dataset[i] for i in range(len(dataset))]
    xyz, rgb = backproject(frames[0].depth, frames[0].intrinsics, frames[0].color, 1)
    return frames, xyz.astype(np.float32), rgb


def slam_stats(i: int) -> dict:
    return {"frame": i, "status": "ok", "tracking": "ok", "surfels": 80000 + 100 * i,
            "ms": {"pyramid": 0.9, "track": 10.9, "fuse": 1.9, "log": 0.2, "load": 3.8},
            "icp": {"iterations": [2, 3, 2], "residual_rms_m": 0.0038, "inliers": 15705, "inlier_ratio": 0.944,
                    "condition": 82.8, "update_norm": 1.5e-05},
            "merged": 15401, "added": 193, "covered": 952, "removed": 0}


class Timer:
    def __init__(self):
        self.ms: dict[str, list[float]] = {}

    def __call__(self, kind: str, fn, *args, **kwargs):
        t0 = time.perf_counter()
        fn(*args, **kwargs)
        self.ms.setdefault(kind, []).append((time.perf_counter() - t0) * 1e3)


def run_logger(log, frames, xyz, rgb, timer: Timer, ready=lambda: None) -> None:
    """The pipeline's calls for FRAMES frames, each kind timed, after one untimed message of each kind (so
    that a live client can subscribe to every channel before the timing starts: ``ready``)."""
    from ti_fusion.slam.slam_step import STATS_SCHEMA

    log.declare_json("/slam/stats", STATS_SCHEMA)
    log.log_calibration(0.0, frames[0].intrinsics)
    f = frames[0]
    log.log_pose(0.5, f.gt_pose, f.gt_pose)
    log.log_depth(0.5, f.depth)
    log.log_image(0.5, f.color)
    log.log_points(0.5, xyz[:100], rgb[:100])
    ready()
    for i in range(FRAMES):
        f = frames[i % len(frames)]
        t = 1.0 + i / 30
        timer("pose", log.log_pose, t, f.gt_pose, f.gt_pose)
        if i % DEPTH_EVERY == 0:
            timer("depth", log.log_depth, t, f.depth)
            timer("color", log.log_image, t, f.color)
        if i > 0 and i % MAP_EVERY == 0:
            timer("map", log.log_points, t, xyz, rgb, max_points=MAP_POINTS)
        timer("stats", log.log_stats, t, slam_stats(i))


class SdkWriter:
    """The mcap Writer calls RunLogger makes, done by foxglove-sdk's MCAP writer (its channels carry
    RunLogger's schemas and bytes)."""

    def __init__(self, path: Path):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.fg = foxglove
        self.context = foxglove.Context()
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=64 * 1024)
        self.writer = foxglove.open_mcap(path, allow_overwrite=True, context=self.context, writer_options=options)
        self.schemas, self.channels = {}, {}

    def register_schema(self, name, encoding, data):
        self.schemas[len(self.schemas) + 1] = self.fg.Schema(name=name, encoding=encoding, data=data)
        return len(self.schemas)

    def register_channel(self, topic, message_encoding, schema_id):
        self.channels[len(self.channels) + 1] = self.fg.Channel(
            topic, schema=self.schemas[schema_id], message_encoding=message_encoding, context=self.context)
        return len(self.channels)

    def add_message(self, channel_id, log_time, data, publish_time):
        self.channels[channel_id].log(data, log_time=log_time)

    def add_metadata(self, name, data):
        self.writer.write_metadata(name, data)

    def finish(self):
        self.writer.close()


def sdk_logger(path: Path):
    """A RunLogger whose writer is the SDK's (the file it opened is left empty and removed)."""
    from ti_fusion.io.mcap_log import RunLogger

    log = RunLogger(path.with_suffix(".unused"), threaded=False)
    log._finalizer.detach()
    log._sink.file.close()
    path.with_suffix(".unused").unlink()
    log._sink.writer = SdkWriter(path)
    log._sink.file = type("NoFile", (), {"flush": lambda self: None})()  # the SDK writes and flushes its file
    log._finalizer = log._sink.writer.finish
    return log


def sdk_messages(path: Path, frames, xyz, rgb, timer: Timer) -> None:
    """The same run with the SDK's message classes and channels, no protobuf classes of ours."""
    import cv2
    import foxglove
    import foxglove.channels as ch
    import foxglove.messages as m
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    from ti_fusion.geometry import rot_to_quat
    from ti_fusion.io.mcap_log import _subset
    from ti_fusion.slam.slam_step import STATS_SCHEMA

    ctx = foxglove.Context()
    options = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=64 * 1024)
    writer = foxglove.open_mcap(path, allow_overwrite=True, context=ctx, writer_options=options)
    tf_ch, pose_ch = ch.FrameTransformsChannel("/tf", context=ctx), ch.PoseInFrameChannel("/camera/pose", context=ctx)
    gt_ch, depth_ch = ch.PoseInFrameChannel("/gt/pose", context=ctx), ch.RawImageChannel("/camera/depth", context=ctx)
    color_ch = ch.CompressedImageChannel("/camera/color", context=ctx)
    cloud_ch = ch.PointCloudChannel("/map/points", context=ctx)
    calib_ch = ch.CameraCalibrationChannel("/camera/calibration", context=ctx)
    stats_ch = foxglove.Channel("/slam/stats", schema=foxglove.Schema(
        name="ti_fusion.SlamStats", encoding="jsonschema", data=json.dumps(STATS_SCHEMA).encode()),
        message_encoding="json", context=ctx)

    def stamp(ns):
        return m.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def pose(T):
        q = rot_to_quat(T[:3, :3])
        return m.Pose(position=m.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                      orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))

    def log_pose(ns, T, G):
        q = rot_to_quat(T[:3, :3])
        tf_ch.log(m.FrameTransforms(transforms=[m.FrameTransform(
            timestamp=stamp(ns), parent_frame_id="world", child_frame_id="camera",
            translation=m.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))]), log_time=ns)
        pose_ch.log(m.PoseInFrame(timestamp=stamp(ns), frame_id="world", pose=pose(T)), log_time=ns)
        gt_ch.log(m.PoseInFrame(timestamp=stamp(ns), frame_id="world", pose=pose(G)), log_time=ns)

    def log_depth(ns, depth):
        mm = np.round(depth * 1000).astype("<u2")
        depth_ch.log(m.RawImage(timestamp=stamp(ns), frame_id="camera", width=mm.shape[1], height=mm.shape[0],
                                encoding="16UC1", step=2 * mm.shape[1], data=mm.tobytes()), log_time=ns)

    def log_image(ns, rgb_image):
        _, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb_image, cv2.COLOR_RGB2BGR))
        color_ch.log(m.CompressedImage(timestamp=stamp(ns), frame_id="camera", data=buf.tobytes(), format="jpeg"),
                     log_time=ns)

    def log_points(ns, xyz, rgb):  # as RunLogger.log_points: the subset, then packed
        idx = _subset(np.flatnonzero(np.isfinite(xyz.sum(axis=1))), MAP_POINTS)
        packed = np.empty(len(idx), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"),
                                           ("b", "u1"), ("a", "u1")])
        packed["x"], packed["y"], packed["z"] = xyz[idx].T
        packed["r"], packed["g"], packed["b"] = rgb[idx].T
        packed["a"] = 255
        F, U = m.PackedElementFieldNumericType.Float32, m.PackedElementFieldNumericType.Uint8
        fields = [m.PackedElementField(name=n, offset=o, type=k) for n, o, k in (
            ("x", 0, F), ("y", 4, F), ("z", 8, F), ("red", 12, U), ("green", 13, U), ("blue", 14, U),
            ("alpha", 15, U))]
        cloud_ch.log(m.PointCloud(timestamp=stamp(ns), frame_id="world", pose=pose(np.eye(4)), point_stride=16,
                                  fields=fields, data=packed.tobytes()), log_time=ns)

    K = frames[0].intrinsics
    calib_ch.log(m.CameraCalibration(frame_id="camera", width=K.width, height=K.height, distortion_model="plumb_bob",
                                     D=[0.0] * 5, K=[K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1],
                                     R=[1, 0, 0, 0, 1, 0, 0, 0, 1], P=[K.fx, 0, K.cx, 0, 0, K.fy, K.cy, 0, 0, 0, 1, 0]),
                 log_time=0)
    f = frames[0]
    log_pose(500_000_000, f.gt_pose, f.gt_pose)
    log_depth(500_000_000, f.depth)
    log_image(500_000_000, f.color)
    log_points(500_000_000, xyz[:100], rgb[:100])
    for i in range(FRAMES):
        f = frames[i % len(frames)]
        ns = int(round((1.0 + i / 30) * 1e9))
        timer("pose", log_pose, ns, f.gt_pose, f.gt_pose)
        if i % DEPTH_EVERY == 0:
            timer("depth", log_depth, ns, f.depth)
            timer("color", log_image, ns, f.color)
        if i > 0 and i % MAP_EVERY == 0:
            timer("map", log_points, ns, xyz, rgb)
        timer("stats", lambda: stats_ch.log(json.dumps(slam_stats(i), separators=(",", ":")).encode(), log_time=ns))
    writer.close()


def part_log(tmp: Path) -> None:
    from ti_fusion.io.live import LiveServer
    from ti_fusion.io.mcap_log import RunLogger, read_log

    frames, xyz, rgb = workload()
    runs: dict[str, list] = {}
    sinks = ("file", "file, caller's thread", "file + live idle", "file + live client", "sdk writer", "sdk messages")
    for name in sinks * REPEATS:  # round robin: a busy moment of the machine spreads over every sink
        path = tmp / f"{name.replace(' ', '_').replace('+', '')}.mcap"
        timer, client = Timer(), None
        if name == "sdk messages":
            sdk_messages(path, frames, xyz, rgb, timer)
        else:
            live = LiveServer("127.0.0.1:0") if "live" in name else None
            log = sdk_logger(path) if name == "sdk writer" else \
                RunLogger(path, live=live, threaded=name != "file, caller's thread")

            def ready():
                nonlocal client
                if name == "file + live client":  # the client subscribes to every channel before the timing
                    client = start_client(live.url)
                    deadline = time.monotonic() + 10
                    while not all(live.subscribed(t) for t in live.topics) and time.monotonic() < deadline:
                        time.sleep(0.01)

            run_logger(log, frames, xyz, rgb, timer, ready)
            timer("close", log.close)  # what the writer thread has yet to write, then the footer
        received = client_counts(client) if client is not None else None
        readable = read_log(path)  # today's reader reads every file
        runs.setdefault(name, []).append((path.stat().st_size / 1e6, timer.ms, readable.complete,
                                          len(readable.stats), received))
    print(f"logging {FRAMES} frames at 640x480 (depth + colour every {DEPTH_EVERY}, a {MAP_POINTS}-point map "
          f"every {MAP_EVERY}), median of {REPEATS} runs:")
    print(f"  {'sink':<22} {'file MB':>8} {'ms/frame':>9}   ms per call: pose  stats  depth colour    map  close   "
          "read_log")
    for name in sinks:
        mb, _, complete, n_stats, received = runs[name][-1]
        ms = statistics.median(sum(sum(v) for k, v in timings.items() if k != "close") / FRAMES
                               for _, timings, *_ in runs[name])
        per_call = {k: statistics.median(statistics.mean(t[k]) for _, t, *_ in runs[name]) for k in runs[name][0][1]}
        calls = "  ".join(f"{per_call.get(k, 0):5.2f}" for k in ("pose", "stats", "depth", "color", "map", "close"))
        note = f"complete, {n_stats} stats" if complete else "NOT complete"
        if received:
            note += f"; client got {sum(received['messages'].values())} messages, {received['bytes'] / 1e6:.0f} MB"
        print(f"  {name:<22} {mb:8.2f} {ms:9.3f}   {' ' * 13}{calls}   {note}")


# --------------------------------------------------------------------------------------------------
# Part "live"


class Rendered:
    """A dataset's first ``n`` frames, read once and kept (the synthetic renderer is slower than SLAM)."""

    def __init__(self, dataset, n: int | None = None):
        self.dataset = dataset
        self.frames = [dataset[i] for i in range(n or len(dataset))]

    def __getattr__(self, name):
        return getattr(self.dataset, name)

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        return self.frames[i]


def part_live(tmp: Path, frames: int) -> None:
    from ti_fusion.backend import current_backend, init_backend
    from ti_fusion.config import Config
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.live import LiveServer
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    if current_backend() is None:
        init_backend("cpu")
    cfg = Config()
    cfg.dataset.downsample, cfg.dataset.stop = 2, frames
    rendered = Rendered(open_dataset(cfg.dataset, cfg.synth))  # every run gets the same frames, rendered once
    results = []
    runs = ("warm-up", "no --live", "--live, no client", "--live, client", "no --live")
    for k, name in enumerate(runs):
        cfg.log.progress = False
        # the warm-up compiles what the first frames do not (the map's sampling at frame 30) and is not shown
        dataset = Rendered(rendered, min(frames, 31)) if name == "warm-up" else rendered
        live = LiveServer("127.0.0.1:0") if "--live," in name else None
        client = start_client(live.url) if name == "--live, client" else None
        run = RunDir("slam", tmp / f"run{k}")
        summary = SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False, live=live).run()
        run.release()
        received = client_counts(client) if client is not None else None
        ms = summary["ms_per_stage"]
        if name != "warm-up":
            results.append((name, summary["fps_processing"], ms["log"]["median"], ms["log"]["max"], received))
    print(f"\nslam on the synthetic sequence, {frames} frames at 320x240 (cpu), frames after the warm-up:")
    print(f"  {'run':<20} {'fps processing':>15} {'ms log median':>14} {'max':>7}")
    for name, fps, log_ms, log_max, received in results:
        note = ""
        if received:
            note = (f"   client got {sum(received['messages'].values())} messages "
                    f"({received['messages'].get('/map/points', 0)} maps), {received['bytes'] / 1e6:.1f} MB")
        print(f"  {name:<20} {fps:15.1f} {log_ms:14.3f} {log_max:7.2f}{note}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("log", "live", "both"), default="both")
    parser.add_argument("--frames", type=int, default=60, help="frames of each slam run in part live")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_logging_") as tmp:
        if args.part in ("log", "both"):
            part_log(Path(tmp))
        if args.part in ("live", "both"):
            part_live(Path(tmp), args.frames)


if __name__ == "__main__":
    main()
