"""The live view (``slam --live``): a WebSocket client connected to a run on the synthetic sequence gets
the log's channels with the log's schemas, and the messages it decodes are the log's; with no client the
log is the same as without ``--live``; SIGTERM closes the server and finalises the log. Loopback only,
every wait bounded."""

from __future__ import annotations

import base64
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from ti_fusion.backend import current_backend
from ti_fusion.cli.main import main
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.live import LiveServer, parse_address
from ti_fusion.io.mcap_log import points_from_msg, pose_from_msg, read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.slam.pipeline import SLAMPipeline

websockets = pytest.importorskip("websockets.sync.client")

# Foxglove's app offers both names; the SDK's server takes the second, the same protocol renamed.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
WAIT_S = 120  # the most any one wait below takes before the test fails (compiling kernels: seconds)


class Client(threading.Thread):
    """A Foxglove WebSocket client: subscribes to every channel it is told of (or to ``topics``), keeps
    what arrives as (topic, log time ns, payload bytes)."""

    def __init__(self, url: str, topics: tuple[str, ...] | None = None):
        super().__init__(daemon=True)
        self.url, self.topics = url, topics
        self.channels: dict[int, dict] = {}  # channel id → the advertised channel
        self.messages: list[tuple[str, int, bytes]] = []
        self.times: list[int] = []  # the server's time messages, ns
        self.server_info: dict | None = None
        self.subprotocol = None
        self.closed = threading.Event()
        self.error: BaseException | None = None
        self._subscriptions: dict[int, str] = {}  # subscription id → topic
        self.refusals: list[str] = []  # the server's "Unknown channel ID" statuses
        self._retries = 100
        self._changed = threading.Condition()

    def run(self) -> None:
        try:
            with websockets.connect(self.url, subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=WAIT_S) as ws:
                self.subprotocol = ws.subprotocol
                for frame in ws:
                    if isinstance(frame, str):
                        self._control(ws, json.loads(frame))
                    elif frame[0] == 1:  # message data: subscription id u32, log time u64, payload
                        sub, ns = struct.unpack_from("<IQ", frame, 1)
                        with self._changed:
                            self.messages.append((self._subscriptions[sub], ns, bytes(frame[13:])))
                            self._changed.notify_all()
                    elif frame[0] == 2:  # time: u64 ns
                        with self._changed:
                            self.times.append(struct.unpack_from("<Q", frame, 1)[0])
                            self._changed.notify_all()
        except websockets.ConnectionClosed:
            pass
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc
        finally:
            self.closed.set()
            with self._changed:
                self._changed.notify_all()

    def _control(self, ws, message: dict) -> None:
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            for channel in message["channels"]:
                self.channels[channel["id"]] = channel
            wanted = [c for c in message["channels"] if self.topics is None or c["topic"] in self.topics]
            self._subscribe(ws, wanted)
        elif message["op"] == "status" and message["message"].startswith("Unknown channel ID:"):
            # the SDK can refuse a subscription sent the instant a channel appears: ask again (unless told,
            # as Foxglove, not to)
            self.refusals.append(message["message"])
            channel = self.channels.get(int(message["message"].rsplit(":", 1)[1]))
            if channel is not None and self._retries > 0:
                self._retries -= 1
                time.sleep(0.01)
                self._subscribe(ws, [channel])

    def _subscribe(self, ws, channels: list[dict]) -> None:
        subscribe = []
        for channel in channels:
            sub = len(self._subscriptions) + 1
            self._subscriptions[sub] = channel["topic"]
            subscribe.append({"id": sub, "channelId": channel["id"]})
        if subscribe:
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subscribe}))

    def wait_for(self, condition, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        with self._changed:
            while not condition():
                left = deadline - time.monotonic()
                if left <= 0 or self.closed.is_set():
                    raise AssertionError(f"the live client: no {what} within {WAIT_S} s (error: {self.error!r})")
                self._changed.wait(min(left, 0.05))

    def received(self, topic: str) -> list[tuple[int, bytes]]:
        return [(ns, data) for t, ns, data in self.messages if t == topic]

    def stats_frames(self, topic: str = "/slam/stats") -> set[int]:
        return {json.loads(data)["frame"] for _, data in self.received(topic)}

    def schema(self, topic: str) -> Schema:
        """The advertised schema as an MCAP schema record (protobuf schemas travel base64-encoded)."""
        (channel,) = [c for c in self.channels.values() if c["topic"] == topic]
        data = channel["schema"].encode()
        if channel["schemaEncoding"] == "protobuf":
            data = base64.b64decode(data)
        return Schema(id=channel["id"], name=channel["schemaName"], encoding=channel["schemaEncoding"], data=data)


def _config(frames: int) -> Config:
    cfg = Config()
    cfg.dataset.downsample, cfg.dataset.stop = 4, frames
    cfg.log.progress, cfg.log.depth_every, cfg.log.map_every = False, 3, 4
    return cfg


def _file_messages(path: Path) -> dict[str, dict[int, bytes]]:
    """topic → {log time ns: payload} of a log, and its schemas by topic."""
    out: dict[str, dict[int, bytes]] = {}
    schemas: dict[str, Schema] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            out.setdefault(channel.topic, {})[message.log_time] = message.data
            schemas[channel.topic] = schema
    return out, schemas


def test_parse_address():
    assert parse_address("8765") == ("127.0.0.1", 8765)
    assert parse_address("0") == ("127.0.0.1", 0)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address("localhost:1") == ("localhost", 1)
    assert parse_address("[::1]:8765") == ("::1", 8765)
    for bad in ("", "abc", "host:", ":80", "70000", "1.2.3.4:-1"):
        with pytest.raises(InputError, match="expected \\[HOST:\\]PORT"):
            parse_address(bad)


def test_a_taken_port_is_one_line(tmp_path, capsys):
    first = LiveServer("127.0.0.1:0")
    try:
        with pytest.raises(InputError, match=f"cannot serve on 127.0.0.1:{first.port}"):
            LiveServer(f"127.0.0.1:{first.port}")
    finally:
        first.close()
    assert main(["slam", "--live", "nope", "--frames", "2", "--downsample", "8", "--quiet",
                 "--out", str(tmp_path / "run")]) == 2
    assert "--live nope: expected [HOST:]PORT" in capsys.readouterr().err


@pytest.mark.slow
def test_a_live_run_sends_what_it_logs(cpu, tmp_path):
    """A client subscribed to every channel decodes the run's messages: the same schemas as the file, the
    same bytes at the same log times, and live maps of at most the live bound. The run waits for the
    client before each frame (its subscriptions to every channel, advertised when the log opens, and the
    last frame's stats), and the server's close waits for the trajectory logged as the run closes (closing
    gives a client's queue a fixed time to drain, which a loaded machine can miss), so what arrives does not
    depend on timing; the last frame and the final map, sent before the trajectory, are checked as they
    arrived."""
    frames = 8
    cfg = _config(frames)
    dataset = open_dataset(cfg.dataset, cfg.synth)
    live = LiveServer("127.0.0.1:0", max_points=500)
    client = Client(live.url)
    client.start()
    run = RunDir("slam", tmp_path / "run")
    pipeline = SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False, live=live)
    register = pipeline.step.register_frame

    def after_the_client(frame):
        client.wait_for(lambda: all(live.subscribed(t) for t in live.topics), "subscription to every channel")
        if frame.index > 0:
            client.wait_for(lambda: frame.index - 1 in client.stats_frames(), f"stats of frame {frame.index - 1}")
        return register(frame)

    pipeline.step.register_frame = after_the_client
    close = live.close

    def after_the_trajectory():  # the last message the log sends (one queue per client: the rest came before it)
        client.wait_for(lambda: client.received("/trajectory"), "trajectory logged as the run closes")
        close()

    live.close = after_the_trajectory
    pipeline.run()
    client.join(WAIT_S)
    assert not client.is_alive() and client.error is None  # the server closed the connection
    assert client.subprotocol == "foxglove.sdk.v1"
    assert live.closed

    in_file, schemas = _file_messages(run.file("log.mcap"))
    advertised = {c["topic"] for c in client.channels.values()}
    assert set(in_file) == {"/tf", "/camera/pose", "/gt/pose", "/slam/stats", "/map/points", "/camera/depth",
                            "/camera/color", "/camera/calibration", "/trajectory"}
    assert advertised == set(in_file) | {"/map/mesh", "/loop_closures", "/loop_closures/refused"}  # before logged
    assert client.received("/trajectory")  # logged as the run closes
    for topic in set(in_file):  # the same schema records: name, encoding and bytes
        schema = client.schema(topic)
        assert (schema.name, schema.encoding, schema.data) == (
            schemas[topic].name, schemas[topic].encoding, schemas[topic].data), topic

    times = [int(round(t * 1e9)) for t in read_log(run.file("log.mcap")).stats_times]
    for topic in set(in_file) - {"/map/points"}:  # every message received is the file's, at its time
        for ns, data in client.received(topic):
            assert in_file[topic].get(ns) == data, (topic, ns)
    assert set(range(frames - 1)) <= client.stats_frames()
    for topic in ("/tf", "/camera/pose", "/gt/pose"):
        assert set(times[:-1]) <= {ns for ns, _ in client.received(topic)}, topic
    for topic in ("/camera/depth", "/camera/color"):
        assert {times[0], times[3], times[6]} <= {ns for ns, _ in client.received(topic)}, topic
    assert times[0] in {ns for ns, _ in client.received("/camera/calibration")}

    # Decoded with the advertised schemas alone: stats as the file has them, poses as read_log reads them.
    log = read_log(run.file("log.mcap"))
    stats = {json.loads(d)["frame"]: json.loads(d) for _, d in client.received("/slam/stats")}
    for frame, message in stats.items():
        assert message == log.stats[frame]
    decode = DecoderFactory().decoder_for("protobuf", client.schema("/camera/pose"))
    for ns, data in client.received("/camera/pose"):
        np.testing.assert_array_equal(pose_from_msg(decode(data)), log.est_poses[times.index(ns)])
    decode = DecoderFactory().decoder_for("protobuf", client.schema("/map/points"))
    clouds = [decode(data) for _, data in client.received("/map/points")]
    assert clouds and client.received("/map/points")[0][0] == times[0]  # the first live map: frame 0
    for cloud in clouds:
        xyz, rgba = points_from_msg(cloud)
        assert 0 < len(xyz) <= 500 and rgba is not None and cloud.frame_id == "world"
        assert cloud.pose.HasField("position") and cloud.pose.orientation.w == 1.0


