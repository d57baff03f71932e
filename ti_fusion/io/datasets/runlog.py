"""ti-fusion's own run log (``log.mcap``, or the run folder that holds it) replayed as a sequence.

The frames are the log's ``/camera/depth`` images (Foxglove ``RawImage``, 16UC1 millimetres), with the
``/camera/color`` image of the same time (JPEG: lossy), the intrinsics of ``/camera/calibration`` and
the ground truth of ``/gt/pose``. A run logs every frame's depth only with ``log.depth_every = 1``; a log
with fewer depth images than frames replays the ones it has, and a note says how many frames the run
had. The depth is the run's own after its range cut, quantised to 1 mm, so a replay tracks as the run
did to within that rounding, not bit for bit.

Detected from an ``.mcap`` file whose profile is not ``ros2`` and that has a ``/camera/depth`` channel of
``foxglove.RawImage`` (a ROS 2 bag is ``rosbag``'s), or from a folder holding such a ``log.mcap``.

A log whose run was killed ends without its summary (the index at the end of the file), possibly in the
middle of a record: it is read from the start up to the last whole chunk (``UnfinalisedLog``), as
``inspect`` reads it, and a note says so; frames are then found by the file offset of their chunk.
"""

from __future__ import annotations

import json
import weakref
from pathlib import Path

import numpy as np

from ti_fusion.config import DatasetConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Frame, RecordedSequence
from ti_fusion.io.datasets.imageio import depth_to_metres, intrinsics_from_numbers, parse_intrinsics

DEPTH, COLOR, CALIBRATION, GROUND_TRUTH = "/camera/depth", "/camera/color", "/camera/calibration", "/gt/pose"
DEPTH_SCHEMA = "foxglove.RawImage"
LOG_NAME = "log.mcap"


def mcap_profile(path: Path) -> str | None:
    """The profile string of an MCAP file's header ("ros2" for a ROS 2 bag), or None when it is no MCAP."""
    try:
        with open(path, "rb") as f:
            head = f.read(8 + 1 + 8 + 4 + 256)
    except OSError:
        return None
    if len(head) < 21 or head[:8] != b"\x89MCAP0\r\n" or head[8] != 0x01:
        return None
    n = int.from_bytes(head[17:21], "little")
    return head[21:21 + n].decode("utf-8", "replace")


def _log_file(root: Path) -> Path:
    return root / LOG_NAME if root.is_dir() else root


def _summary(reader):
    """The MCAP summary, or None for a file without one (a killed run's: its tail may be anything)."""
    try:
        return reader.get_summary()
    except Exception:  # a torn file: whatever the footer's place holds is not a footer
        return None


