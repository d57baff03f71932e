"""A RealSense camera as a sequence: ``ti-fusion slam --camera realsense[:SERIAL]`` (pyrealsense2, the
optional extra ``pip install 'ti-fusion[realsense]'``).

The device's depth (z16) and colour (rgb8) streams at 640×480, 30 Hz, are started with the SDK's pipeline;
the depth units come from the depth sensor, the intrinsics from the depth stream's profile, and the colour
camera's intrinsics and the depth-to-colour extrinsics from theirs, so colour is registered to depth by
the same kernel as a recording's (``ti_fusion/io/registration.py``). Frames are handed to the run loop
like any dataset's (one loop owner: the pipeline), in arrival order; a frame's time is the depth frame's
timestamp in seconds. The stream has no end of its own (``endless``): the run ends at ``--frames N``, or
at the first Ctrl-C, which ends the stream as a recording's end would (the run finishes with its map and
summary; a second Ctrl-C stops it at once, keeping the trajectory and a finalised log); the device is
stopped when the dataset is closed.

``realsense:FILE.bag`` plays a recording back through the SDK (``enable_device_from_file``, not in real
time), which runs the same calls as a device: the tests' way in, and a way to check a recording as the
live path sees it. Its end ends the run (``StreamEnded``).
"""

from __future__ import annotations

import weakref
from pathlib import Path

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.datasets.imageio import depth_to_metres

WIDTH, HEIGHT, FPS = 640, 480, 30
WAIT_MS = 5000          # a device that sends no frame for this long is gone
OPEN_ENDED = 2**31 - 1  # frames in a stream without --frames: until Ctrl-C
KEEP = 8                # frames kept after they were read (the run's first-frame check reads ahead)


class StreamEnded(Exception):
    """A played-back recording has no more frames: the run ends there (``Pipeline`` stops its loop)."""


def parse_camera(spec: str) -> tuple[str | None, Path | None]:
    """(serial, recording) of ``realsense``, ``realsense:SERIAL`` or ``realsense:FILE.bag``."""
    kind, _, rest = str(spec).partition(":")
    if kind.strip().lower() != "realsense":
        raise InputError(None, f"--camera {spec}: unknown camera kind {kind!r}; expected realsense[:SERIAL]")
    rest = rest.strip()
    if rest.endswith(".bag"):
        if not Path(rest).is_file():
            raise InputError(rest, "recording to play back (--camera realsense:FILE.bag) does not exist")
        return None, Path(rest)
    return (rest or None), None


def _pyrealsense2():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        why = "is not installed" if getattr(exc, "name", "") in ("pyrealsense2", "pyrealsense2.pyrealsense2") \
            and "lib" not in str(exc) else f"cannot be loaded ({exc})"
        raise InputError(None, f"--camera realsense needs pyrealsense2, which {why}: pip install 'ti-fusion[realsense]' "
                               "(Linux x86_64, Windows; on Linux the SDK also needs libusb-1.0)") from None
    return rs


def _stop_pipeline(pipe, playback) -> None:
    """Stop the streams; a playback goes back to real time first, so that the SDK's reader is not blocked on a
    full queue while the pipeline stops (librealsense's non-real-time stop can hang or abort)."""
    if playback is not None:
        playback.set_real_time(True)
    pipe.stop()


