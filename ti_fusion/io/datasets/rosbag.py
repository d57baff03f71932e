"""ROS 2 bags as RGB-D sequences: a rosbag2 folder (``metadata.yaml`` and its ``.mcap`` or ``.db3``
files) or a single ``.mcap`` file, as ``ros2 bag record`` writes them.

Read with ``rosbags`` because it is pure Python (no ROS installation), reads rosbag2 folders of either
storage and bare MCAP files, and decodes CDR with the standard message types built in, handing image
data over as NumPy arrays.

- Topics: depth is the ``sensor_msgs/msg/Image`` topic whose images are ``16UC1``/``mono16`` (millimetres)
  or ``32FC1`` (metres), per REP 118; colour an Image topic in ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` or
  ``mono8``, or a ``sensor_msgs/msg/CompressedImage`` topic (JPEG/PNG); intrinsics come from the depth
  topic's ``camera_info`` sibling, else the bag's only ``sensor_msgs/msg/CameraInfo`` topic. A kind with
  one candidate is taken; with several, one line lists them with the option that picks one
  (``--depth-topic``, ``--color-topic``, ``--camera-info-topic``; ``dataset.*_topic``).
- Frames are the depth messages in header-stamp order; a frame's timestamp is its header stamp in
  seconds, so ``trajectory.tum`` compares directly with the bag's own ground truth. A stamp repeated is
  left out (with a note).
- Colour is paired with depth by header stamp, nearest first (TUM's associate rule) within
  ``dataset.max_time_difference``; a depth frame without colour in that window is kept without colour
  (a note counts them). Colour is registered to depth when both have one ``frame_id``; when the frames
  differ it is not (a note says so) and only colours the map, resized to the depth size when needed.
- Depth scale: REP 118's (1000 units per metre for 16-bit, 1 for 32FC1) unless ``--depth-scale`` says
  otherwise. Intrinsics: ``--intrinsics`` (``dataset.intrinsics``), else the CameraInfo's K, whose size
  must be the depth images'; a bag with neither is refused.
- Ground truth: a ``geometry_msgs/msg/PoseStamped`` or ``nav_msgs/msg/Odometry`` topic named by
  ``--gt-topic`` (the depth camera's optical frame in the world: x right, y down, z forward), or a TUM
  file (``--ground-truth``; ``groundtruth.txt`` or ``poses.tum`` in a rosbag2 folder), interpolated at
  each depth stamp as TUM's is. Never taken from a topic unasked: an odometry topic is an estimate.
- A cut-off recording (an ``.mcap`` file without its footer, e.g. a recorder that was killed) is read up
  to its last complete record, with a note; a rosbag2 folder without ``metadata.yaml`` is read from its
  single ``.mcap`` file.
"""

from __future__ import annotations

import weakref
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, quat_to_rot
from ti_fusion.io.datasets.base import Frame, RecordedSequence
from ti_fusion.io.datasets.compressed import decode_compressed_color, decode_compressed_depth, is_compressed_depth
from ti_fusion.io.datasets.imageio import depth_to_metres, intrinsics_from_numbers, parse_intrinsics
from ti_fusion.io.datasets.extrinsics import (TF_MESSAGE, TRANSFORM, TRANSFORM_STAMPED, extrinsics_from_message,
                                              read_extrinsics_file, transform_matrix)
from ti_fusion.io.datasets.realsense import depth_to_color
from ti_fusion.io.datasets.realsense import recognise as recognise_realsense

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

# encoding → (NumPy type, units per metre by REP 118)
DEPTH_ENCODINGS = {"16UC1": ("u2", 1000.0), "mono16": ("u2", 1000.0), "32FC1": ("f4", 1.0)}
# encoding → (channels, OpenCV conversion to RGB, None = already RGB)
COLOR_ENCODINGS = {"rgb8": (3, None), "bgr8": (3, cv2.COLOR_BGR2RGB), "rgba8": (4, cv2.COLOR_RGBA2RGB),
                   "bgra8": (4, cv2.COLOR_BGRA2RGB), "mono8": (1, cv2.COLOR_GRAY2RGB)}
GROUND_TRUTH_FILES = ("groundtruth.txt", "poses.tum")


def _typestore(ros1: bool = False):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)


def _field(msg, name: str):
    """A CameraInfo field by its ROS 2 name (``k``, ``d``) or its ROS 1 one (``K``, ``D``)."""
    value = getattr(msg, name, None)
    return getattr(msg, name.upper()) if value is None else value


def _stamp(header) -> float:
    # whole nanoseconds over 10⁹ as integers: Python rounds the quotient once, so a stamp written from a decimal
    # text of at most nine places (a TUM file's) reads back as that text's float, not an ulp off it
    return (int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)) / 10**9


