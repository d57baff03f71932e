"""ti-fusion's own run log (``log.mcap``, or the run folder that holds it) replayed as a sequence.

The frames are the log's ``/camera/depth`` images (Foxglove ``RawImage``, 16UC1 millimetres), with the
``/camera/color`` image of the same time (JPEG: lossy), the intrinsics of ``/camera/calibration`` and
the ground truth of ``/gt/pose``. A run logs every frame's depth only with ``log.depth_every = 1``; a log
with fewer depth images than frames replays the ones it has, and a note says how many frames the run
had. The depth is the run's own after its range cut, quantised to 1 mm, so a replay tracks as the run
did to within that rounding, not bit for bit.

Detected from an ``.mcap`` file whose profile is not ``ros2`` and that has a ``/camera/depth`` channel of
``foxglove.RawImage`` (a ROS 2 bag is ``rosbag``'s), or from a folder holding such a ``log.mcap``.
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


def _channels(path: Path) -> dict[str, str]:
    """{topic: schema name} of a finalised MCAP file (from its summary)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None:
        return {}
    return {c.topic: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else ""
            for c in summary.channels.values()}


class RunLogDataset(RecordedSequence):
    """A ti-fusion run log's depth (and colour) images as frames (see the module docstring)."""

    format = "log"
    depth_scale = 1000.0  # /camera/depth is 16UC1 millimetres

    @property
    def colour_for_tracking(self) -> bool:  # the log does not say: the user's word (dataset.color_registered)
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
        try:
            self._reader = make_reader(self._file, decoder_factories=[DecoderFactory()])
            if self._reader.get_summary() is None:
                raise InputError(self.path, "the log has no summary (its run did not finish writing it): not "
                                            "replayable")
            depth, color, gt, calibration = [], {}, {}, None
            for _, channel, message, msg in self._reader.iter_decoded_messages(
                    topics=[DEPTH, COLOR, CALIBRATION, GROUND_TRUTH], log_time_order=True):
                t = message.log_time
                if channel.topic == DEPTH:
                    depth.append((t, (msg.width, msg.height, msg.encoding)))
                elif channel.topic == COLOR:
                    color[t] = True
                elif channel.topic == CALIBRATION:
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
        if frames is not None and frames > len(self._times):
            self.note(f"the run had {frames} frames and logged the depth of {len(self._times)} (log.depth_every > 1): "
                      "those are replayed")

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
        info.update(colour=any(self._has_color), ground_truth_frames=self.ground_truth_frames())
        return info

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