class RealSenseCamera(Dataset):
    """Frames from a RealSense device (or the SDK's playback of a recording) as a Dataset."""

    format = "realsense"

    def __init__(self, spec: str = "realsense", config=None, downsample: int = 1,
                 start: int = 0, stop: int | None = None, stride: int = 1):
        serial, recording = parse_camera(spec)
        super().__init__(recording or Path(f"realsense{':' + serial if serial else ''}"), downsample=downsample,
                         start=start, stop=stop, stride=stride)
        from ti_fusion.config import DatasetConfig

        # not ``config``: the run's first-frame check would read frames ahead of the loop (a short playback ends)
        self.dataset_config = config or DatasetConfig()
        self.name = recording.stem if recording else f"realsense-{serial or 'camera'}"
        self.recording = recording
        rs = _pyrealsense2()
        self._rs = rs
        cfg = rs.config()
        if recording is not None:
            cfg.enable_device_from_file(str(recording), repeat_playback=False)
            cfg.enable_all_streams()
        else:
            devices = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
            if not devices:
                raise InputError(None, "--camera realsense: no RealSense camera is attached (pyrealsense2 found no "
                                       "device; check the USB 3 cable, or `rs-enumerate-devices`)")
            if serial and serial not in devices:
                raise InputError(None, f"--camera realsense:{serial}: no camera with that serial number; attached: "
                                       f"{', '.join(devices)}")
            if serial:
                cfg.enable_device(serial)
            cfg.enable_stream(rs.stream.depth, WIDTH, HEIGHT, rs.format.z16, FPS)
            cfg.enable_stream(rs.stream.color, WIDTH, HEIGHT, rs.format.rgb8, FPS)
        self._pipe = rs.pipeline()
        try:
            playback = None
            if recording is not None:  # every recorded frame, as fast as the run takes them, from the first one
                playback = cfg.resolve(rs.pipeline_wrapper(self._pipe)).get_device().as_playback()
                playback.set_real_time(False)
                # paused until the pipeline has started: a playback that reads while the pipeline starts hands
                # frames to a syncer not yet listening, and which are lost depends on the threads' timing
                playback.pause()
            profile = self._pipe.start(cfg)  # starts the device the config resolved (it keeps it)
            if playback is not None:
                playback.resume()
        except RuntimeError as exc:
            raise InputError(None, f"--camera {spec}: the camera's streams cannot be started: {exc}") from None
        device = profile.get_device()
        self._stop = weakref.finalize(self, _stop_pipeline, self._pipe,
                                      device.as_playback() if recording is not None else None)
        self.device_name = device.get_info(rs.camera_info.name)
        where = "the recording played back by pyrealsense2" if recording else f"the device ({self.device_name})"
        units = device.first_depth_sensor().get_depth_scale()  # metres per depth unit
        self.depth_scale = float(f"{1.0 / units:.6g}")
        self.depth_scale_source = f"{where}: depth units {units:.6g} m"
        depth_profile = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        self._intrinsics = self._camera(depth_profile.get_intrinsics())
        self.intrinsics_source = where
        self.color_intrinsics, self.color_extrinsics = None, None
        color = [s for s in profile.get_streams() if s.stream_type() == rs.stream.color]
        if color:
            color_profile = color[0].as_video_stream_profile()
            self.color_intrinsics = self._camera(color_profile.get_intrinsics())
            e = depth_profile.get_extrinsics_to(color_profile)  # rotation column-major, p_color = R p_depth + t
            T = np.eye(4)
            T[:3, :3] = np.asarray(e.rotation, dtype=np.float64).reshape(3, 3).T
            T[:3, 3] = e.translation
            self.color_extrinsics = T
        self._frames: dict[int, tuple] = {}  # index → (time, raw depth, colour): read once, in order
        self._next = 0

    def _camera(self, i) -> Intrinsics:
        if any(i.coeffs):
            self.note(f"the {i.width}x{i.height} stream's {i.model} distortion {list(i.coeffs)} is not applied")
        return Intrinsics(float(i.fx), float(i.fy), float(i.ppx), float(i.ppy), int(i.width), int(i.height))

    # -- the Dataset interface ------------------------------------------------------------------
    @property
    def raw_intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def indices(self):
        start, stop, stride = self._selection
        return range(OPEN_ENDED)[start:stop:stride]  # a range: the stream's length is unknown

    def _num_raw_frames(self) -> int:
        return OPEN_ENDED

    @property
    def endless(self) -> bool:
        return self._selection[1] is None  # no --frames (or --stop): until Ctrl-C

    def _read(self) -> tuple:
        """The next (time s, raw uint16 depth, RGB colour or None) from the SDK."""
        rs = self._rs
        while True:
            ok, frames = self._pipe.try_wait_for_frames(WAIT_MS)
            if not ok:
                if self.recording is not None:
                    raise StreamEnded(f"{self.recording}: the recording ends after {self._next} frames")
                raise InputError(None, f"--camera realsense: no frame from the camera for {WAIT_MS / 1000:g} s "
                                       "(unplugged?)")
            depth = frames.get_depth_frame()
            if not depth:
                continue
            color = frames.get_color_frame()
            image = None
            if color and color.get_profile().format() in (rs.format.rgb8, rs.format.bgr8):
                image = np.asanyarray(color.get_data()).copy()
                if color.get_profile().format() == rs.format.bgr8:
                    image = np.ascontiguousarray(image[..., ::-1])
            return depth.get_timestamp() / 1000.0, np.asanyarray(depth.get_data()).copy(), image

    def _load_raw(self, raw_index: int) -> Frame:
        while self._next <= raw_index:  # frames arrive in order: read up to the one asked for
            self._frames[self._next] = self._read()
            self._frames.pop(self._next - KEEP, None)
            self._next += 1
        if raw_index not in self._frames:
            raise InputError(None, f"--camera realsense: frame {raw_index} was read and let go (frames are read once, "
                                   "in order)")
        t, raw, color = self._frames[raw_index]
        depth = depth_to_metres(raw, self.depth_scale, self.dataset_config.depth_max)
        meta = {"camera": self.name}
        if color is not None and self.color_extrinsics is not None:
            meta["color_camera"] = (self.color_intrinsics, self.color_extrinsics)
        return Frame(index=raw_index, timestamp=t, depth=depth, intrinsics=self._intrinsics, color=color, meta=meta)

    def describe_format(self) -> str:
        line = super().describe_format() + f"; depth scale from {self.depth_scale_source}"
        if self.color_extrinsics is not None:
            C, t = self.color_intrinsics, self.color_extrinsics[:3, 3]
            line += (f"; colour camera fx {C.fx:g} fy {C.fy:g} cx {C.cx:g} cy {C.cy:g} at {C.width}x{C.height}, "
                     f"depth-to-colour translation ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m (registered to depth)")
        return line

    def describe(self) -> dict:
        info = super().describe()
        info.update(camera=self.device_name, recording=str(self.recording) if self.recording else None,
                    depth_scale_from=self.depth_scale_source, color=self.color_extrinsics is not None)
        return info

    def close(self) -> None:
        """Stop the device's streams (also done when the dataset is garbage-collected)."""
        self._stop()