# --------------------------------------------------------------------------------------------------
# Messages of a bag
# --------------------------------------------------------------------------------------------------
class BagFile:
    """The messages of a bag (rosbags' reader): topics and types, a pass over some topics, and one
    message fetched again by the key the pass gave it (its log time and rank among the topic's messages
    of that time)."""

    truncated = False

    def __init__(self, path: Path):
        # a .bag file is ROS 1 (its own serialisation and message definitions, e.g. CameraInfo's K and D)
        self.ros1 = path.is_file() and path.suffix == ".bag"
        if self.ros1:
            from rosbags.rosbag1 import Reader
        else:
            from rosbags.rosbag2 import Reader

        self.path = path
        self._store = _typestore(self.ros1)
        self._reader = Reader(path)
        self._reader.open()
        self._connections = {}
        for c in self._reader.connections:
            self._connections.setdefault(c.topic, []).append(c)
        self.topics = {t: (cs[0].msgtype, sum(c.msgcount for c in cs)) for t, cs in self._connections.items()}

    def scan(self, topics) -> Iterator[tuple[str, tuple, bytes, int]]:
        """(topic, key, raw message, log time in ns) of every message of ``topics``, in log-time order."""
        conns = [c for t in topics for c in self._connections[t]]
        last, rank = {}, {}
        for conn, t_ns, raw in self._reader.messages(conns):
            rank[conn.topic] = rank.get(conn.topic, 0) + 1 if last.get(conn.topic) == t_ns else 0
            last[conn.topic] = t_ns
            yield conn.topic, (t_ns, rank[conn.topic]), raw, t_ns

    def fetch(self, topic: str, key: tuple) -> bytes:
        t_ns, rank = key
        for i, (_, _, raw) in enumerate(self._reader.messages(self._connections[topic], start=t_ns, stop=t_ns + 1)):
            if i == rank:
                return raw
        raise InputError(self.path, f"message of {topic} at {t_ns} ns is gone (was the bag changed while read?)")

    def deserialize(self, raw: bytes, msgtype: str):
        return self._store.deserialize_ros1(raw, msgtype) if self.ros1 else self._store.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        self._reader.close()


class CutMcap:
    """The complete records of an MCAP file that ends early (no footer: a recorder killed mid-write), read
    in file order with ``mcap``'s stream reader; a message's key is where its record (or its chunk) starts."""

    truncated = True

    def __init__(self, path: Path):
        from mcap.records import Channel, Chunk, Message, Schema

        self.path = path
        self._store = _typestore()
        self._file = open(path, "rb")
        self._chunk_cache: tuple[int, list] | None = None
        self._channels: dict[int, tuple[str, str]] = {}  # channel id → (topic, message type)
        self._index: list[tuple[int, int, int, int]] = []  # (channel id, record offset, index in its chunk or -1,
        #                                                       log time in ns)
        schemas: dict[int, str] = {}
        records = self._records(0)
        counts: dict[int, int] = {}
        self.read_to = 0
        try:
            for offset, record in records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    self._channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                elif isinstance(record, Message):
                    self._index.append((record.channel_id, offset, -1, record.log_time))
                elif isinstance(record, Chunk):
                    for k, inner in enumerate(self._chunk_records(offset, record)):
                        if isinstance(inner, Schema):
                            schemas[inner.id] = inner.name
                        elif isinstance(inner, Channel):
                            self._channels[inner.id] = (inner.topic, schemas.get(inner.schema_id, ""))
                        elif isinstance(inner, Message):
                            self._index.append((inner.channel_id, offset, k, inner.log_time))
                self.read_to = self._file.tell()
        except Exception:  # the cut: a record that the file ends inside, or garbage after the last whole one
            pass
        for cid, _, _, _ in self._index:
            counts[cid] = counts.get(cid, 0) + 1
        self.topics = {}
        for cid, (topic, msgtype) in self._channels.items():
            _, n = self.topics.get(topic, (msgtype, 0))
            self.topics[topic] = (msgtype, n + counts.get(cid, 0))

    def _records(self, offset: int):
        """(file offset, record) from ``offset`` on; chunks are handed over whole."""
        from mcap.stream_reader import StreamReader

        self._file.seek(offset)
        reader = StreamReader(self._file, skip_magic=offset > 0, emit_chunks=True)
        records = reader.records
        while True:
            start = self._file.tell()
            record = next(records, None)
            if record is None:
                return
            yield (8 if start == 0 else start), record  # the first read takes the magic with it

    def _chunk_records(self, offset: int, chunk) -> list:
        from mcap.stream_reader import breakup_chunk

        if self._chunk_cache is None or self._chunk_cache[0] != offset:
            self._chunk_cache = (offset, breakup_chunk(chunk))
        return self._chunk_cache[1]

    def scan(self, topics) -> Iterator[tuple[str, tuple, bytes, int]]:
        wanted = {cid for cid, (t, _) in self._channels.items() if t in topics}
        for cid, offset, k, log_ns in self._index:
            if cid in wanted:
                key = (offset, k)
                yield self._channels[cid][0], key, self._data(key), log_ns

    def fetch(self, topic: str, key: tuple) -> bytes:
        return self._data(key)

    def deserialize(self, raw: bytes, msgtype: str):
        return self._store.deserialize_cdr(raw, msgtype)

    def _data(self, key: tuple) -> bytes:
        offset, k = key
        _, record = next(self._records(offset))
        return record.data if k < 0 else self._chunk_records(offset, record)[k].data

    def close(self) -> None:
        self._file.close()


