"""RealSense recordings: the ROS 1 bags that the RealSense Viewer, ``rs-record`` and
``rs2::recorder`` write, recognised by the SDK's own topic names.

Layout (librealsense's rosbag format, version 3)::

    /device_0/sensor_0/Depth_0/image/data         sensor_msgs/Image, mono16 (Z16)
    /device_0/sensor_0/Depth_0/info/camera_info   sensor_msgs/CameraInfo of that stream
    /device_0/sensor_0/Depth_0/tf/0               geometry_msgs/Transform: the stream's extrinsics
    /device_0/sensor_0/option/Depth Units/value   std_msgs/Float32: metres per depth unit
    /device_0/sensor_1/Color_0/image/data         sensor_msgs/Image, rgb8/bgr8/...
    /device_0/sensor_1/Color_0/info/camera_info
    /device_0/sensor_1/Color_0/tf/0

Every stream's ``tf/0`` holds the extrinsics from the device's reference stream (the depth stream
itself: identity) to that stream: p_stream = R p_ref + t. pyrealsense2's playback of the shared D435
recording reports ``depth.get_extrinsics_to(color)`` as exactly the colour stream's ``tf/0`` (translation
(0.01431, 0.00060, 0.00061) m, the same rotation). Both images carry ``frame_id`` "0", which says nothing
about registration: the colour camera is a separate sensor, so its colour is registered to depth through
these extrinsics and the two camera_infos, never taken as registered.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np


_STREAM = re.compile(r"^/device_(\d+)/sensor_(\d+)/([A-Za-z]+)_(\d+)/image/data$")


@dataclass
class RealSenseTopics:
    """The topics of one RealSense recording that ti-fusion reads (None where the recording lacks one)."""

    depth: str
    depth_info: str | None
    depth_units: str | None
    depth_tf: str | None
    color: str | None
    color_info: str | None
    color_tf: str | None

    def stream(self, topic: str) -> str:
        """``/device_0/sensor_0/Depth_0`` of ``/device_0/sensor_0/Depth_0/image/data``."""
        return topic.rsplit("/image/data", 1)[0]


def recognise(topics: dict, depth_topic: str | None = None, color_topic: str | None = None) -> RealSenseTopics | None:
    """The RealSense topics of a bag whose depth stream has the SDK's names, else None. ``depth_topic`` /
    ``color_topic``: the user's choice, when given (``none`` for colour: no colour)."""
    streams = {}
    for topic in topics:
        m = _STREAM.match(topic)
        if m:
            streams.setdefault(m.group(3).lower(), []).append(topic)
    depths = [depth_topic] if depth_topic else streams.get("depth", [])
    if len(depths) != 1 or not _STREAM.match(depths[0]):
        return None
    depth = depths[0]
    device, sensor = _STREAM.match(depth).group(1, 2)
    if color_topic and str(color_topic).lower() == "none":
        colors = []
    elif color_topic:
        colors = [color_topic]
    else:
        colors = [t for t in streams.get("color", []) if _STREAM.match(t).group(1) == device]
    color = colors[0] if len(colors) == 1 else None

    def have(topic):
        return topic if topic in topics else None

    units = have(f"/device_{device}/sensor_{sensor}/option/Depth Units/value")
    base_d = depth.rsplit("/image/data", 1)[0]
    base_c = color.rsplit("/image/data", 1)[0] if color and _STREAM.match(color) else None
    return RealSenseTopics(depth=depth, depth_info=have(f"{base_d}/info/camera_info"), depth_units=units,
                           depth_tf=have(f"{base_d}/tf/0"), color=color,
                           color_info=have(f"{base_c}/info/camera_info") if base_c else None,
                           color_tf=have(f"{base_c}/tf/0") if base_c else None)


def depth_to_color(depth_tf: np.ndarray | None, color_tf: np.ndarray) -> np.ndarray:
    """T_color_depth (p_color = T p_depth) from the two streams' extrinsics (reference to stream)."""
    depth_from_ref = np.eye(4) if depth_tf is None else depth_tf
    return color_tf @ np.linalg.inv(depth_from_ref)