@pytest.mark.slow
def test_no_client_costs_no_map_and_changes_no_log(cpu, tmp_path):
    """With --live and nobody connected, the map is sampled for the file only, and the log holds what a run
    without --live writes."""
    counts = {}
    for name, live in (("plain", None), ("live", LiveServer("127.0.0.1:0"))):
        cfg = _config(6)
        run = RunDir("slam", tmp_path / name)
        pipeline = SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, run, current_backend(),
                                show_progress=False, live=live)
        sample = pipeline.step.map_points
        calls = []
        pipeline.step.map_points = lambda n: calls.append(n) or sample(n)
        pipeline.run()
        log = read_log(run.file("log.mcap"))
        counts[name] = ({t: c.count for t, c in log.channels.items()}, len(calls))
    assert counts["live"][0] == counts["plain"][0]
    assert counts["live"][1] == counts["plain"][1]


def test_a_late_client_gets_the_calibration(tmp_path):
    """/camera/calibration is logged once: a client that subscribes later gets it again, at its log time."""
    from ti_fusion.camera import Intrinsics
    from ti_fusion.io.mcap_log import RunLogger

    live = LiveServer("127.0.0.1:0")
    path = tmp_path / "log.mcap"
    with RunLogger(path, live=live) as log:
        log.log_calibration(1.5, Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480))
        client = Client(live.url, topics=("/camera/calibration", "/camera/pose"))
        client.start()
        client.wait_for(lambda: live.subscribed("/camera/calibration") and live.subscribed("/camera/pose"),
                        "subscriptions")
        log.log_pose(2.0, np.eye(4))  # the next message sends it
        client.wait_for(lambda: client.received("/camera/calibration"), "calibration")
    client.join(WAIT_S)
    in_file, _ = _file_messages(path)
    assert client.received("/camera/calibration") == [(1_500_000_000, in_file["/camera/calibration"][1_500_000_000])]