def open_bag(root: Path) -> tuple[BagFile | CutMcap, str | None]:
    """The messages of the bag at ``root``, and a note when it was read in a way that the user should know."""
    from rosbags.rosbag1 import ReaderError as Ros1ReaderError
    from rosbags.rosbag2 import ReaderError

    path, note = root, None
    if root.is_dir() and not (root / "metadata.yaml").is_file():
        files = sorted(root.glob("*.mcap"))
        if len(files) != 1:
            raise InputError(root, "no metadata.yaml, and " + (f"{len(files)} .mcap files: give one of them" if files
                                                               else "no .mcap file: not a ROS 2 bag"))
        path, note = files[0], f"no metadata.yaml in the folder: {files[0].name} is read on its own"
    try:
        return BagFile(path), note
    except Ros1ReaderError as exc:
        problem = str(exc)
        if "index" in problem.lower():  # rosbag1 needs the index a killed recorder never wrote
            raise InputError(path, f"a ROS 1 bag without its index ({problem.rstrip('.')}; a recording cut off?): "
                                   "`rosbag reindex` it first") from None
        raise InputError(path, f"cannot read the ROS 1 bag: {problem}") from None
    except ReaderError as exc:
        problem = str(exc)
    except (OSError, ValueError, KeyError) as exc:
        problem = f"unreadable bag: {exc}"
    if "Profile is not ros2" in problem:
        raise InputError(path, "an MCAP file, but not a ROS 2 bag (its profile is not ros2); a ti-fusion run log "
                               "replays with --format log")
    if path.suffix == ".mcap" and ("end magic" in problem or "footer" in problem.lower()):
        try:
            bag = CutMcap(path)
        except Exception as exc:  # not even the start of an MCAP file: report rosbags' reason
            raise InputError(path, f"{problem.rstrip('.')}; reading it record by record failed too: {exc}") from None
        count = sum(n for _, n in bag.topics.values())
        if count:
            size = path.stat().st_size
            cut = f"the file ends without MCAP's footer (a recording cut off): read up to byte {bag.read_to} of " \
                  f"{size}, {count} complete messages"
            return bag, cut if note is None else f"{note}; {cut}"
        bag.close()
    raise InputError(path, f"cannot read the bag: {problem}")


