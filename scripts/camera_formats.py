"""One synthetic sequence written in every camera format ti-fusion reads, each run with ``ti-fusion slam``:
the ATE per format (the table in docs/DATA.md). The formats: the TUM folder (``ti-fusion synth``), ROS 2 bags (raw
32FC1, compressedDepth 16UC1 and 32FC1 with JPEG colour), ROS 1 bags (raw 16UC1, compressedDepth 16UC1),
a ROS 1 bag whose colour comes from a second camera beside the depth camera (``--color-extrinsics``),
and a bag laid out as a RealSense recording (the SDK's topics, its depth units, its tf/0 extrinsics).

    .venv/bin/python scripts/camera_formats.py --scene room --frames 60 --out /tmp/formats
    .venv/bin/python scripts/camera_formats.py --scene wall --frames 90 --color-weight 0.01 --only tum,offset

Prints a Markdown table (format, files, ATE, failures) and writes it to OUT/table.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.geometry import make_pose, rot_to_quat, so3_exp

FX = 262.5  # the synthetic camera at 320×240
T_OFFSET = make_pose(so3_exp(np.array([0.01, -0.02, 0.01])), [0.025, 0.003, -0.002])  # colour camera, 2.5 cm aside
K_COLOR = Intrinsics(fx=300.0, fy=301.0, cx=165.0, cy=118.0, width=320, height=240)
DEPTH, COLOR, INFO, COLOR_INFO, GT = ("/camera/depth/image_rect_raw", "/camera/color/image_raw",
                                      "/camera/depth/camera_info", "/camera/color/camera_info", "/ground_truth/pose")


def _stores():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.LATEST), get_typestore(Stores.ROS1_NOETIC)


STORE, STORE1 = _stores()
MSG = STORE.types


def _header(t: float, frame: str):
    ns = round(t * 1e9)
    return MSG["std_msgs/msg/Header"](stamp=MSG["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                      frame_id=frame)


def _image(t, a, encoding, frame):
    a = np.ascontiguousarray(a)
    return MSG["sensor_msgs/msg/Image"](header=_header(t, frame), height=a.shape[0], width=a.shape[1],
                                        encoding=encoding, is_bigendian=0, step=a.strides[0],
                                        data=a.view(np.uint8).reshape(-1))


def _info(t, w, h, k, frame):
    fx, fy, cx, cy = k
    roi = MSG["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return MSG["sensor_msgs/msg/CameraInfo"](header=_header(t, frame), height=h, width=w, distortion_model="plumb_bob",
                                             d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]),
                                             r=np.eye(3).reshape(-1), p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]),
                                             binning_x=0, binning_y=0, roi=roi)


def _pose(t, T):
    q, p = rot_to_quat(T[:3, :3]), T[:3, 3]
    return MSG["geometry_msgs/msg/PoseStamped"](header=_header(t, "world"), pose=MSG["geometry_msgs/msg/Pose"](
        position=MSG["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
        orientation=MSG["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def _transform(T):
    q, p = rot_to_quat(T[:3, :3]), T[:3, 3]
    return MSG["geometry_msgs/msg/Transform"](translation=MSG["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                                              rotation=MSG["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))


def ros1(msg):
    """The ROS 1 form of a message built here (CameraInfo's K/D, Header's seq)."""
    cls = STORE1.types[msg.__msgtype__]
    values = {}
    for name in cls.__dataclass_fields__:
        if name == "__msgtype__":
            continue
        value = 0 if name == "seq" else getattr(msg, name, None)
        value = getattr(msg, name.lower()) if value is None else value
        values[name] = ros1(value) if hasattr(value, "__msgtype__") else value
    return cls(**values)


def write_bag(path: Path, shots, *, ros1_bag: bool, depth: str, color: str, color_k=None, color_frame="camera_optical"):
    """``shots`` = [(t, depth metres, RGB, pose)]; ``depth`` raw32 | raw16 | cd16 | cd32; ``color`` rgb8 | jpeg."""
    from rosbags import rosbag1, rosbag2

    from ti_fusion.io.datasets.compressed import encode_compressed_depth

    compressed = depth.startswith("cd")
    image_t, comp_t, info_t = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
    store = STORE1 if ros1_bag else STORE
    writer = rosbag1.Writer(path) if ros1_bag else rosbag2.Writer(path, version=9)
    with writer as w:
        depth_topic = DEPTH + "/compressedDepth" if compressed else DEPTH
        conns = {k: w.add_connection(topic, t, typestore=store) for k, topic, t in (
            ("d", depth_topic, comp_t if compressed else image_t), ("c", COLOR, comp_t if color == "jpeg" else image_t),
            ("i", INFO, info_t), ("g", GT, "geometry_msgs/msg/PoseStamped"))}
        if color_k is not None:
            conns["ci"] = w.add_connection(COLOR_INFO, info_t, typestore=store)
        for t, z, rgb, T in shots:
            h, wd = z.shape
            records = []
            if depth == "raw32":
                records.append(("d", image_t, _image(t, z, "32FC1", "camera_optical")))
            else:
                enc = "32FC1" if depth == "cd32" else "16UC1"
                units = z if enc == "32FC1" else np.round(z * 1000).astype(np.uint16)
                if compressed:
                    data = np.frombuffer(encode_compressed_depth(units, enc), np.uint8)
                    records.append(("d", comp_t, MSG[comp_t](header=_header(t, "camera_optical"),
                                                             format=f"{enc}; compressedDepth png", data=data)))
                else:
                    records.append(("d", image_t, _image(t, units, enc, "camera_optical")))
            records.append(("i", info_t, _info(t, wd, h, (FX, FX, (wd - 1) / 2, (h - 1) / 2), "camera_optical")))
            if color == "jpeg":
                data = cv2.imencode(".jpg", rgb[..., ::-1])[1].reshape(-1)
                records.append(("c", comp_t, MSG[comp_t](header=_header(t, color_frame),
                                                         format="rgb8; jpeg compressed bgr8", data=data)))
            else:
                records.append(("c", image_t, _image(t, rgb, "rgb8", color_frame)))
            if color_k is not None:
                records.append(("ci", info_t, _info(t, rgb.shape[1], rgb.shape[0], color_k, color_frame)))
            records.append(("g", "geometry_msgs/msg/PoseStamped", _pose(t, T)))
            for key, msgtype, msg in records:
                raw = STORE1.serialize_ros1(ros1(msg), msgtype) if ros1_bag else STORE.serialize_cdr(msg, msgtype)
                w.write(conns[key], round(t * 1e9), raw)
    return path


def write_realsense_bag(path: Path, shots, units: float = 0.001):
    """The SDK's layout: Depth_0 mono16 in ``units``, Color_0 rgb8 from the offset camera, tf/0 of each stream,
    frame_id "0" on both images; ground truth on /ground_truth/pose (no RealSense recording has it)."""
    from rosbags import rosbag1

    d, c = "/device_0/sensor_0/Depth_0", "/device_0/sensor_1/Color_0"
    h, w = shots[0][1].shape
    with rosbag1.Writer(path) as bag:
        conns = {}

        def put(topic, msgtype, msg, t):
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=STORE1)
            bag.write(conns[topic], round(t * 1e9), STORE1.serialize_ros1(ros1(msg), msgtype))

        t0 = shots[0][0]
        put(f"{d}/info/camera_info", "sensor_msgs/msg/CameraInfo", _info(0, w, h, (FX, FX, (w - 1) / 2, (h - 1) / 2), ""), t0)
        put(f"{c}/info/camera_info", "sensor_msgs/msg/CameraInfo", _info(0, w, h, K_COLOR.as_tuple(), ""), t0)
        put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", MSG["std_msgs/msg/Float32"](data=units), t0)
        put(f"{d}/tf/0", "geometry_msgs/msg/Transform", _transform(np.eye(4)), t0)
        put(f"{c}/tf/0", "geometry_msgs/msg/Transform", _transform(T_OFFSET), t0)
        for t, z, rgb, T in shots:
            put(f"{d}/image/data", "sensor_msgs/msg/Image", _image(t, np.round(z / units).astype(np.uint16), "mono16", "0"), t)
            put(f"{c}/image/data", "sensor_msgs/msg/Image", _image(t, rgb, "rgb8", "0"), t)
            put(GT, "geometry_msgs/msg/PoseStamped", _pose(t, T), t)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="room")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--color-weight", type=float, default=0.0, help="icp.color_weight of every run")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--only", default="", help="comma-separated row keys (tum,ros2-32,ros2-cd16,ros2-cd32,"
                                                "ros1-16,ros1-cd16,offset,offset-unregistered,realsense)")
    args = ap.parse_args()
    from ti_fusion.backend import init_backend
    from ti_fusion.cli.main import main as cli
    from ti_fusion.cli.synth import write_tum_sequence
    from ti_fusion.config import SynthConfig
    from ti_fusion.io.trajectory import read_tum
    from ti_fusion.synthetic.scene import SyntheticSequence

    init_backend("cpu")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    synth = SynthConfig(scene=args.scene, frames=args.frames, width=320, height=240, fx=FX)
    tum = out / "tum"
    if not (tum / "associations.txt").is_file():
        write_tum_sequence(SyntheticSequence(synth), tum)
    seq = SyntheticSequence(synth)
    _, poses = read_tum(tum / "groundtruth.txt")
    shots, offset = [], []
    for line, T in zip((tum / "associations.txt").read_text().splitlines(), poses):
        t, rgb, _, dep = line.split()
        z = cv2.imread(str(tum / dep), cv2.IMREAD_UNCHANGED).astype(np.float32) / np.float32(5000.0)
        rgb_img = cv2.cvtColor(cv2.imread(str(tum / rgb)), cv2.COLOR_BGR2RGB)
        shots.append((float(t), z, rgb_img, T))
        offset.append((float(t), z, seq.render_offset_color(T, T_OFFSET, K_COLOR), T))
    (out / "T_color_depth.txt").write_text("\n".join(" ".join(f"{x:.12g}" for x in r) for r in T_OFFSET) + "\n")
    extr = str(out / "T_color_depth.txt")
    rows = {
        "tum": ("TUM folder (ti-fusion synth)", lambda p: tum, []),
        "ros2-32": ("ROS 2 bag, 32FC1 + rgb8", lambda p: write_bag(p, shots, ros1_bag=False, depth="raw32", color="rgb8"),
                    ["--gt-topic", GT]),
        "ros2-cd16": ("ROS 2 bag, compressedDepth 16UC1 PNG + JPEG", lambda p: write_bag(
            p, shots, ros1_bag=False, depth="cd16", color="jpeg"), ["--gt-topic", GT]),
        "ros2-cd32": ("ROS 2 bag, compressedDepth 32FC1 (quantised) + JPEG", lambda p: write_bag(
            p, shots, ros1_bag=False, depth="cd32", color="jpeg"), ["--gt-topic", GT]),
        "ros1-16": ("ROS 1 bag, 16UC1 mm + rgb8", lambda p: write_bag(
            p.with_suffix(".bag"), shots, ros1_bag=True, depth="raw16", color="rgb8"), ["--gt-topic", GT]),
        "ros1-cd16": ("ROS 1 bag, compressedDepth 16UC1 + JPEG", lambda p: write_bag(
            p.with_suffix(".bag"), shots, ros1_bag=True, depth="cd16", color="jpeg"), ["--gt-topic", GT]),
        "offset": ("ROS 1 bag, 16UC1 mm, colour camera 2.5 cm aside + --color-extrinsics", lambda p: write_bag(
            p.with_suffix(".bag"), offset, ros1_bag=True, depth="raw16", color="rgb8", color_k=K_COLOR.as_tuple(),
            color_frame="camera_color_optical"), ["--gt-topic", GT, "--color-extrinsics", extr]),
        "offset-unregistered": ("the same, colour taken as registered (no extrinsics: wrong)", lambda p: write_bag(
            p.with_suffix(".bag"), offset, ros1_bag=True, depth="raw16", color="rgb8", color_k=K_COLOR.as_tuple()),
            ["--gt-topic", GT]),
        "realsense": ("ROS 1 bag in the RealSense SDK's layout (units, tf/0, colour aside)", lambda p: write_realsense_bag(
            p.with_suffix(".bag"), offset), ["--gt-topic", GT]),
    }
    only = [k for k in args.only.split(",") if k] or list(rows)
    lines = [f"scene {args.scene}, {args.frames} frames at 320x240, icp.color_weight {args.color_weight:g}", "",
             "| format | ATE (cm) | failures | colour used by tracking |", "|---|---|---|---|"]
    for key in only:
        title, make, options = rows[key]
        existing = [p for p in (out / key, (out / key).with_suffix(".bag")) if p.exists()]
        data = existing[0] if existing else make(out / key)  # written once per OUT folder
        run = out / f"run-{key}"
        code = cli(["slam", str(data), *options, "--out", str(run), "--overwrite", "--quiet",
                    "--set", f"icp.color_weight={args.color_weight}"])
        if code != 0:
            lines.append(f"| {title} | exit {code} | | |")
            continue
        s = json.loads((run / "summary.json").read_text())
        d = s["dataset"]
        used = "registered by the kernel" if d.get("color_camera") else ("yes" if d.get("color_for_tracking") else "no")
        lines.append(f"| {title} | {100 * s['ate_rmse_m']:.3f} | {s['tracking_failures']} | {used} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines)
    (out / f"table-{args.scene}-{args.color_weight:g}.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