def test_the_clients_time_is_the_dataset_time(tmp_path):
    """The server has the time capability and sends each new log time: a client's timeline runs on the
    dataset's time, as the file's does."""
    from ti_fusion.io.mcap_log import RunLogger

    live = LiveServer("127.0.0.1:0")
    with RunLogger(tmp_path / "log.mcap", live=live) as log:
        client = Client(live.url, topics=("/camera/pose",))
        client.start()
        client.wait_for(lambda: live.subscribed("/camera/pose"), "subscription")
        for t in (1.5, 1.5, 2.25):
            log.log_pose(t, np.eye(4))
        log.log_stats(2.25, {"frame": 0})
        client.wait_for(lambda: len(client.received("/camera/pose")) == 3 and 2_250_000_000 in client.times,
                        "poses and times")
    client.join(WAIT_S)
    assert "time" in client.server_info["capabilities"]
    assert client.times == [1_500_000_000, 2_250_000_000]  # once per new time, in order


def test_a_refused_client_is_one_line(tmp_path, caplog):
    """A client that offers only the old sub-protocol (Foxglove Studio, Lichtblick before 1.22.1) is refused
    with HTTP 400 at every retry; the terminal gets one warning that names the protocol and the clients,
    not the SDK's line per retry."""
    import logging

    from websockets.exceptions import InvalidStatus

    other = LiveServer("127.0.0.1:0")  # another server open in the process (a record does not say which refused)
    live = LiveServer("127.0.0.1:0")
    try:
        with caplog.at_level(logging.INFO):
            for _ in range(3):
                with pytest.raises(InvalidStatus, match="400"):
                    websockets.connect(live.url, subprotocols=["foxglove.websocket.v1"], open_timeout=WAIT_S)
            deadline = time.monotonic() + WAIT_S  # the SDK logs from its own thread, after the refusal
            while live.refused < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            client = Client(live.url, topics=())  # a current client still connects
            client.start()
            client.wait_for(lambda: client.server_info is not None, "server info")
    finally:
        live.close()
        other.close()
    client.join(WAIT_S)
    assert live.refused == 3
    refused = [r for r in caplog.records if "refused" in r.getMessage() or "Dropping" in r.getMessage()]
    assert len(refused) == 1 and refused[0].levelno == logging.WARNING and refused[0].name == "ti_fusion.io.live"
    assert "foxglove.sdk.v1" in refused[0].getMessage() and "Lichtblick 1.22.1" in refused[0].getMessage()


