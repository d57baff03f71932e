"""Run logs in MCAP, laid out so that Foxglove's 3D, Image and Plot panels need no set-up.

Channels (log time = the frame's dataset timestamp; ``docs/LOGS.md`` has the full table):

    /tf                 foxglove.FrameTransforms   protobuf  world → camera, once per frame
    /camera/pose        foxglove.PoseInFrame       protobuf  estimated camera-to-world pose, frame "world"
    /gt/pose            foxglove.PoseInFrame       protobuf  ground truth, when the dataset has it
    /slam/stats         ti_fusion.SlamStats        json      one dict per frame, its JSON Schema declared
    /map/points         foxglove.PointCloud        protobuf  x,y,z float32 + red,green,blue,alpha uint8
    /camera/depth       foxglove.RawImage          protobuf  16UC1, millimetres, 0 = no depth
    /camera/color       foxglove.CompressedImage   protobuf  jpeg (or png)
    /camera/calibration foxglove.CameraCalibration protobuf  pinhole K, P
    /loop_closures      foxglove.SceneUpdate       protobuf  loop closures applied: one LINE_LIST, frame "world"
    /loop_closures/refused foxglove.SceneUpdate    protobuf  loop candidates not applied: one LINE_LIST
    /map/mesh           foxglove.SceneUpdate       protobuf  slam --mesh: the mesh as one TRIANGLE_LIST, frame "world"
    /trajectory         foxglove.PosesInFrame      protobuf  at the end: every pose as trajectory.tum has it (after
                                                             loop closure's corrections), frame "world"

Why this encoding. The geometry channels use Foxglove's official protobuf schemas from
``foxglove-schemas-protobuf``: the schema names are the ones Foxglove recognises, the messages are
compact binary (a 200 000-point cloud is 3.2 MB of packed floats, not base64 text inside JSON), the
file carries the FileDescriptorSet so any reader can decode it without our code, and the generated
classes catch field typos when we write. The stats channels are different: their fields change as the
SLAM loop and the feature odometry grow, and a protobuf message for them would have to be compiled and
versioned each time. They are plain JSON (message encoding ``json``, schema encoding ``jsonschema``):
the command declares each one's JSON Schema before its first message (``declare_json``), so Foxglove
autocompletes every message path in the Plot panel and a test validates every message against it. MCAP
allows a different encoding per channel, so one file mixes both.
Depth is 16UC1 millimetres: half the size of 32FC1, lossless for 7-Scenes (TUM's 0.2 mm steps round to 1 mm).

Two sinks, one path. With a live sink (``ti_fusion.io.live.LiveServer``) every message that goes into
the file also goes, as the same bytes on a channel with the same schema, to the Foxglove WebSocket
clients subscribed to its topic; with no client subscribed a message costs the live sink one set
look-up. Map clouds are the exception: the live view gets its own, smaller and at a bounded rate
(``log_points(..., file=False)``), so that watching a run does not slow it.

Crash safety. ``RunLogger`` is a context manager that writes the summary and footer on normal exit,
on an exception and on Ctrl-C (KeyboardInterrupt passes through ``__exit__``); a logger left open
is also finalised when it is garbage-collected or the interpreter exits. If the process is killed
hard (SIGKILL, power loss) the footer is missing: ``mcap.reader.make_reader(...).iter_messages()``
then fails (it seeks to the footer), but every chunk already on disk is intact. Chunks are kept
small (64 KiB by default) and the file is flushed after every message, so a killed run loses at most
the last open chunk and the messages still queued for the writer thread (``QUEUE_SIZE``; see
``RunLogger``). ``read_log`` below reads linearly, stops cleanly at a torn chunk and reports
``complete=False`` — the same thing ``mcap recover`` (the Go CLI) does.
"""

from __future__ import annotations

import json
import math
import os
import platform
import queue
import sys
import threading
import warnings
import weakref
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import build_file_descriptor_set

from ti_fusion.errors import InputError, OutputError, displayable
from ti_fusion.geometry import quat_to_rot, rot_to_quat
from ti_fusion.interrupts import critical
from ti_fusion.io.outputs import jsonable

WORLD_FRAME = "world"
CAMERA_FRAME = "camera"
STATS_TOPIC = "/slam/stats"
LOOP_TOPIC = "/loop_closures"
# The candidates not applied have a topic of their own, which the layout hides: a lap has hundreds of them, and
# Foxglove draws translucent lines after opaque ones, so even thin and faint they bury the map and the loop closed.
LOOP_REFUSED_TOPIC = "/loop_closures/refused"
LOOP_ENTITY = "loop_closures"  # one entity per topic, replaced by each message: it holds every edge so far
LOOP_REFUSED_ENTITY = "loop_closures_refused"
# RGBA in [0, 1]: loop closures applied green and thick, candidates not applied red, thin and faint
LOOP_APPLIED_RGBA = (0.17, 0.80, 0.25, 1.0)
LOOP_NOT_APPLIED_RGBA = (0.90, 0.15, 0.15, 0.3)
LOOP_APPLIED_PX, LOOP_NOT_APPLIED_PX = 3.0, 1.0  # line widths, pixels at any zoom
# A loop's two keyframes are close (it joins the return to the start): its line alone is a few pixels under the
# trajectory and the candidates' lines in Foxglove, so a sphere (diameter, metres) marks each end as well.
LOOP_APPLIED_END_M = 0.12
MESH_TOPIC = "/map/mesh"
TRAJECTORY_TOPIC = "/trajectory"
MESH_ENTITY = "mesh"
JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
MCAP_MAGIC = b"\x89MCAP0\r\n"

# The channels of the log_* methods, by their default topics.
LIVE_CHANNELS = {"/tf": FrameTransforms, "/camera/pose": PoseInFrame, "/gt/pose": PoseInFrame,
                 "/camera/calibration": CameraCalibration, "/camera/depth": RawImage,
                 "/camera/color": CompressedImage, "/map/points": PointCloud, "/trajectory": PosesInFrame,
                 "/map/mesh": SceneUpdate, LOOP_TOPIC: SceneUpdate, LOOP_REFUSED_TOPIC: SceneUpdate}