# --------------------------------------------------------------------------------------------------
# Messages to arrays
# --------------------------------------------------------------------------------------------------
def _image_array(msg, dtype: str, channels: int, where: str) -> np.ndarray:
    """The H×W(×C) array of a ``sensor_msgs/msg/Image``, honouring ``step`` and ``is_bigendian``."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize * channels
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h == 0 or w == 0 or step < w * item or data.size < h * step:
        raise InputError(None, f"{where}: image of {w}x{h} {msg.encoding} with step {step} holds {data.size} bytes")
    rows = data[: h * step].reshape(h, step)[:, : w * item]
    order = ">" if msg.is_bigendian else "<"
    array = np.ascontiguousarray(rows).view(np.dtype(order + dtype) if np.dtype(dtype).itemsize > 1 else dtype)
    array = array.reshape((h, w, channels) if channels > 1 else (h, w))
    return array.astype(array.dtype.newbyteorder("="), copy=False)


def depth_raw(msg, msgtype: str, where: str) -> tuple[np.ndarray, str]:
    """(raw array, encoding) of a depth Image or compressedDepth CompressedImage: uint16 units, or float32."""
    if msgtype == COMPRESSED:
        if not is_compressed_depth(msg.format):
            raise InputError(None, f"{where}: a CompressedImage in {msg.format!r}, not compressedDepth: not depth")
        return decode_compressed_depth(msg.format, msg.data, where)
    if msg.encoding not in DEPTH_ENCODINGS:
        raise InputError(None, f"{where}: depth encoding {msg.encoding!r}, expected one of {', '.join(DEPTH_ENCODINGS)}")
    return _image_array(msg, DEPTH_ENCODINGS[msg.encoding][0], 1, where), msg.encoding


def raw_to_metres(raw: np.ndarray, scale: float, depth_max: float | None) -> np.ndarray:
    """float32 metres (0 = no measurement): raw units / ``scale``; NaN and ±Inf (REP 118's no return, too
    far, too near) and non-positive values are 0."""
    if raw.dtype == np.uint16:
        return depth_to_metres(raw, scale, depth_max)
    depth = raw.astype(np.float32) / np.float32(scale)
    bad = ~np.isfinite(depth) | (depth <= 0)
    if depth_max is not None and depth_max > 0:
        bad |= depth > depth_max
    depth[bad] = 0.0
    return depth


def depth_image(msg, scale: float, depth_max: float | None, where: str, msgtype: str = IMAGE) -> np.ndarray:
    """float32 metres (0 = no measurement) of a depth Image or compressedDepth message."""
    return raw_to_metres(depth_raw(msg, msgtype, where)[0], scale, depth_max)


def color_image(msg, msgtype: str, where: str) -> np.ndarray:
    """uint8 H×W×3 RGB of a colour Image or CompressedImage."""
    if msgtype == COMPRESSED:
        return decode_compressed_color(msg.format, msg.data, where)
    if msg.encoding not in COLOR_ENCODINGS:
        raise InputError(None, f"{where}: colour encoding {msg.encoding!r}, expected one of {', '.join(COLOR_ENCODINGS)}")
    channels, conversion = COLOR_ENCODINGS[msg.encoding]
    image = _image_array(msg, "u1", channels, where)
    return np.ascontiguousarray(image) if conversion is None else cv2.cvtColor(image, conversion)


def pose_of(msg, msgtype: str) -> np.ndarray:
    """4×4 pose of a PoseStamped or Odometry message."""
    pose = msg.pose if msgtype == POSE_STAMPED else msg.pose.pose
    p, q = pose.position, pose.orientation
    return make_pose(quat_to_rot(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


# librealsense's names for the models OpenCV calls otherwise (its Brown-Conrady is plumb_bob's k1 k2 p1 p2 k3)
_MODEL_ALIASES = {"brown conrady": "plumb_bob"}


def _camera(info, width: int, height: int, where: str) -> Intrinsics:
    """The Intrinsics of a CameraInfo (ROS 1 or 2): K, and D in its distortion model (undistorted per frame)."""
    model = str(info.distortion_model or "")
    return intrinsics_from_numbers(np.asarray(_field(info, "k"), dtype=np.float64), width, height, where,
                                   np.asarray(_field(info, "d"), dtype=np.float64),
                                   _MODEL_ALIASES.get(model.strip().lower(), model))


def _k_text(k) -> str:
    k = np.asarray(k, dtype=np.float64).reshape(-1)
    return f"fx {k[0]:g} fy {k[4]:g} cx {k[2]:g} cy {k[5]:g}"


# --------------------------------------------------------------------------------------------------
# The dataset
# --------------------------------------------------------------------------------------------------
class RosbagDataset(RecordedSequence):
    """A ROS 1 or ROS 2 bag's depth (and colour) images as frames (see the module docstring)."""

    format = "rosbag"
    identified_by = "a ROS 2 bag (metadata.yaml, *.mcap)"
    single_file = True
    reads_color_camera = True
    reads = frozenset({"intrinsics", "depth_scale", "ground_truth", "depth_topic", "color_topic", "camera_info_topic",
                       "gt_topic"})
    reads_in_process = True  # one reader process, in order (concurrent_reads is False: one open bag)

    @property
    def color_for_tracking(self) -> bool:  # one frame_id for both, or the user's word (dataset.color_registered)
        return bool(self.color_registered) or self.config.color_registered

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, downsample=downsample, start=start, stop=stop, stride=stride)
        self.config = config or DatasetConfig()
        self.name = self.root.stem if self.root.is_file() else self.root.name
        if not self.root.exists():
            raise InputError(self.root, "bag does not exist")
        self.bag, note = open_bag(self.root)
        self._closer = weakref.finalize(self, self.bag.close)
        if note:
            self.note(note)
        self.realsense = None
        # the colour camera where colour is not registered to depth: its intrinsics and T_color_depth
        self.color_intrinsics: Intrinsics | None = None
        self.color_extrinsics: np.ndarray | None = None
        self.color_calibration_source: str | None = None
        self.topics = self._choose_topics()
        self._index()
        self._intrinsics = self._find_intrinsics()
        if self.realsense is not None:
            self._realsense_calibration()
        if self.config.color_extrinsics:
            self._stated_color_camera(self.config.color_extrinsics)
        elif self.config.color_intrinsics:
            raise InputError(None, "--color-intrinsics registers colour to depth together with --color-extrinsics "
                                   "FILE|TOPIC (the colour camera's pose from the depth camera)")
        self._gt_poses = self._ground_truth()

    # -- topics ---------------------------------------------------------------------------------
    def _first(self, topic: str):
        msgtype = self.bag.topics[topic][0]
        for _, _, raw, _ in self.bag.scan([topic]):
            return self.bag.deserialize(raw, msgtype)
        return None

    def _choose_topics(self) -> dict[str, str | None]:
        cfg, bag = self.config, self.bag
        of_type = {}
        for topic, (msgtype, count) in sorted(bag.topics.items()):
            if count:
                of_type.setdefault(msgtype, []).append(topic)
        depth, color = [], []
        for topic in of_type.get(IMAGE, []):
            encoding = self._first(topic).encoding
            if encoding in DEPTH_ENCODINGS:
                depth.append(topic)
            elif encoding in COLOR_ENCODINGS:
                color.append(topic)
        for topic in of_type.get(COMPRESSED, []):
            (depth if is_compressed_depth(self._first(topic).format) else color).append(topic)
        infos = of_type.get(CAMERA_INFO, [])
        self.realsense = recognise_realsense(bag.topics, cfg.depth_topic, cfg.color_topic)
        if self.realsense is not None:  # the SDK's topics say which stream is which
            depth = [self.realsense.depth]
            color = [self.realsense.color] if self.realsense.color else color

        listed = ", ".join(f"{t} ({bag.topics[t][0]})" for t in sorted(bag.topics)) or "none"
        chosen, ambiguous = {}, []

        def pick(kind, given, candidates, option, types):
            """The topic the option gives (checked), else the only candidate; None when there is none."""
            if given:
                if given not in bag.topics:
                    raise InputError(self.root, f"{option} {given}: no such topic in the bag (topics: {listed})")
                msgtype = bag.topics[given][0]
                if msgtype not in types or (candidates is not None and given not in candidates):
                    first = self._first(given) if msgtype in (IMAGE, COMPRESSED) else None
                    encoding = f" in {first.encoding}" if msgtype == IMAGE else \
                        f" in format {first.format!r}" if msgtype == COMPRESSED else ""
                    raise InputError(self.root, f"{option} {given}: a {msgtype} topic{encoding}, not a {kind} topic")
                return given
            if len(candidates) > 1:
                ambiguous.append(f"{kind}: {', '.join(candidates)} ({option} TOPIC)")
            return candidates[0] if len(candidates) == 1 else None

        chosen["depth"] = pick("depth", cfg.depth_topic, depth, "--depth-topic", (IMAGE, COMPRESSED))
        no_color = str(cfg.color_topic).lower() == "none"
        chosen["color"] = None if no_color else pick("colour", cfg.color_topic, color, "--color-topic",
                                                      (IMAGE, COMPRESSED))
        chosen["camera_info"] = None
        if not cfg.intrinsics:
            sibling = chosen["depth"].rsplit("/", 1)[0] + "/camera_info" if chosen["depth"] else None
            if self.realsense is not None and not cfg.camera_info_topic:
                sibling = self.realsense.depth_info
            elif chosen["depth"] and sibling not in infos and bag.topics[chosen["depth"]][0] == COMPRESSED:
                # image_transport's topic: /camera/depth/image_raw/compressedDepth beside /camera/depth/camera_info
                sibling = chosen["depth"].rsplit("/", 2)[0] + "/camera_info"
            if not cfg.camera_info_topic and sibling in infos:
                chosen["camera_info"] = sibling
            else:
                chosen["camera_info"] = pick("camera info", cfg.camera_info_topic, infos, "--camera-info-topic",
                                             (CAMERA_INFO,))
        chosen["ground_truth"] = pick("ground truth", cfg.gt_topic, None, "--gt-topic", (POSE_STAMPED, ODOMETRY)) \
            if cfg.gt_topic else None
        poses = sorted(t for t in bag.topics if bag.topics[t][0] in (POSE_STAMPED, ODOMETRY))
        if poses and not cfg.gt_topic:  # a bag's poses may be anything (odometry, a plan): the user says which
            import logging

            logging.getLogger(__name__).info(
                f"the bag has pose topics ({', '.join(f'{t} ({bag.topics[t][0]})' for t in poses)}): --gt-topic "
                f"{poses[0]} evaluates the run against one (ATE, RPE; the trajectory then starts at its first "
                "pose); without it there is no ground truth and the trajectory starts at the identity")
        if ambiguous:
            raise InputError(self.root, "more than one candidate topic: " + "; ".join(ambiguous))
        if chosen["depth"] is None:
            raise InputError(self.root, f"no depth image topic (a {IMAGE} in {', '.join(DEPTH_ENCODINGS)}, or a "
                                        f"compressedDepth {COMPRESSED}); topics: {listed}")
        if not cfg.intrinsics and chosen["camera_info"] is None:
            raise InputError(self.root, f"no {CAMERA_INFO} topic to give the intrinsics: pass --intrinsics "
                                        "fx,fy,cx,cy or --intrinsics FILE")
        return chosen

    # -- one pass over the bag: stamps, sizes, the calibration, the ground truth -----------------
    def _index(self) -> None:
        topics = self.topics
        read = [t for t in (topics["depth"], topics["color"], topics["camera_info"], topics["ground_truth"]) if t]
        depth, color, gt, infos = [], [], [], []
        self._first_depth, self._first_color = None, None
        try:
            for topic, key, raw, log_ns in self.bag.scan(read):
                msgtype = self.bag.topics[topic][0]
                msg = self.bag.deserialize(raw, msgtype)
                if topic == topics["depth"]:
                    depth.append((_stamp(msg.header), key, log_ns * 1e-9))
                    self._first_depth = msg if self._first_depth is None else self._first_depth
                elif topic == topics["color"]:
                    color.append((_stamp(msg.header), key, log_ns * 1e-9))
                    self._first_color = msg if self._first_color is None else self._first_color
                elif topic == topics["camera_info"]:
                    infos.append((_stamp(msg.header), msg, log_ns * 1e-9))
                else:
                    gt.append((_stamp(msg.header), pose_of(msg, msgtype), log_ns * 1e-9))
        except InputError:
            raise
        except Exception as exc:  # rosbags' ReaderError, a CDR decoding error: the bag is damaged
            raise InputError(self.root, f"cannot read the bag's messages: {exc}") from None
        if not depth:
            raise InputError(self.root, f"empty sequence: no message on {topics['depth']}")

        # header stamps that cannot order the frames (all zero, all one value): the recorder's receive times
        header = np.array([s for s, _, _ in depth])
        self.stamps_from = "header stamps"
        if len(depth) > 1 and np.all(header == header[0]):
            what = "all zero" if header[0] == 0 else f"all {header[0]:.6f}"
            self.note(f"the header stamps of {topics['depth']} are {what}: the bag's receive times are used as the "
                      "frames' times (and for colour, camera info and ground truth)")
            self.stamps_from = "receive times (the header stamps are unusable)"
            depth, color = [(t, k, t) for _, k, t in depth], [(t, k, t) for _, k, t in color]
            infos, gt = [(t, m, t) for _, m, t in infos], [(t, T, t) for _, T, t in gt]
        self._gt_samples = [(s, T) for s, T, _ in gt]
        self._infos = [(s, m) for s, m, _ in infos]

        if any(b[0] < a[0] for a, b in zip(depth, depth[1:])):
            self.note(f"the depth messages on {topics['depth']} are not in header-stamp order in the bag: they are "
                      "taken in stamp order")
            depth.sort(key=lambda x: x[0])
        stamps = np.array([s for s, _, _ in depth])
        repeated = np.flatnonzero(np.diff(stamps) == 0) + 1
        if len(repeated):
            self.note(f"{len(repeated)} depth messages repeat the header stamp of the one before: left out")
            self.dropped_frames = len(repeated)
            left_out = set(repeated.tolist())
            depth = [d for i, d in enumerate(depth) if i not in left_out]
            stamps = np.array([s for s, _, _ in depth])
        self._stamps = stamps
        self._depth_keys = [k for _, k, _ in depth]
        where = f"{self.root}: {topics['depth']} message 0"
        first, self.encoding = depth_raw(self._first_depth, self.bag.topics[topics["depth"]][0], where)
        self.depth_scale = float(self.config.depth_scale) or DEPTH_ENCODINGS[self.encoding][1]
        self.depth_scale_source = ("--depth-scale / dataset.depth_scale" if self.config.depth_scale
                                   else f"REP 118 for {self.encoding}")
        self._size = (int(first.shape[1]), int(first.shape[0]))
        self._color_keys: list = [None] * len(depth)
        self.color_registered = None
        self._color_size = None
        if color:
            self._pair_color([(s, k) for s, k, _ in color])

    def _pair_color(self, color: list) -> None:
        from ti_fusion.io.trajectory import associate

        tolerance = self.config.max_time_difference
        color_stamps = np.array([s for s, _ in color])
        i_depth, i_color = associate(self._stamps, color_stamps, tolerance)
        for i, j in zip(i_depth, i_color):
            self._color_keys[i] = color[j][1]
        unpaired = len(self._stamps) - len(i_depth)
        if unpaired:
            self.note(f"{unpaired} of {len(self._stamps)} depth images have no colour image within {tolerance:g} s "
                      f"({self.stamps_from}): they are used without colour (--set dataset.max_time_difference=SECONDS "
                      "widens the window)")
        topic = self.topics["color"]
        first = color_image(self._first_color, self.bag.topics[topic][0], f"{self.root}: {topic} message 0")
        self._color_size = (first.shape[1], first.shape[0])
        depth_frame = self._first_depth.header.frame_id
        color_frame = self._first_color.header.frame_id
        self.color_registered = bool(depth_frame) and depth_frame == color_frame
        if self.realsense is not None:
            self.color_registered = False  # a separate sensor: registered through the recorded extrinsics
        elif not self.color_registered and depth_frame and color_frame:
            self.note(f"colour ({color_frame}) is not registered to depth ({depth_frame}): it only colours the map")
        elif not depth_frame or not color_frame:
            self.color_registered = None  # no frame_id to tell
        if self._color_size != self._size and self.realsense is None:
            (w, h), (dw, dh) = self._color_size, self._size
            where = f"in the depth's frame ({depth_frame}) " if self.color_registered else ""
            self.note(f"the colour images on {topic} are {w}x{h} {where}and the depth images {dw}x{dh}: colour is "
                      "not registered to depth, so it is resized to the depth images' size and only colours the map "
                      "(--color-topic none reads no colour)")
            self.color_registered = False

    # -- intrinsics and ground truth ------------------------------------------------------------
    def _find_intrinsics(self) -> Intrinsics:
        width, height = self._size
        if self.config.intrinsics:
            spec = self.config.intrinsics
            text = ",".join(str(v) for v in spec) if isinstance(spec, (list, tuple)) else spec
            self.intrinsics_source = f"{text} (--intrinsics / dataset.intrinsics)"
            return parse_intrinsics(spec, width, height)
        topic = self.topics["camera_info"]
        if not self._infos:
            raise InputError(self.root, f"no message on {topic}: pass --intrinsics fx,fy,cx,cy or FILE")
        info = self._info_in_force()
        if (int(info.width), int(info.height)) not in ((width, height), (0, 0)):
            raise InputError(self.root, f"{topic} is for {info.width}x{info.height} images, the depth images on "
                                        f"{self.topics['depth']} are {width}x{height} (pass --intrinsics)")
        self.intrinsics_source = f"{topic} (CameraInfo K)"
        return _camera(info, width, height, f"{self.root}: {topic}")

    def _info_in_force(self):
        """The CameraInfo of the selected frames: the last one at or before each frame's stamp (the first
        before any). One calibration serves the whole run, so a K that changes between selected frames is
        refused, naming the frame, with the selection that avoids it."""
        stamps = np.array([s for s, _ in self._infos])
        order = np.argsort(stamps, kind="stable")
        infos = [self._infos[i][1] for i in order]
        stamps = stamps[order]
        selected = self.indices
        in_force = np.maximum(np.searchsorted(stamps, self._stamps[selected], side="right") - 1, 0)
        first = infos[in_force[0]]

        def calibration(m):
            return (int(m.width), int(m.height), tuple(np.round(np.asarray(_field(m, "k"), np.float64), 9)))

        for n, i in zip(selected, in_force):
            if calibration(infos[i]) != calibration(first):
                topic, k0, k1 = self.topics["camera_info"], _field(first, "k"), _field(infos[i], "k")
                first_frame = selected[0]
                raise InputError(self.root, f"{topic} changes during the recording: {_k_text(k0)} up to frame "
                                            f"{n - 1}, {_k_text(k1)} from frame {n} (stamp {self._stamps[n]:.6f}); one "
                                            f"calibration serves a run: read the frames before the change (--start "
                                            f"{first_frame} --stop {n}) or after it (--start {n}), or state one with "
                                            "--intrinsics")
        return first

    def _realsense_calibration(self) -> None:
        """A RealSense recording's depth units, and its colour camera (intrinsics, extrinsics) for registration."""
        rs, cfg = self.realsense, self.config
        if not cfg.depth_scale and rs.depth_units:
            units = float(self._first(rs.depth_units).data)  # metres per depth unit
            if not np.isfinite(units) or units <= 0:
                raise InputError(self.root, f"{rs.depth_units}: depth units {units}: pass --depth-scale")
            self.depth_scale = float(f"{1.0 / units:.6g}")  # float32 0.001 → 1000, not 999.99995
            self.depth_scale_source = f"{rs.depth_units} ({units:.6g} m per unit, RealSense recording)"
        elif not cfg.depth_scale:
            self.note("the RealSense recording holds no Depth Units option: the depth is taken as millimetres")
        if self.topics["color"] is None or self.topics["color"] != rs.color:
            return
        if not (rs.color_info and rs.color_tf):
            self.note(f"the recording holds no {'camera_info' if not rs.color_info else 'extrinsics (tf)'} of the "
                      "colour stream: colour only colours the map, resized")
            return
        info = self._first(rs.color_info)
        w, h = self._color_size
        self.color_intrinsics = _camera(info, w, h, f"{self.root}: {rs.color_info}")
        depth_tf = transform_matrix(self._first(rs.depth_tf)) if rs.depth_tf else None
        self.color_extrinsics = depth_to_color(depth_tf, transform_matrix(self._first(rs.color_tf)))
        self.color_calibration_source = f"{rs.color_info} and {rs.color_tf} (RealSense recording)"

    def _stated_color_camera(self, spec: str) -> None:
        """The colour camera from ``--color-extrinsics`` (a file, or a transform topic of the bag) and the
        colour topic's camera_info; it replaces a RealSense recording's recorded extrinsics."""
        topic, option = self.topics["color"], f"--color-extrinsics {spec}"
        if topic is None:
            raise InputError(None, f"{option}: the bag gives no colour to register (no colour topic chosen)")
        if spec in self.bag.topics:
            msgtype = self.bag.topics[spec][0]
            if msgtype not in (TRANSFORM, TRANSFORM_STAMPED, TF_MESSAGE):
                raise InputError(self.root, f"{option}: a {msgtype} topic, not a transform ({TRANSFORM}, "
                                            f"{TRANSFORM_STAMPED} or {TF_MESSAGE})")
            T = extrinsics_from_message(self._first(spec), msgtype, self._first_depth.header.frame_id,
                                        self._first_color.header.frame_id, f"{self.root}: {spec}")
        elif Path(spec).is_file():
            T = read_extrinsics_file(spec)
        else:
            raise InputError(None, f"{option}: neither a file nor a topic of the bag")
        if self.config.color_intrinsics:
            w, h = self._color_size
            self.color_intrinsics = parse_intrinsics(self.config.color_intrinsics, w, h, option="--color-intrinsics")
            self.color_calibration_source = f"{self.config.color_intrinsics} (--color-intrinsics) and {spec} " \
                                            "(--color-extrinsics)"
        elif self.color_intrinsics is None:
            base = topic.rsplit("/", 2 if self.bag.topics[topic][0] == COMPRESSED else 1)[0]
            info = f"{base}/camera_info"
            if info not in self.bag.topics:
                raise InputError(self.root, f"{option}: registration needs the colour camera's intrinsics, and "
                                            f"there is no {info} beside {topic}")
            w, h = self._color_size
            self.color_intrinsics = _camera(self._first(info), w, h, f"{self.root}: {info}")
            self.color_calibration_source = f"{info} and {spec} (--color-extrinsics)"
        else:
            self.color_calibration_source = f"{self.color_calibration_source.split(' and ')[0]} and {spec} " \
                                            "(--color-extrinsics)"
        self.color_extrinsics = T
        self.color_registered = False  # not as recorded: the kernel registers it (ti_fusion/io/registration.py)
        self.notes = [n for n in self.notes if "only colours the map" not in n]

    def describe_format(self) -> str:
        line = super().describe_format() + f"; depth scale from {self.depth_scale_source}; times from {self.stamps_from}"
        if self.color_extrinsics is not None:
            C, t = self.color_intrinsics, self.color_extrinsics[:3, 3]
            line += (f"; colour camera fx {C.fx:g} fy {C.fy:g} cx {C.cx:g} cy {C.cy:g} at {C.width}x{C.height}, "
                     f"depth-to-colour translation ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m, "
                     f"rotation {np.degrees(np.arccos(np.clip((np.trace(self.color_extrinsics[:3, :3]) - 1) / 2, -1, 1))):.2f} deg "
                     f"({self.color_calibration_source})")
        return line

    def _ground_truth(self) -> list[np.ndarray | None]:
        from ti_fusion.io.datasets.tum import interpolate_pose
        from ti_fusion.io.trajectory import read_tum

        cfg = self.config
        files = [self.root / n for n in GROUND_TRUTH_FILES if self.root.is_dir() and (self.root / n).is_file()]
        if cfg.ground_truth and self.topics["ground_truth"]:
            raise InputError(None, "--ground-truth and --gt-topic both give the ground truth: keep one")
        if self.topics["ground_truth"]:
            if not self._gt_samples:
                raise InputError(self.root, f"--gt-topic {self.topics['ground_truth']}: no message")
            stamps = np.array([s for s, _ in self._gt_samples])
            poses = np.array([T for _, T in self._gt_samples])
            self.ground_truth_source = f"{self.topics['ground_truth']} (--gt-topic)"
            where = self.topics["ground_truth"]
        elif cfg.ground_truth or files:
            if len(files) > 1 and not cfg.ground_truth:
                raise InputError(self.root, f"holds {' and '.join(p.name for p in files)}: keep one ground truth")
            path = Path(cfg.ground_truth) if cfg.ground_truth else files[0]
            stamps, poses = read_tum(path)
            self.ground_truth_source = f"{path} ({'dataset.ground_truth' if cfg.ground_truth else 'in the bag folder'})"
            where = str(path)
        else:
            self.ground_truth_source = None
            return [None] * len(self._stamps)
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        tolerance = cfg.max_time_difference
        gt = [interpolate_pose(stamps, poses, t, tolerance) for t in self._stamps]
        if all(T is None for T in gt):
            raise InputError(self.root, f"ground truth {where}: no pose within {tolerance:g} s of any depth header "
                                        f"stamp ({self._stamps[0]:.6f} to {self._stamps[-1]:.6f}; the ground truth: "
                                        f"{stamps[0]:.6f} to {stamps[-1]:.6f})")
        return gt

    # -- the Dataset interface ------------------------------------------------------------------
    def _num_raw_frames(self) -> int:
        return len(self._stamps)

    def _load_raw(self, raw_index: int) -> Frame:
        topics, K = self.topics, self._intrinsics
        where = f"{self.root}: {topics['depth']} message {raw_index}"
        raw, _ = depth_raw(self._decode(topics["depth"], self._depth_keys[raw_index]),
                           self.bag.topics[topics["depth"]][0], where)
        if (raw.shape[1], raw.shape[0]) != self._size:
            raise InputError(None, f"{where}: image is {raw.shape[1]}x{raw.shape[0]}, the first is "
                                   f"{K.width}x{K.height}")
        depth = raw_to_metres(raw, self.depth_scale, self.config.depth_max)
        color = None
        if self._color_keys[raw_index] is not None:
            msgtype = self.bag.topics[topics["color"]][0]
            color = color_image(self._decode(topics["color"], self._color_keys[raw_index]), msgtype,
                                f"{self.root}: {topics['color']}")
            if (color.shape[1], color.shape[0]) != self._color_size:
                (w, h) = self._color_size
                raise InputError(None, f"{self.root}: {topics['color']}: the colour image of frame {raw_index} is "
                                       f"{color.shape[1]}x{color.shape[0]}, the first {w}x{h} (--color-topic none "
                                       "reads no colour)")
            if color.shape[:2] != depth.shape and self.color_extrinsics is None:
                color = cv2.resize(color, (K.width, K.height), interpolation=cv2.INTER_AREA)
        meta = {"depth_topic": topics["depth"], "color_topic": topics["color"]}
        if color is not None and self.color_extrinsics is not None:  # registered in the run loop's thread
            meta["color_camera"] = (self.color_intrinsics, self.color_extrinsics)
        return self._frame(raw_index, float(self._stamps[raw_index]), depth, color, meta)

    def _decode(self, topic: str, key):
        try:
            return self.bag.deserialize(self.bag.fetch(topic, key), self.bag.topics[topic][0])
        except InputError:
            raise
        except Exception as exc:
            raise InputError(self.root, f"cannot read a message of {topic}: {exc}") from None

    def describe(self) -> dict:
        info = super().describe()
        info.update(topics=dict(self.topics), depth_encoding=self.encoding, depth_scale_from=self.depth_scale_source,
                    color=self.topics["color"] is not None, color_registered=self.color_registered,
                    times_from=self.stamps_from, realsense=self.realsense is not None,
                    color_camera=None if self.color_extrinsics is None else {
                        "fx": self.color_intrinsics.fx, "fy": self.color_intrinsics.fy, "cx": self.color_intrinsics.cx,
                        "cy": self.color_intrinsics.cy, "width": self.color_intrinsics.width,
                        "height": self.color_intrinsics.height, "T_color_depth": self.color_extrinsics.tolist(),
                        "source": self.color_calibration_source},
                    ground_truth_from=self.ground_truth_source, truncated=self.bag.truncated,
                    ground_truth_frames=self.ground_truth_frames())
        return info

    def close(self) -> None:
        """Close the bag's files (also done when the dataset is garbage-collected)."""
        self._closer()

    # A reader process (ti_fusion.io.prefetch) gets the dataset pickled: everything but the open bag, which
    # it opens again (the index of frames, topics and calibration is the one made here).
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for name in ("bag", "_closer"):
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.bag, _ = open_bag(self.root)
        self._closer = weakref.finalize(self, self.bag.close)

    @staticmethod
    def detect(root: Path) -> str | None:
        """What identifies a bag: an .mcap or .db3 file, a rosbag2 folder's metadata.yaml, or the .mcap
        files of a folder that lost it; else None."""
        from ti_fusion.io.datasets.runlog import mcap_profile

        root = Path(root)
        if root.is_file():
            if root.suffix == ".mcap":  # an MCAP of another profile is no bag (ti-fusion's log.mcap: "log")
                return "a .mcap file" if mcap_profile(root) in ("ros2", None) else None
            if root.suffix == ".bag":
                return "a .bag file (ROS 1)"
            return "a .db3 file" if root.suffix == ".db3" else None
        meta = root / "metadata.yaml"
        if meta.is_file():
            try:
                head = meta.read_text(errors="replace")[:4096]
            except OSError:
                return None
            return "metadata.yaml (rosbag2)" if "rosbag2_bagfile_information" in head else None
        found = [p for p in sorted(root.glob("*.mcap")) if mcap_profile(p) == "ros2"]
        return found[0].name if found else None