@pytest.mark.slow
def test_sigterm_closes_the_server_and_finalises_the_log(tmp_path):
    """``ti-fusion slam --live``: a client gets stats while the run goes; SIGTERM ends the run with 143, the
    client sees the connection close, and the log is finalised with what the client got."""
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "ti_fusion", "slam", "--live", "127.0.0.1:0", "--frames", "1000",
                             "--downsample", "4", "--quiet", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = _read_line(proc, "live: ", WAIT_S)
        client = Client(line.split()[1], topics=("/slam/stats",))
        client.start()
        client.wait_for(lambda: len(client.stats_frames()) >= 2, "two stats messages")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(WAIT_S) == 128 + signal.SIGTERM
        client.join(WAIT_S)
        assert not client.is_alive() and client.error is None
        assert "stopped by SIGTERM" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    log = read_log(out / "log.mcap")
    assert log.complete and len(log.stats) < 1000
    in_file, _ = _file_messages(out / "log.mcap")
    for ns, data in client.received("/slam/stats"):
        assert in_file["/slam/stats"][ns] == data


def _read_line(proc: subprocess.Popen, prefix: str, timeout: float) -> str:
    """The first line of the process's stdout that starts with ``prefix`` (read on a thread: bounded)."""
    found: list[str] = []

    def read():
        for line in proc.stdout:
            if line.startswith(prefix):
                found.append(line.strip())
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    if not found:
        raise AssertionError(f"no '{prefix}' line within {timeout} s; stderr: {proc.stderr.read() if proc.poll() is not None else ''}")
    return found[0]