def _channels(path: Path) -> dict[str, str]:
    """{topic: schema name} of an MCAP file: from its summary, or read from the start when it has none."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = _summary(make_reader(f))
        if summary is None:
            return UnfinalisedLog(f, until_topic=DEPTH).topics()
    return {c.topic: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else ""
            for c in summary.channels.values()}


class UnfinalisedLog:
    """An MCAP file without a summary read from the start to its last whole record: its schemas and
    channels, and where each message is (the file offset of its chunk), so that one can be read again."""

    def __init__(self, f, until_topic: str | None = None):
        from mcap.records import Channel, Chunk, Message, Metadata, Schema
        from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk

        self.file = f
        self.schemas, self.channels, self.metadata = {}, {}, {}
        self.messages: list[tuple[str, int, int | None, object]] = []  # (topic, log time, chunk offset, unchunked)
        self.torn = False  # the file ends inside a record
        self._chunk = (None, [])  # the last chunk read again: (offset, its messages)
        f.seek(0)
        reader = StreamReader(f, skip_magic=False, emit_chunks=True, validate_crcs=True)
        stream, records = reader._stream, reader.records
        while True:
            offset = stream.count
            try:
                record = next(records)
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except StopIteration:
                break
            except CRCValidationError as exc:  # damage, not the cut of a killed run
                from ti_fusion.io.mcap_log import damage

                raise InputError(Path(getattr(f, "name", "log.mcap")), f"damaged at byte {offset}: {damage(exc)}; "
                                                                        "the file changed after it was written") from None
            except Exception:  # a torn record: the cut of a killed run
                self.torn = True
                break
            for item in inner:
                if isinstance(item, Schema):
                    self.schemas[item.id] = item
                elif isinstance(item, Channel):
                    self.channels[item.id] = item
                elif isinstance(item, Metadata):
                    self.metadata[item.name] = dict(item.metadata)
                elif isinstance(item, Message) and item.channel_id in self.channels:
                    topic = self.channels[item.channel_id].topic
                    chunked = isinstance(record, Chunk)
                    self.messages.append((topic, item.log_time, offset if chunked else None,
                                          None if chunked else item))
            if until_topic is not None and any(c.topic == until_topic for c in self.channels.values()):
                break

    def topics(self) -> dict[str, str]:
        return {c.topic: self.schemas[c.schema_id].name if c.schema_id in self.schemas else ""
                for c in self.channels.values()}

    def message(self, topic: str, t: int, offset: int | None, unchunked):
        """The raw ``Message`` record of ``topic`` at log time ``t`` in the chunk at ``offset``."""
        if unchunked is not None:
            return unchunked
        from mcap.records import Message
        from mcap.stream_reader import StreamReader, breakup_chunk

        if self._chunk[0] != offset:
            self.file.seek(offset)
            chunk = next(StreamReader(self.file, skip_magic=True, emit_chunks=True).records)
            self._chunk = (offset, [m for m in breakup_chunk(chunk) if isinstance(m, Message)])
        for m in self._chunk[1]:
            if m.log_time == t and self.channels[m.channel_id].topic == topic:
                return m
        return None

    def decoded(self, topic: str, t: int, offset: int | None, unchunked):
        """The decoded protobuf message (None when the chunk does not hold it)."""
        from mcap_protobuf.decoder import DecoderFactory

        m = self.message(topic, t, offset, unchunked)
        if m is None:
            return None
        channel = self.channels[m.channel_id]
        decode = DecoderFactory().decoder_for(channel.message_encoding, self.schemas.get(channel.schema_id))
        return decode(m.data)


class RunLogDataset(RecordedSequence):
    """A ti-fusion run log's depth (and colour) images as frames (see the module docstring)."""

    format = "log"
    identified_by = "a run log (log.mcap)"
    single_file = True
    reads_in_process = True  # one reader process, in order (concurrent_reads is False: one open file)
    depth_scale = 1000.0  # /camera/depth is 16UC1 millimetres

    @property
    def color_for_tracking(self) -> bool:  # the log does not say: the user's word (dataset.color_registered)
        return self.config.color_registered

    def __init__(self, root, config: DatasetConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        from mcap.reader import make_reader
        from mcap_protobuf.decoder import DecoderFactory

        super().__init__(root, downsample=downsample, start=start, stop=stop, stride=stride)
        self.config = cfg = config or DatasetConfig()
        self.path = _log_file(self.root)
        self.name = self.root.name if self.root.is_dir() else self.root.stem
        if not self.path.is_file():
            raise InputError(self.path, "run log does not exist")
        self._file = open(self.path, "rb")
        self._closer = weakref.finalize(self, self._file.close)
        self._unfinalised = None  # an UnfinalisedLog, and where each message is, for a log without summary
        try:
            self._reader = make_reader(self._file, validate_crcs=True, decoder_factories=[DecoderFactory()])
            if _summary(self._reader) is None:
                messages = self._read_unfinalised()
            else:
                messages = ((channel.topic, message.log_time, msg) for _, channel, message, msg in
                            self._reader.iter_decoded_messages(topics=[DEPTH, COLOR, CALIBRATION, GROUND_TRUTH],
                                                               log_time_order=True))
            depth, color, gt, calibration = [], {}, {}, None
            for topic, t, msg in messages:
                if topic == DEPTH:
                    depth.append((t, (msg.width, msg.height, msg.encoding)))
                elif topic == COLOR:
                    color[t] = True
                elif topic == CALIBRATION:
                    calibration = calibration or msg
                else:
                    from ti_fusion.io.mcap_log import pose_from_msg

                    gt[t] = pose_from_msg(msg)
        except InputError:
            raise
        except Exception as exc:  # a damaged file: mcap's and protobuf's errors
            raise InputError(self.path, f"cannot read the run log: {exc}") from None
        if not depth:
            raise InputError(self.path, f"no {DEPTH} images in the log: nothing to replay")
        encodings = {e for _, (_, _, e) in depth}
        if encodings != {"16UC1"}:
            raise InputError(self.path, f"{DEPTH} images in {', '.join(sorted(encodings))}, expected 16UC1")
        if self._unfinalised is not None:
            torn = ""
            if len(depth) > 1 and depth[-1][0] not in color and any(t in color for t, _ in depth[:-1]):
                depth = depth[:-1]  # the cut fell between the last frame's depth and its colour
                self.dropped_frames += 1
                torn = " (the last depth image's colour was cut off: left out)"
            self.note(f"the log ends without its summary (its run was stopped before finishing it"
                      f"{', in the middle of a record' if self._unfinalised.torn else ''}): the {len(depth)} depth "
                      f"images written before the cut are replayed{torn}")
        self._times = [t for t, _ in depth]
        self._has_color = [t in color for t in self._times]
        self._gt_poses = [gt.get(t) for t in self._times]
        width, height, _ = depth[0][1]
        if cfg.intrinsics:
            self.intrinsics_source = f"{cfg.intrinsics} (--intrinsics / dataset.intrinsics)"
            self._intrinsics = parse_intrinsics(cfg.intrinsics, width, height)
        elif calibration is not None:
            self.intrinsics_source = f"{CALIBRATION} in the log"
            self._intrinsics = intrinsics_from_numbers(list(calibration.K), width, height, self.path)
        else:
            raise InputError(self.path, f"no {CALIBRATION} in the log: pass --intrinsics fx,fy,cx,cy or FILE")
        frames = self._frames_of_run()
        if frames is not None and frames > len(self._times) and self._unfinalised is None:
            self.note(f"the run had {frames} frames and logged the depth of {len(self._times)} (log.depth_every > 1): "
                      "those are replayed")

    def _read_unfinalised(self):
        """(topic, log time, decoded message) of the replayed topics of a log without summary, in log-time
        order, read up to the cut; a note says how far the log goes."""
        log = self._unfinalised = UnfinalisedLog(self._file)
        wanted = sorted((m for m in log.messages if m[0] in (DEPTH, COLOR, CALIBRATION, GROUND_TRUTH)),
                        key=lambda m: m[1])
        self._where = {(topic, t): (offset, unchunked) for topic, t, offset, unchunked in wanted}
        for topic, t, offset, unchunked in wanted:
            if topic == DEPTH:  # only the size and encoding are needed now: read from the chunk's raw bytes
                yield topic, t, log.decoded(topic, t, offset, unchunked)
            elif topic == COLOR:
                yield topic, t, None
            else:
                yield topic, t, log.decoded(topic, t, offset, unchunked)

    def _frames_of_run(self) -> int | None:
        """The frame count of the run's dataset record (metadata "dataset", JSON values), if the log has it."""
        try:
            for record in self._reader.iter_metadata():
                if record.name == "dataset":
                    frames = json.loads(record.metadata.get("frames", "null"))
                    return frames if isinstance(frames, int) else None
        except Exception:  # a log without that record replays all the same
            return None
        return None

    def _num_raw_frames(self) -> int:
        return len(self._times)

    def _message(self, topic: str, t: int):
        if self._unfinalised is not None:
            msg = self._unfinalised.decoded(topic, t, *self._where.get((topic, t), (None, None)))
            if msg is None:
                raise InputError(self.path, f"no {topic} message at {t} ns (was the log changed while read?)")
            return msg
        try:
            found = self._reader.iter_decoded_messages(topics=[topic], starting_at=t, ending_at=t)
        except TypeError:  # mcap before 1.6 names the bounds start_time and end_time (exclusive)
            found = self._reader.iter_decoded_messages(topics=[topic], start_time=t, end_time=t + 1)
        for _, _, _, msg in found:
            return msg
        raise InputError(self.path, f"no {topic} message at {t} ns (was the log changed while read?)")

    def _load_raw(self, raw_index: int) -> Frame:
        import cv2

        t, K = self._times[raw_index], self._intrinsics
        msg = self._message(DEPTH, t)
        raw = np.frombuffer(msg.data, dtype="<u2", count=msg.height * msg.step // 2)
        raw = raw.reshape(msg.height, msg.step // 2)[:, : msg.width]
        if (msg.width, msg.height) != (K.width, K.height):
            raise InputError(self.path, f"{DEPTH} image {raw_index} is {msg.width}x{msg.height}, the first "
                                        f"{K.width}x{K.height}")
        depth = depth_to_metres(raw, self.depth_scale, self.config.depth_max)
        color = None
        if self._has_color[raw_index]:
            image = cv2.imdecode(np.frombuffer(self._message(COLOR, t).data, dtype=np.uint8), cv2.IMREAD_COLOR)
            if image is None or image.shape[:2] != depth.shape:
                raise InputError(self.path, f"{COLOR} image at {t} ns cannot be decoded at the depth's size")
            color = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        return self._frame(raw_index, t * 1e-9, depth, color, {"log": str(self.path)})

    def describe(self) -> dict:
        info = super().describe()
        info.update(color=any(self._has_color), ground_truth_frames=self.ground_truth_frames())
        return info

    # A reader process (ti_fusion.io.prefetch) gets the dataset pickled: everything but the open file and its
    # readers, which it opens again.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for name in ("_file", "_closer", "_reader", "_unfinalised"):
            state.pop(name, None)
        state["_was_unfinalised"] = self._unfinalised is not None
        return state

    def __setstate__(self, state: dict) -> None:
        from mcap.reader import make_reader
        from mcap_protobuf.decoder import DecoderFactory

        unfinalised = state.pop("_was_unfinalised")
        self.__dict__.update(state)
        self._file = open(self.path, "rb")
        self._closer = weakref.finalize(self, self._file.close)
        self._reader = make_reader(self._file, decoder_factories=[DecoderFactory()])
        self._unfinalised = UnfinalisedLog(self._file) if unfinalised else None

    @staticmethod
    def detect(root: Path) -> str | None:
        """A ti-fusion run log: an .mcap file (or a folder's log.mcap) whose profile is not ros2, with a
        /camera/depth channel of RawImage; else None."""
        path = _log_file(Path(root))
        if not path.is_file() or mcap_profile(path) in (None, "ros2"):
            return None
        try:
            channels = _channels(path)
        except Exception:
            return None
        if channels.get(DEPTH) != DEPTH_SCHEMA:
            return None
        return f"{path.name} (a ti-fusion run log)" if Path(root).is_file() else f"{LOG_NAME} (a ti-fusion run log)"