def live_channel_specs() -> list[tuple[str, str, str, str, bytes]]:
    """(topic, message encoding, schema name, schema encoding, schema bytes) of each of LIVE_CHANNELS."""
    return [(topic, MessageEncoding.Protobuf, message_type.DESCRIPTOR.full_name, SchemaEncoding.Protobuf,
             build_file_descriptor_set(message_type).SerializeToString())
            for topic, message_type in LIVE_CHANNELS.items()]

# Small chunks: a run killed with SIGKILL loses at most one open chunk (about 90 frames of poses and
# stats; big messages such as depth images and point clouds close a chunk on their own).
DEFAULT_CHUNK_SIZE = 64 * 1024
_POINTS_SEED = 0  # fixed: the same cloud is always downsampled to the same points


def software_versions() -> dict[str, str]:
    """Versions worth recording in the ``versions`` metadata record (read without importing Taichi)."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for dist in ("ti-fusion", "taichi", "numpy", "opencv-python-headless", "mcap",
                 "mcap-protobuf-support", "foxglove-schemas-protobuf", "protobuf"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            pass
    return out


def json_object(properties: dict[str, dict], required: tuple[str, ...] = (), description: str = "") -> dict:
    """A JSON Schema object with these properties and no others (a field that a message gains without its
    schema fails validation), the ``required`` ones in every message."""
    if not isinstance(properties, dict) or not properties:
        raise ValueError("a JSON object needs its properties: Foxglove cannot read an object without them")
    missing = [name for name in required if name not in properties]
    if missing:
        raise ValueError(f"required fields {missing} are not among the object's properties")
    schema = {"type": "object", "properties": properties, "required": list(required),
              "additionalProperties": False}
    return {"description": description, **schema} if description else schema


def json_field(kind: str, description: str, **extra) -> dict:
    """A JSON Schema leaf: ``kind`` "integer", "number", "string", "boolean", or "array" with typed
    ``items`` (a leaf's ``{"type": ...}`` or a ``json_object``); one type, never a union such as ["number",
    "null"]: a value that may be missing (None, NaN, infinite) is left out of the message instead
    (``log_stats``), so the field is not required. Units go in the description unless the name has them."""
    if kind not in FOXGLOVE_LEAF_TYPES and kind != "array":
        raise ValueError(f"field type {kind!r}: one of {FOXGLOVE_LEAF_TYPES + ('array',)} (objects: json_object)")
    if (kind == "array") != ("items" in extra):
        raise ValueError("an array field needs its items' schema, and only an array has items")
    schema = {"type": kind, "description": description, **extra}
    problems = foxglove_schema_problems({"type": "object", "properties": {"field": schema}})
    if problems:
        raise ValueError(problems[0])
    return schema


# Foxglove's and Lichtblick's parseJsonSchema (packages/mcap-support/src/parseJsonSchema.ts) read a JSON
# channel's schema into the message paths of their panels; a schema they cannot read hides the channel.
FOXGLOVE_LEAF_TYPES = ("boolean", "string", "number", "integer")


def foxglove_schema_problems(schema: dict, path: str = "") -> list[str]:
    """What Foxglove's JSON Schema parser would refuse in ``schema`` (an object's): its type switch, rule
    for rule. Each field has one ``type`` string; "object" has ``properties``; "array" has ``items`` of a
    leaf type or an object (no arrays of arrays); a string's ``contentEncoding`` is none or "base64"."""
    where = path or "the schema"
    if schema.get("type") != "object":
        return [f"{where}: expected \"type\": \"object\", got {json.dumps(schema.get('type'))}"]
    if not isinstance(schema.get("properties"), dict):
        return [f"{where}: an object without properties"]
    problems = []
    for name, field_schema in schema["properties"].items():
        at = f"{path}.{name}" if path else name
        kind = field_schema.get("type") if isinstance(field_schema, dict) else None
        if kind == "string" and field_schema.get("contentEncoding") not in (None, "base64"):
            problems.append(f"{at}: unsupported contentEncoding {field_schema['contentEncoding']!r}")
        elif kind == "object":
            problems += foxglove_schema_problems(field_schema, at)
        elif kind == "array":
            items = field_schema.get("items")
            item_kind = items.get("type") if isinstance(items, dict) else None
            if item_kind == "object":
                problems += foxglove_schema_problems(items, at + "[]")
            elif item_kind == "string" and items.get("contentEncoding") is not None:
                problems.append(f"{at}[]: unsupported contentEncoding for an array item")
            elif item_kind not in FOXGLOVE_LEAF_TYPES:
                problems.append(f"{at}: unsupported array item type {json.dumps(item_kind)}")
        elif kind not in FOXGLOVE_LEAF_TYPES:
            problems.append(f"{at}: unsupported type {json.dumps(kind)} (one type string per field)")
    return problems