# --------------------------------------------------------------------------------------------------
# Clients that misbehave, channels logged at the end, serving the network
# --------------------------------------------------------------------------------------------------
def test_a_client_that_never_reads_does_not_hold_the_end_of_the_run(tmp_path, caplog):
    """A client subscribes to everything, then stops reading (its socket fills): the run's messages are
    dropped for it (a bounded queue), and closing the log stops the server without waiting for that client's
    close handshake, which never comes (the SDK's stop alone waited until the client went away)."""
    import logging

    from ti_fusion.io.live import CLOSE_TIMEOUT_S
    from ti_fusion.io.mcap_log import RunLogger

    live = LiveServer("127.0.0.1:0")
    with websockets.connect(live.url, subprotocols=SUBPROTOCOLS, max_size=None, max_queue=1, open_timeout=WAIT_S,
                            close_timeout=1) as ws:
        channels = {}
        while len(channels) < len(live.topics):  # serverInfo, then the advertisements
            message = json.loads(ws.recv(timeout=WAIT_S))
            channels.update({c["id"]: c for c in message.get("channels", [])})
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": i} for i in channels]}))
        deadline = time.monotonic() + WAIT_S
        while not all(live.subscribed(t) for t in live.topics) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert all(live.subscribed(t) for t in live.topics)
        depth = np.random.default_rng(0).uniform(0.5, 4.0, (240, 320)).astype(np.float32)
        log = RunLogger(tmp_path / "log.mcap", live=live)
        for i in range(300):  # 300 depth images of 150 kB: far more than the socket's buffers hold
            log.log_pose(i, np.eye(4))
            log.log_depth(i, depth)
        closing = threading.Thread(target=log.close)
        with caplog.at_level(logging.WARNING, logger="ti_fusion.io.live"):
            closing.start()
            closing.join(WAIT_S)  # a bound for a broken close; it takes CLOSE_TIMEOUT_S and the linger
        assert not closing.is_alive() and live.closed
    assert read_log(tmp_path / "log.mcap").complete
    assert [r.getMessage() for r in caplog.records] == [
        f"live: a client did not take what was sent to it: stopped serving without waiting for it "
        f"(after {CLOSE_TIMEOUT_S:g} s)"]


def test_channels_logged_at_the_end_reach_a_client_that_subscribed_at_once(tmp_path):
    """Every channel a run logs is advertised before a client can connect, so a client that subscribes to
    what it is told at once, and never asks again (as Foxglove does), has no subscription refused, and gets
    the trajectory and the mesh that are logged as the run ends."""
    from ti_fusion.io.mcap_log import RunLogger
    from ti_fusion.mapping.mesh import Mesh

    live = LiveServer("127.0.0.1:0")
    client = Client(live.url)
    client._retries = 0
    client.start()  # connects before the log opens: the moment of the race
    client.wait_for(lambda: {c["topic"] for c in client.channels.values()} >= {"/tf", "/trajectory", "/map/mesh"},
                    "advertisements before the log opens")
    client.wait_for(lambda: all(live.subscribed(t) for t in live.topics), "subscriptions")
    close = live.close

    def after_they_arrive():  # (closing gives a client's queue a fixed time to drain: not what is tested here)
        client.wait_for(lambda: all(client.received(t) for t in ("/tf", "/trajectory", "/map/mesh")),
                        "the channels logged at the end")
        close()

    live.close = after_they_arrive
    mesh = Mesh(vertices=np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32), faces=np.array([[0, 1, 2]]),
                normals=np.tile(np.float32([0, 0, -1]), (3, 1)), colors=np.full((3, 3), 200, np.uint8))
    with RunLogger(tmp_path / "log.mcap", live=live) as log:
        for i in range(3):
            log.log_pose(i, np.eye(4))
        log.log_trajectory(2, [np.eye(4)] * 3)
        log.log_mesh(2, mesh)
    client.join(WAIT_S)
    assert client.error is None and client.refusals == []
    in_file, _ = _file_messages(tmp_path / "log.mcap")
    for topic in ("/tf", "/trajectory", "/map/mesh"):
        assert client.received(topic) and all(in_file[topic][ns] == data for ns, data in client.received(topic)), topic


@pytest.mark.slow
def test_every_interface_warns_and_gives_urls_a_client_can_use(cpu, tmp_path, capsys):
    """--live 0.0.0.0:PORT serves the network: the run warns, and prints URLs a client can use (this
    machine's addresses), not ws://0.0.0.0."""
    live = LiveServer("0.0.0.0:0")
    try:
        urls = live.urls()
        assert urls[0] == f"ws://127.0.0.1:{live.port}" and all("0.0.0.0" not in u for u in urls)
        for url in urls:  # each one connects
            client = Client(url, topics=())
            client.start()
            client.wait_for(lambda: client.server_info is not None, f"server info at {url}")
    finally:
        live.close()
    assert main(["slam", "--live", "0.0.0.0:0", "--frames", "2", "--downsample", "8", "--quiet",
                 "--out", str(tmp_path / "run")]) == 0
    captured = capsys.readouterr()
    (warning,) = [line for line in captured.err.splitlines() if "live:" in line]
    assert warning.startswith("ti-fusion slam: warning: live: serving on every network interface (0.0.0.0): anyone")
    (line,) = [line for line in captured.out.splitlines() if line.startswith("live: ")]
    assert line.startswith("live: ws://127.0.0.1:") and "0.0.0.0" not in line and "from another machine: ws://" in line