def without_nulls(value):
    """``value`` with every dict entry that is None left out, at any depth (list items are kept): Foxglove
    reads no union type such as ["number", "null"], so a missing value is a field left out of the message."""
    if isinstance(value, dict):
        return {k: without_nulls(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [without_nulls(v) for v in value]
    return value


def json_message(value):
    """``without_nulls(jsonable(value))`` in one pass: plain dicts with text keys, lists, tuples, and Python
    numbers, text, booleans and None are taken as they are (a NaN or infinite float becomes None, and a None
    dict entry is left out); anything else goes through those two. A frame's stats are almost all such
    values, and the two passes were a large share of the log's per-frame time on the loop's thread."""
    kind = type(value)
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is int or kind is str or kind is bool or value is None:
        return value
    if kind is dict:
        out = {}
        for k, v in value.items():
            if type(k) is not str:  # str(k) could make two keys one: the two passes' order decides
                return without_nulls(jsonable(value))
            v = json_message(v)
            if v is not None:
                out[k] = v
        return out
    if kind is list or kind is tuple:
        return [json_message(v) for v in value]
    return without_nulls(jsonable(value))


# --------------------------------------------------------------------------------------------------
# Writing


class RunLogger:
    """Writes one run's MCAP log. Use as ``with RunLogger(path, metadata) as log: ...``.

    ``metadata`` maps a record name ("config", "dataset", "backend", "versions") to a dict; MCAP
    metadata is str → str, so values that are not strings are stored JSON-encoded.
    Times ``t`` are in seconds (the frame's dataset timestamp); they become nanosecond log times.
    ``live``: a second sink (``ti_fusion.io.live.LiveServer``) that gets every message too, and is closed
    with the log.

    Each ``log_*`` call checks its arguments, copies the arrays it was given and hands the rest (encoding,
    serialising, compressing chunks, writing, the live sink) to the log's writer thread, in call order, so
    that the loop's thread does not wait for it. A write error there (a full disk) is raised by the next
    call or by ``close``. ``threaded=False`` writes in the caller's thread instead.
    """

    def __init__(self, path: str | Path, metadata: dict[str, dict] | None = None,
                 chunk_size: int = DEFAULT_CHUNK_SIZE, live=None, threaded: bool = True):
        self.live = live
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._sink = _Sink(self.path, chunk_size, live)
        self._topics: dict[str, str] = {}  # topic → schema name, as the calls so far declared them
        self._last_ns = 0
        self._warned_time = False
        self.closed = False
        self._queue = _WriteQueue(self._sink, threaded)
        # Finalise even when the caller forgets close(): at garbage collection or interpreter exit.
        self._finalizer = weakref.finalize(self, self._queue.finish)
        for name, record in (metadata or {}).items():
            self.log_metadata(name, record)
        if live is not None:
            # The live channels exist from the start: a client that connects sees them all at once (and the
            # SDK can refuse a subscription sent in the instant after a channel appears).
            for spec in live_channel_specs():
                live.add_channel(*spec)

    # -- context manager: finalise on normal exit, on any exception and on KeyboardInterrupt ------
    def __enter__(self) -> "RunLogger":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False  # let the exception (or Ctrl-C) continue

    def close(self) -> None:
        """Write what is queued, the summary and the footer, close the file, and stop the live sink
        (idempotent). A stop signal meanwhile waits for the file to be whole."""
        if not self.closed:
            self.closed = True
            try:
                with critical():
                    self._finalizer()  # runs the queue's finish once, then detaches
            finally:
                if self.live is not None:
                    self.live.close()
            self._queue.raise_error()

    def flush(self) -> None:
        """Wait until everything logged so far is in the file."""
        self._queue.wait()

    # -- channels ---------------------------------------------------------------------------------
    def log_metadata(self, name: str, record: dict) -> None:
        """A metadata record: str → str, non-string values JSON-encoded."""
        data = {displayable(str(k)): displayable(v) if isinstance(v, str) else json.dumps(jsonable(v))
                for k, v in record.items()}
        self._submit(_Sink.metadata, name, data)

    def log_pose(self, t: float, pose: np.ndarray, gt_pose: np.ndarray | None = None) -> None:
        """Camera-to-world ``pose`` on /tf and /camera/pose; ``gt_pose`` on /gt/pose."""
        ns = self._ns(t)
        pose = np.array(pose, dtype=np.float64)
        gt_pose = None if gt_pose is None else np.array(gt_pose, dtype=np.float64)
        for topic, kind in (("/tf", FrameTransforms), ("/camera/pose", PoseInFrame), ("/gt/pose", PoseInFrame)):
            self._claim(topic, kind)
        self._submit(_write_pose, ns, pose, gt_pose)

    def log_trajectory(self, t: float, poses, topic: str = TRAJECTORY_TOPIC) -> None:
        """The run's camera-to-world ``poses`` as one message (at the end: /camera/pose has each frame's pose as
        it was tracked, this one the trajectory as written, loop closure's corrections included)."""
        ns = self._ns(t)
        poses = [np.array(p, dtype=np.float64) for p in poses]
        self._claim(topic, PosesInFrame)
        self._submit(_write_trajectory, ns, poses, topic)

    def declare_json(self, topic: str, schema: dict) -> None:
        """Declare a JSON channel and its JSON Schema before its first message (the schema record is named
        after the topic: /slam/stats → ti_fusion.SlamStats)."""
        if topic in self._topics:
            raise ValueError(f"{topic} is declared already")
        problems = foxglove_schema_problems(schema)
        if problems:
            raise ValueError(f"{topic}: Foxglove cannot read this schema: {'; '.join(problems)}")
        schema = {"$schema": JSON_SCHEMA_DIALECT, "title": topic, **schema}
        name = _stats_schema_name(topic)
        self._topics[topic] = name
        self._submit(_Sink.add_channel, topic, name, SchemaEncoding.JSONSchema, json.dumps(schema).encode(),
                     MessageEncoding.JSON)

    def log_stats(self, t: float, stats: dict, channel: str = STATS_TOPIC) -> None:
        """One JSON message: any dict of numbers, strings, lists, nested dicts (NumPy values welcome). A
        dict entry that is None, NaN or infinite is left out of the message (JSON has no NaN, and Foxglove
        reads no nullable field). A channel that was not declared gets a schema inferred from its first
        message."""
        if not isinstance(stats, dict):
            raise TypeError(f"stats must be a dict, got {type(stats).__name__}")
        ns = self._ns(t)
        message = json_message(stats)  # a copy: the caller may change its dict afterwards
        if channel not in self._topics:
            self.declare_json(channel, _json_schema_of(message))
        self._submit(_write_json, channel, message, ns)

    def log_points(self, t: float, xyz: np.ndarray, rgb: np.ndarray | None = None,
                   topic: str = "/map/points", max_points: int = 200_000, file: bool = True,
                   live: bool = True) -> int:
        """A world-frame point cloud; at most ``max_points`` (a fixed-seed random subset). Returns the count
        written to the file (``file=False``: sent to the live sink).

        ``rgb``: N×3 (or N×4) uint8 0–255, or floats in 0–1. The live sink gets the cloud only while a
        client subscribes to ``topic``, and at most its own ``max_points`` of it.
        """
        ns = self._ns(t)
        xyz = np.array(xyz).reshape(-1, 3)
        if rgb is not None and len(rgb) != len(xyz):
            raise ValueError(f"rgb has {len(rgb)} rows for {len(xyz)} points")
        if rgb is not None:
            rgb = np.array(rgb)
            _as_rgba8(rgb[:0], 0)  # (its shape checked here: the error is the caller's)
        finite = np.flatnonzero(np.isfinite(xyz[:, 0] + xyz[:, 1] + xyz[:, 2]))  # NaN/inf anywhere → dropped
        self._claim(topic, PointCloud)  # advertised to live clients even when no cloud is sent
        to_live = live and self.live is not None and self.live.subscribed(topic)
        counts = {}  # sink → how many points it gets
        if file:
            counts["file"] = min(len(finite), max_points)
        if to_live:
            counts["live"] = min(len(finite), max_points, self.live.max_points)
        self._submit(_write_points, topic, ns, xyz, rgb, finite, counts)
        return counts.get("file", counts.get("live", 0))

    def log_depth(self, t: float, depth: np.ndarray, topic: str = "/camera/depth") -> None:
        """A depth image in the camera frame as 16UC1 millimetres (0 = no depth).

        ``depth``: float metres (0, NaN, negative = invalid) or uint16 millimetres as is.
        """
        ns = self._ns(t)
        self._claim(topic, RawImage)
        self._submit(_write_depth, topic, ns, np.array(depth))

    def log_image(self, t: float, rgb: np.ndarray, topic: str = "/camera/color", fmt: str = "jpeg") -> None:
        """A colour image (H×W×3 uint8 RGB) as a CompressedImage, ``fmt`` "jpeg" or "png"."""
        ns = self._ns(t)
        if fmt not in ("jpeg", "png"):
            raise ValueError(f"image format {fmt!r}: jpeg or png")
        self._claim(topic, CompressedImage)
        self._submit(_write_image, topic, ns, np.array(rgb, dtype=np.uint8), fmt)

    def log_calibration(self, t: float, intrinsics, topic: str = "/camera/calibration") -> None:
        """Pinhole intrinsics (``camera.Intrinsics``), so Foxglove can draw the camera frustum."""
        ns = self._ns(t)
        numbers = tuple(float(v) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
        size = (int(intrinsics.width), int(intrinsics.height))
        self._claim(topic, CameraCalibration)
        self._submit(_write_calibration, topic, ns, numbers, size)

    def log_loop_edges(self, t: float, segments, topic: str = LOOP_TOPIC,
                       refused_topic: str = LOOP_REFUSED_TOPIC) -> int:
        """Loop edges as two ``foxglove.SceneUpdate`` messages in the world frame (the poses' frame), one entity
        each whose LinePrimitive of type LINE_LIST joins the two positions of each edge: the loops applied on
        ``topic``, thick and green with a sphere at each end; the candidates not applied on ``refused_topic``,
        thin, faint and red. ``segments``: (p_from (3,), p_to (3,), applied) in world coordinates, every edge
        to show (each entity replaces the previous message's, so pass all edges so far; an empty list clears
        them). Edges with a non-finite end are left out; returns how many were written."""
        ns = self._ns(t)
        edges = []
        for p_from, p_to, applied in segments:
            ends = [np.array(p, dtype=np.float64).reshape(3) for p in (p_from, p_to)]
            if all(np.all(np.isfinite(e)) for e in ends):
                edges.append((ends[0], ends[1], bool(applied)))
        self._claim(topic, SceneUpdate)
        self._claim(refused_topic, SceneUpdate)
        self._submit(_write_loop_edges, topic, ns, [e for e in edges if e[2]], True)
        self._submit(_write_loop_edges, refused_topic, ns, [e for e in edges if not e[2]], False)
        return len(edges)

    def log_mesh(self, t: float, mesh, topic: str = MESH_TOPIC) -> None:
        """A triangle mesh (``ti_fusion.mapping.mesh.Mesh``) as a ``foxglove.SceneUpdate`` in the world frame:
        one entity holding one TriangleListPrimitive with a colour per vertex (packed by
        ``mesh_files.scene_update_bytes``: protobuf's classes take seconds over 100 k vertices). The mesh's
        arrays are read by the writer thread: they must not change after the call."""
        ns = self._ns(t)
        self._claim(topic, SceneUpdate)
        self._submit(_write_mesh, topic, ns, mesh)

    # -- internals --------------------------------------------------------------------------------
    def _ns(self, t: float) -> int:
        """Seconds → log-time nanoseconds; NaN, inf or negative repeat the previous time (0 at first)."""
        if self.closed:
            raise RuntimeError(f"{self.path}: the log is closed")
        try:
            t = float(t)
        except (TypeError, ValueError):
            t = math.nan
        if not (math.isfinite(t) and t >= 0):
            if not self._warned_time:
                warnings.warn(f"{self.path}: timestamp {t!r} is not a finite non-negative number; "
                              "logging at the previous time instead", stacklevel=3)
                self._warned_time = True
            return self._last_ns
        self._last_ns = int(round(t * 1e9))
        return self._last_ns

    def _claim(self, topic: str, message_type) -> None:
        """``topic`` carries ``message_type`` from now on (an error here when it carries another)."""
        name = message_type.DESCRIPTOR.full_name
        known = self._topics.setdefault(topic, name)
        if known != name:
            raise ValueError(f"topic {topic} carries {known}, cannot write a {name}")

    def _submit(self, task, *args) -> None:
        if self.closed:
            raise RuntimeError(f"{self.path}: the log is closed")
        self._queue.put(task, args)


# --------------------------------------------------------------------------------------------------
# The writer's side: what runs on the log's writer thread


class _Sink:
    """The file and the live sink as the writer thread writes them: the MCAP writer, the channels and
    schemas registered so far. Only the writer thread (or, unthreaded, the caller) touches it."""

    def __init__(self, path: Path, chunk_size: int, live):
        self.file = _LogFile(path)
        self.live = live
        self.writer = _Uninterrupted(McapWriter(self.file, chunk_size=chunk_size, compression=CompressionType.ZSTD))
        self.writer.start(profile="", library=f"ti-fusion {_package_version()}")
        self.channels: dict[str, int] = {}  # topic → channel id
        self.schemas: dict[tuple[str, str], int] = {}  # (schema name, encoding) → schema id

    def metadata(self, name: str, data: dict) -> None:
        self.writer.add_metadata(name, data)

    def proto(self, topic: str, message, ns: int, file: bool = True, live: bool = True) -> None:
        self.proto_channel(topic, type(message))
        self.write(topic, message.SerializeToString(), ns, file, live)

    def proto_channel(self, topic: str, message_type) -> None:
        if topic not in self.channels:
            self.add_channel(topic, message_type.DESCRIPTOR.full_name, SchemaEncoding.Protobuf,
                             build_file_descriptor_set(message_type).SerializeToString(), MessageEncoding.Protobuf)

    def add_channel(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                    message_encoding: str) -> None:
        """A new topic: its channel (and its schema, unless another topic has it) in both sinks."""
        schema_id = self.schemas.get((schema_name, schema_encoding))
        if schema_id is None:
            schema_id = self.writer.register_schema(name=schema_name, encoding=schema_encoding, data=schema_data)
            self.schemas[(schema_name, schema_encoding)] = schema_id
        self.channels[topic] = self.writer.register_channel(topic, message_encoding, schema_id)
        if self.live is not None:
            self.live.add_channel(topic, message_encoding, schema_name, schema_encoding, schema_data)

    def write(self, topic: str, data: bytes, ns: int, file: bool = True, live: bool = True) -> None:
        """One message to the file and to the live sink (which drops it unless a client subscribes)."""
        if file:
            self.writer.add_message(self.channels[topic], log_time=ns, data=data, publish_time=ns)
        if live and self.live is not None:
            self.live.log(topic, data, ns)

    def finish(self) -> None:
        """Summary + footer, then close; the file is closed even if finishing fails (disk full...)."""
        try:
            self.writer.finish()
        finally:
            self.file.close()


# Messages queued for the writer thread at most: a few frames' worth (a frame logs 3 to 6), so that a
# slow disk holds the loop back rather than filling the memory, and a killed run loses only these.
QUEUE_SIZE = 32


# The GIL's switch interval while a writer thread runs: the loop's thread waits for the GIL whenever the
# writer holds it (building protobuf messages), up to the interval each time; CPython's default is 5 ms.
_SWITCH_INTERVAL_S = 0.0005
_switch = {"users": 0, "saved": None}
_switch_lock = threading.Lock()


def _shorter_switch_interval(take: bool) -> None:
    """The first writer thread in shortens the interval, the last one out gives it back."""
    with _switch_lock:
        if take:
            if _switch["users"] == 0:
                _switch["saved"] = sys.getswitchinterval()
                sys.setswitchinterval(min(_switch["saved"], _SWITCH_INTERVAL_S))
            _switch["users"] += 1
        else:
            _switch["users"] -= 1
            if _switch["users"] == 0:
                sys.setswitchinterval(_switch["saved"])


class _WriteQueue:
    """The log's writer thread and its bounded queue of (task, args); ``threaded=False`` runs each task at
    once in the caller's thread. Holds no reference to the ``RunLogger``, whose collection finishes it."""

    def __init__(self, sink: _Sink, threaded: bool):
        self._sink = sink
        self._failed: BaseException | None = None  # the write error that stopped the writing
        self._unraised = False  # and it has not reached the caller yet
        self._finished = False
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(QUEUE_SIZE)
            # a daemon: a logger never closed must not keep the interpreter from exiting (its finalizer,
            # at exit, still writes what is queued)
            self._thread = threading.Thread(target=self._run, name="ti-fusion-log", daemon=True)
            self._thread.start()
            _shorter_switch_interval(True)

    def put(self, task, args: tuple) -> None:
        self.raise_error()
        if self._queue is None:
            self._do(task, args)
            self.raise_error()
            return
        with critical():  # a stop waits until the message is queued: every call that returned is in the log
            self._queue.put((task, args))

    def _do(self, task, args: tuple) -> None:
        if self._failed is not None:  # after a write error nothing more is written
            return
        try:
            task(self._sink, *args)
            self._sink.file.flush()  # each message on disk as soon as written: a killed run keeps it
        except BaseException as exc:  # (a full disk): raised by the caller's next call or close
            self._failed, self._unraised = exc, True

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                self._do(*item)
            finally:
                self._queue.task_done()

    def wait(self) -> None:
        """Until every task queued so far is done."""
        if self._queue is not None and self._thread.is_alive():
            self._queue.join()
        self.raise_error()

    def raise_error(self) -> None:
        """The write error of the writer thread, once."""
        if self._unraised:
            self._unraised = False
            raise self._failed

    def finish(self) -> None:
        """Every queued task, then the summary and footer; the file closed. Once."""
        if self._finished:
            return
        self._finished = True
        try:
            if self._thread is not None:
                self._queue.put(None)
                self._thread.join()
                _shorter_switch_interval(False)
        finally:
            if self._failed is None:
                self._sink.finish()
            else:
                try:  # the write that failed would fail again: close what can be closed
                    self._sink.finish()
                except Exception:
                    pass


def _write_pose(sink: _Sink, ns: int, pose: np.ndarray, gt_pose: np.ndarray | None) -> None:
    if np.all(np.isfinite(pose)):
        tf = FrameTransforms()
        tr = tf.transforms.add()
        _fill_transform(tr, ns, pose, WORLD_FRAME, CAMERA_FRAME)
        sink.proto("/tf", tf, ns)
        sink.proto("/camera/pose", _pose_in_frame(ns, pose), ns)
    if gt_pose is not None and np.all(np.isfinite(gt_pose)):
        sink.proto("/gt/pose", _pose_in_frame(ns, gt_pose), ns)


def _write_trajectory(sink: _Sink, ns: int, poses: list, topic: str) -> None:
    msg = PosesInFrame(frame_id=WORLD_FRAME)
    _set_stamp(msg.timestamp, ns)
    for pose in poses:
        if np.all(np.isfinite(pose)):
            _fill_pose(msg.poses.add(), pose)
    sink.proto(topic, msg, ns)


def _write_json(sink: _Sink, channel: str, message: dict, ns: int) -> None:
    sink.write(channel, json.dumps(message, separators=(",", ":"), allow_nan=False).encode(), ns)


def _write_points(sink: _Sink, topic: str, ns: int, xyz: np.ndarray, rgb, finite: np.ndarray, counts: dict) -> None:
    sink.proto_channel(topic, PointCloud)
    kept = {name: _subset(finite, n) for name, n in counts.items()}  # sink → the indices it gets
    shared = "file" in kept and "live" in kept and len(kept["file"]) == len(kept["live"])
    if shared:  # both sinks share one message when they get the same points
        del kept["live"]
    for name, idx in kept.items():
        rows = slice(None) if len(idx) == len(xyz) else idx  # every point: views, not copies by index
        colors = None if rgb is None else _as_rgba8(rgb[rows], len(idx))
        cloud = _point_cloud(ns, np.asarray(xyz[rows], dtype=np.float32), colors)
        sink.proto(topic, cloud, ns, file=name == "file", live=name == "live" or shared)


def _write_depth(sink: _Sink, topic: str, ns: int, depth: np.ndarray) -> None:
    if depth.dtype == np.uint16:
        mm = depth
    else:
        d = depth.astype(np.float64) * 1000.0
        valid = np.isfinite(d) & (d > 0) & (d < 65535.5)
        mm = np.where(valid, np.round(np.where(valid, d, 0.0)), 0).astype(np.uint16)
    mm = np.ascontiguousarray(mm, dtype="<u2")
    h, w = mm.shape
    msg = RawImage(frame_id=CAMERA_FRAME, width=w, height=h, encoding="16UC1", step=2 * w, data=mm.tobytes())
    _set_stamp(msg.timestamp, ns)
    sink.proto(topic, msg, ns)


def _write_image(sink: _Sink, topic: str, ns: int, rgb: np.ndarray, fmt: str) -> None:
    import cv2

    ext = {"jpeg": ".jpg", "png": ".png"}[fmt]
    ok, buf = cv2.imencode(ext, cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"could not encode a {np.shape(rgb)} image as {fmt}")
    msg = CompressedImage(frame_id=CAMERA_FRAME, data=buf.tobytes(), format=fmt)
    _set_stamp(msg.timestamp, ns)
    sink.proto(topic, msg, ns)


def _write_calibration(sink: _Sink, topic: str, ns: int, numbers: tuple, size: tuple) -> None:
    fx, fy, cx, cy = numbers
    msg = CameraCalibration(
        frame_id=CAMERA_FRAME, width=size[0], height=size[1], distortion_model="plumb_bob", D=[0.0] * 5,
        K=[fx, 0, cx, 0, fy, cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1], P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0])
    _set_stamp(msg.timestamp, ns)
    sink.proto(topic, msg, ns)


def _write_loop_edges(sink: _Sink, topic: str, ns: int, edges: list, applied: bool) -> None:
    """One kind's edges (the loops applied, or the candidates not) as one entity holding one LINE_LIST."""
    msg = SceneUpdate()
    entity = msg.entities.add()
    _set_stamp(entity.timestamp, ns)
    entity.frame_id = WORLD_FRAME
    entity.id = LOOP_ENTITY if applied else LOOP_REFUSED_ENTITY
    entity.frame_locked = False
    rgba, px = (LOOP_APPLIED_RGBA, LOOP_APPLIED_PX) if applied else (LOOP_NOT_APPLIED_RGBA, LOOP_NOT_APPLIED_PX)
    line = entity.lines.add()
    line.type = LinePrimitive.LINE_LIST
    line.thickness = px
    line.scale_invariant = True
    line.pose.orientation.w = 1.0
    line.color.r, line.color.g, line.color.b, line.color.a = rgba
    for p_from, p_to, _ in edges:
        for e in (p_from, p_to):
            point = line.points.add()
            point.x, point.y, point.z = (float(v) for v in e)
            if applied:
                sphere = entity.spheres.add()
                sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z = (float(v) for v in e)
                sphere.pose.orientation.w = 1.0
                sphere.size.x = sphere.size.y = sphere.size.z = LOOP_APPLIED_END_M
                sphere.color.r, sphere.color.g, sphere.color.b, sphere.color.a = LOOP_APPLIED_RGBA
    sink.proto(topic, msg, ns)


def _write_mesh(sink: _Sink, topic: str, ns: int, mesh) -> None:
    from ti_fusion.io.mesh_files import scene_update_bytes

    head = SceneUpdate().entities.add()
    _set_stamp(head.timestamp, ns)
    head.frame_id = WORLD_FRAME
    head.id = MESH_ENTITY
    head.frame_locked = False
    sink.proto_channel(topic, SceneUpdate)
    sink.write(topic, scene_update_bytes(head.SerializeToString(), mesh.vertices, mesh.faces, mesh.colors), ns)


class _LogFile:
    """The log's file as the MCAP writer uses it (write, tell, flush, close), with an ``OSError`` (a full
    disk) turned into an ``OutputError`` that names the log."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self._file = open(path, "wb")
        except OSError as exc:
            raise OutputError(path, f"cannot be written: {exc.strerror or exc}") from None

    def _call(self, name: str, *args):
        try:
            return getattr(self._file, name)(*args)
        except OSError as exc:
            raise OutputError(self.path, f"cannot be written: {exc.strerror or exc}") from exc

    def write(self, data) -> int:
        return self._call("write", data)

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        self._call("flush")

    def close(self) -> None:
        self._call("close")


class _Uninterrupted:
    """The MCAP writer with each call a ``critical`` block: a stop signal waits for the call to end, since a
    chunk cut halfway (taken from the chunk buffer, not yet written) loses every message it held."""

    def __init__(self, writer: McapWriter):
        self._writer = writer

    def __getattr__(self, name: str):
        method = getattr(self._writer, name)

        def call(*args, **kwargs):
            with critical():
                return method(*args, **kwargs)

        return call


def _package_version() -> str:
    from ti_fusion import __version__

    return __version__


def _stats_schema_name(topic: str) -> str:
    """"/slam/stats" → "ti_fusion.SlamStats"."""
    parts = [p for p in topic.replace("-", "_").replace("/", "_").split("_") if p]
    return "ti_fusion." + ("".join(p[:1].upper() + p[1:] for p in parts) or "Stats")


def _set_stamp(stamp, ns: int) -> None:
    stamp.seconds, stamp.nanos = divmod(int(ns), 1_000_000_000)


def _fill_pose(msg, pose: np.ndarray) -> None:
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in pose[:3, 3])
    q = rot_to_quat(pose[:3, :3])
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (float(v) for v in q)


def _fill_transform(tr: FrameTransform, ns: int, pose: np.ndarray, parent: str, child: str) -> None:
    # Foxglove: translation/rotation place the child frame in the parent, i.e. camera-to-world.
    _set_stamp(tr.timestamp, ns)
    tr.parent_frame_id, tr.child_frame_id = parent, child
    tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in pose[:3, 3])
    q = rot_to_quat(pose[:3, :3])
    tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = (float(v) for v in q)


def _pose_in_frame(ns: int, pose: np.ndarray) -> PoseInFrame:
    msg = PoseInFrame(frame_id=WORLD_FRAME)
    _set_stamp(msg.timestamp, ns)
    _fill_pose(msg.pose, pose)
    return msg


def _as_rgba8(rgb: np.ndarray, n: int) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.shape[0] != n or rgb.ndim != 2 or rgb.shape[1] not in (3, 4):
        raise ValueError(f"rgb must be N×3 or N×4 with N = {n}, got shape {rgb.shape}")
    if rgb.dtype.kind == "f":
        rgb = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0)
    rgba = np.full((n, 4), 255, dtype=np.uint8)
    rgba[:, : rgb.shape[1]] = np.clip(rgb, 0, 255).astype(np.uint8)
    return rgba


def _point_cloud(ns: int, xyz: np.ndarray, rgba: np.ndarray | None) -> PointCloud:
    names = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgba is not None:
        names += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
    packed = np.empty(len(xyz), dtype=np.dtype(names))  # 12 or 16 bytes per point, no padding
    packed["x"], packed["y"], packed["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgba is not None:
        packed["red"], packed["green"], packed["blue"], packed["alpha"] = rgba.T
    msg = PointCloud(frame_id=WORLD_FRAME, point_stride=packed.dtype.itemsize, data=packed.tobytes())
    _set_stamp(msg.timestamp, ns)
    msg.pose.position.SetInParent()  # the cloud's origin is the world origin: position (0, 0, 0) ...
    msg.pose.orientation.w = 1.0     # ... and the identity rotation, both set
    for name, _ in names:
        kind = PackedElementField.FLOAT32 if name in "xyz" else PackedElementField.UINT8
        msg.fields.add(name=name, offset=packed.dtype.fields[name][1], type=kind)
    return msg


def _subset(idx: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``idx``: a fixed-seed random subset in order, so the same cloud always gives
    the same points."""
    if len(idx) <= max_points:
        return idx
    return np.sort(np.random.default_rng(_POINTS_SEED).choice(idx, max_points, replace=False))


def _json_schema_of(value) -> dict | None:
    """A JSON Schema describing ``value``'s shape (for Foxglove's message-path autocomplete), in the form
    Foxglove reads; None for what one message cannot type (null, an empty list, a list of lists): such a
    field is left out of the schema."""
    if isinstance(value, dict):
        properties = {k: s for k, s in ((k, _json_schema_of(v)) for k, v in value.items()) if s is not None}
        return {"type": "object", "properties": properties}
    if isinstance(value, list):
        items = _json_schema_of(value[0]) if value else None
        return None if items is None or items["type"] == "array" else {"type": "array", "items": items}
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, (int, float)):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    return None


# --------------------------------------------------------------------------------------------------
# Reading


@dataclass
class ChannelInfo:
    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    count: int = 0


@dataclass
class LogContents:
    """What ``read_log`` gets out of a log. Times in seconds; poses camera-to-world 4×4 float64."""

    path: Path
    complete: bool                      # False: no footer (run killed), recovered from whole chunks
    channels: dict[str, ChannelInfo]
    start_s: float | None
    end_s: float | None
    metadata: dict[str, dict[str, str]]
    stats_topic: str | None             # /slam/stats, or the only other JSON ".../stats" channel
    stats: list[dict]
    stats_times: np.ndarray
    est_times: np.ndarray
    est_poses: np.ndarray               # N×4×4 from /camera/pose (or /tf when that is missing)
    gt_times: np.ndarray
    gt_poses: np.ndarray                # M×4×4 from /gt/pose
    json_messages: dict[str, list[tuple[float, dict]]] = field(default_factory=dict)

    @property
    def message_count(self) -> int:
        return sum(c.count for c in self.channels.values())

    def metadata_value(self, record: str, key: str) -> Any:
        """A metadata value decoded back from JSON (a plain string stays a string)."""
        raw = self.metadata[record][key]
        try:
            return json.loads(raw)
        except json.JSONDecodeError:
            return raw


def read_log(path: str | Path) -> LogContents:
    """Read a ti-fusion MCAP log: channel counts, time range, metadata, stats and poses.

    Reads linearly rather than through the footer's index, so an unfinalised file (a run killed
    hard) yields every message in the chunks that reached the disk, with ``complete=False``.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir() and (path / "log.mcap").is_file():  # a run's folder
        path = path / "log.mcap"
    if not path.is_file():
        raise InputError(path, "not a file (expected an .mcap log, or a run folder holding log.mcap)")
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise InputError(path, "not an MCAP file (its first bytes are not the MCAP magic)")
        f.seek(-len(MCAP_MAGIC), os.SEEK_END)
        finalised = f.read() == MCAP_MAGIC  # a finalised file ends with the magic: it cannot be torn
        f.seek(0)
        return _read_records(path, StreamReader(f, skip_magic=False, validate_crcs=True), finalised)


def _read_records(path: Path, reader: StreamReader, finalised: bool = False) -> LogContents:
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    infos: dict[str, ChannelInfo] = {}
    metadata: dict[str, dict[str, str]] = {}
    decoders: dict[int, Any] = {}
    factory = DecoderFactory()
    json_messages: dict[str, list[tuple[float, dict]]] = {}
    poses: dict[str, list[tuple[int, np.ndarray]]] = {"/camera/pose": [], "/gt/pose": [], "/tf": []}
    t_min = t_max = None
    complete = False
    records = reader.records
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - a torn record ends an unfinalised file; anything else is damage
            if isinstance(exc, CRCValidationError) or finalised:
                raise InputError(path, f"damaged near byte {reader._stream.count}: {damage(exc)}; the file changed "
                                       "after it was written") from None
            break
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            schema = schemas.get(record.schema_id)
            infos.setdefault(record.topic, ChannelInfo(
                record.topic, schema.name if schema else "", schema.encoding if schema else "",
                record.message_encoding))
        elif isinstance(record, Metadata):
            metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Footer):
            complete = True
        elif isinstance(record, Message):
            channel = channels[record.channel_id]
            infos[channel.topic].count += 1
            t_min = record.log_time if t_min is None else min(t_min, record.log_time)
            t_max = record.log_time if t_max is None else max(t_max, record.log_time)
            if channel.message_encoding == MessageEncoding.JSON:
                json_messages.setdefault(channel.topic, []).append(
                    (record.log_time / 1e9, json.loads(record.data)))
            elif channel.topic in poses:
                decode = decoders.get(channel.id)
                if decode is None:
                    decode = decoders[channel.id] = factory.decoder_for(
                        channel.message_encoding, schemas.get(channel.schema_id))
                pose = _pose_of(decode(record.data), channel.topic)
                if pose is not None:
                    poses[channel.topic].append((record.log_time, pose))
    stats_topic = _pick_stats_topic(json_messages)
    stats_pairs = json_messages.get(stats_topic, []) if stats_topic else []
    est = poses["/camera/pose"] or poses["/tf"]
    est_t, est_p = _sorted_poses(est)
    gt_t, gt_p = _sorted_poses(poses["/gt/pose"])
    return LogContents(
        path=path, complete=complete, channels=infos,
        start_s=None if t_min is None else t_min / 1e9, end_s=None if t_max is None else t_max / 1e9,
        metadata=metadata, stats_topic=stats_topic,
        stats=[m for _, m in stats_pairs], stats_times=np.array([t for t, _ in stats_pairs]),
        est_times=est_t, est_poses=est_p, gt_times=gt_t, gt_poses=gt_p, json_messages=json_messages)


def damage(exc: Exception) -> str:
    """What a damaged MCAP record's error says, in a few words."""
    if isinstance(exc, CRCValidationError):
        return f"a {type(exc.record).__name__.lower()}'s CRC does not match its data"
    return " ".join(str(exc).split())[:200] or type(exc).__name__


def _pick_stats_topic(json_messages: dict) -> str | None:
    if STATS_TOPIC in json_messages:
        return STATS_TOPIC
    candidates = [t for t in json_messages if t.endswith("stats")]
    return candidates[0] if candidates else None


def _sorted_poses(pairs: list[tuple[int, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    if not pairs:
        return np.zeros(0), np.zeros((0, 4, 4))
    pairs = sorted(pairs, key=lambda p: p[0])
    return np.array([ns / 1e9 for ns, _ in pairs]), np.stack([p for _, p in pairs])


def _pose_of(msg, topic: str) -> np.ndarray | None:
    if topic == "/tf":
        for tr in msg.transforms:
            if tr.parent_frame_id == WORLD_FRAME and tr.child_frame_id == CAMERA_FRAME:
                return _matrix(tr.translation, tr.rotation)
        return None
    return pose_from_msg(msg)


def _matrix(p, q) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_rot(np.array([q.x, q.y, q.z, q.w]))
    T[:3, 3] = (p.x, p.y, p.z)
    return T


def pose_from_msg(msg) -> np.ndarray:
    """4×4 pose of a foxglove.PoseInFrame (or foxglove.Pose)."""
    pose = msg.pose if hasattr(msg, "pose") else msg
    return _matrix(pose.position, pose.orientation)


def points_from_msg(msg: PointCloud) -> tuple[np.ndarray, np.ndarray | None]:
    """(N×3 float32 xyz, N×4 uint8 rgba or None) of a foxglove.PointCloud written by ``log_points``."""
    kinds = {PackedElementField.FLOAT32: "<f4", PackedElementField.UINT8: "u1"}
    dtype = np.dtype({"names": [f.name for f in msg.fields], "formats": [kinds[f.type] for f in msg.fields],
                      "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_stride})
    packed = np.frombuffer(msg.data, dtype=dtype)
    xyz = np.stack([packed["x"], packed["y"], packed["z"]], axis=1)
    names = set(dtype.names)
    rgba = None
    if {"red", "green", "blue", "alpha"} <= names:
        rgba = np.stack([packed["red"], packed["green"], packed["blue"], packed["alpha"]], axis=1)
    return xyz, rgba


def loop_edges_from_msg(msg: SceneUpdate) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """The (p_from, p_to, applied) edges of a ``log_loop_edges`` message on either topic (applied: drawn
    green)."""
    edges = []
    for entity in msg.entities:
        for line in entity.lines:
            pts = np.array([(p.x, p.y, p.z) for p in line.points], dtype=np.float64).reshape(-1, 3)
            green = [c.g > c.r for c in line.colors] or [line.color.g > line.color.r] * len(pts)
            edges += [(pts[k], pts[k + 1], bool(green[k])) for k in range(0, len(pts) - 1, 2)]
    return edges


def depth_from_msg(msg: RawImage) -> np.ndarray:
    """Float32 metres (0 = no depth) of a foxglove.RawImage in 16UC1 millimetres or 32FC1 metres."""
    if msg.encoding == "16UC1":
        mm = np.frombuffer(msg.data, dtype="<u2").reshape(msg.height, msg.step // 2)[:, : msg.width]
        return mm.astype(np.float32) / 1000.0
    if msg.encoding == "32FC1":
        return np.frombuffer(msg.data, dtype="<f4").reshape(msg.height, msg.step // 4)[:, : msg.width].copy()
    raise ValueError(f"not a depth encoding: {msg.encoding}")


__all__ = ["RunLogger", "read_log", "LogContents", "ChannelInfo", "software_versions", "json_object", "json_field",
           "pose_from_msg", "points_from_msg", "depth_from_msg", "loop_edges_from_msg", "STATS_TOPIC",
           "LOOP_TOPIC", "LOOP_REFUSED_TOPIC"]
