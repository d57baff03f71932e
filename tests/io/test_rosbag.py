"""MCAP files and ROS 2 bags as input: bags written here with rosbags' writer from the synthetic sequence
track as its TUM-format copy does; topics, encodings, stamps and damaged bags on small hand-made bags (no
Taichi); ti-fusion's own run log replays."""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config, DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.geometry import make_pose, rot_to_quat, so3_exp
from ti_fusion.io.datasets import detect, open_dataset
from ti_fusion.io.datasets.rosbag import RosbagDataset, depth_image
from ti_fusion.io.trajectory import read_tum
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.LATEST)
STORE1 = get_typestore(Stores.ROS1_NOETIC)
MSG = STORE.types
FRAMES = 20
K = (262.5, 262.5, 159.5, 119.5)  # the synthetic camera at 320×240
K_SMALL = (32.8125, 32.8125, 19.5, 14.5)  # the same field of view at the small bags' 40×30
DEPTH = "/camera/depth/image_rect_raw"
COLOR = "/camera/color/image_raw"
INFO = "/camera/depth/camera_info"
COLOR_INFO = "/camera/color/camera_info"
GT = "/ground_truth/pose"


# --------------------------------------------------------------------------------------------------
# Writing bags
# --------------------------------------------------------------------------------------------------
@dataclass
class Shot:
    """One frame to write: depth in metres (float32), RGB colour or None, header stamp, camera-to-world pose;
    ``numbers``, where given, are the pose's (tx, ty, tz, qx, qy, qz, qw) to write instead of ``pose``'s."""

    t: float
    depth: np.ndarray
    color: np.ndarray | None
    pose: np.ndarray
    numbers: tuple[float, ...] | None = None


def _time(t: float):
    ns = round(t * 1e9)
    return MSG["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(t: float, frame: str):
    return MSG["std_msgs/msg/Header"](stamp=_time(t), frame_id=frame)


def image_msg(t: float, array: np.ndarray, encoding: str, frame: str = "camera_optical"):
    a = np.ascontiguousarray(array)
    return MSG["sensor_msgs/msg/Image"](header=_header(t, frame), height=a.shape[0], width=a.shape[1],
                                         encoding=encoding, is_bigendian=0, step=a.strides[0],
                                         data=a.view(np.uint8).reshape(-1))


def info_msg(t: float, width: int, height: int, k=None, frame: str = "camera_optical"):
    """CameraInfo of ``k`` (fx, fy, cx, cy), by default the synthetic camera's field of view at this size."""
    fx, fy, cx, cy = k or (K[0] * width / 320, K[1] * width / 320, (width - 1) / 2, (height - 1) / 2)
    roi = MSG["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return MSG["sensor_msgs/msg/CameraInfo"](
        header=_header(t, frame), height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]), r=np.eye(3).reshape(-1),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0, roi=roi)


def pose_msg(t: float, T: np.ndarray, kind: str, numbers=None):
    q, p = (rot_to_quat(T[:3, :3]), T[:3, 3]) if numbers is None else (numbers[3:], numbers[:3])
    pose = MSG["geometry_msgs/msg/Pose"](position=MSG["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                         orientation=MSG["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    if kind == "pose":
        return MSG["geometry_msgs/msg/PoseStamped"](header=_header(t, "world"), pose=pose)
    cov = MSG["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    zero = MSG["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = MSG["geometry_msgs/msg/TwistWithCovariance"](twist=MSG["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                         covariance=np.zeros(36))
    return MSG["nav_msgs/msg/Odometry"](header=_header(t, "world"), child_frame_id="camera_optical", pose=cov,
                                        twist=twist)


def ros1_msg(msg):
    """The ROS 1 form of a message built here: the same fields (CameraInfo's d, k, r, p are D, K, R, P),
    and Header's seq."""
    cls = STORE1.types[msg.__msgtype__]
    values = {}
    for name in cls.__dataclass_fields__:
        if name == "__msgtype__":
            continue
        value = 0 if name == "seq" else getattr(msg, name, None)
        value = getattr(msg, name.lower()) if value is None else value
        values[name] = ros1_msg(value) if hasattr(value, "__msgtype__") else value
    return cls(**values)


def write_bag(path: Path, shots: list[Shot], depth_encoding: str = "32FC1", color_encoding: str | None = "rgb8",
              color_lag: float = 0.0, gt: str | None = "pose", info: bool = True, depth_topics=(DEPTH,),
              storage: str = "mcap", color_frame: str = "camera_optical", log_delays=None, ros1: bool = False,
              compressed_depth: bool = False, infos=None, stamps=None, color_k=None) -> Path:
    """A rosbag2 folder of ``shots`` (log time = header stamp, as a recorder close to the driver writes it,
    plus ``log_delays[i]`` seconds for shot i's depth), or a ROS 1 ``.bag`` file with ``ros1``.
    ``depth_encoding`` 16UC1 writes millimetres, ``compressed_depth`` as image_transport's compressedDepth
    PNG; ``color_encoding`` is rgb8, bgr8, mono8, "jpeg" or "png" (CompressedImage); ``color_lag`` delays
    colour's stamps; ``gt`` is "pose", "odom" or None; ``infos[i]`` is shot i's (fx, fy, cx, cy);
    ``stamps[i]`` overrides shot i's header stamps (log times stay the shot's); ``color_k`` (fx, fy, cx, cy)
    writes the colour camera's camera_info beside the colour topic."""
    from rosbags import rosbag1

    from ti_fusion.io.datasets.compressed import encode_compressed_depth

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    image_type, compressed_type = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
    depth_type = compressed_type if compressed_depth else image_type
    store = STORE1 if ros1 else STORE
    writer = rosbag1.Writer(path) if ros1 else Writer(path, version=9, storage_plugin=plugin)
    with writer as w:
        depth_conns = [w.add_connection(t, depth_type, typestore=store) for t in depth_topics]
        color_conn = None if color_encoding is None else w.add_connection(
            COLOR, compressed_type if color_encoding in ("jpeg", "png") else image_type, typestore=store)
        info_conn = w.add_connection(INFO, "sensor_msgs/msg/CameraInfo", typestore=store) if info else None
        color_info_conn = None if color_k is None else w.add_connection(COLOR_INFO, "sensor_msgs/msg/CameraInfo",
                                                                        typestore=store)
        gt_type = {"pose": "geometry_msgs/msg/PoseStamped", "odom": "nav_msgs/msg/Odometry"}.get(gt)
        gt_conn = w.add_connection(GT, gt_type, typestore=store) if gt else None
        records = []
        for i, s in enumerate(shots):
            h, wd = s.depth.shape
            t = s.t if stamps is None else stamps[i]
            depth = s.depth if depth_encoding == "32FC1" else np.round(s.depth * 1000).astype(np.uint16)
            logged = s.t + (log_delays[i] if log_delays else 0.0)
            if compressed_depth:
                msg = MSG[compressed_type](header=_header(t, "camera_optical"),
                                           format=f"{depth_encoding}; compressedDepth png",
                                           data=np.frombuffer(encode_compressed_depth(depth, depth_encoding), np.uint8))
            else:
                msg = image_msg(t, depth, depth_encoding)
            for conn in depth_conns:
                records.append((logged, conn, depth_type, msg))
            if info_conn:
                records.append((s.t, info_conn, "sensor_msgs/msg/CameraInfo",
                                info_msg(t, wd, h, None if infos is None else infos[i])))
            if color_info_conn is not None:
                records.append((s.t, color_info_conn, "sensor_msgs/msg/CameraInfo",
                                info_msg(t, s.color.shape[1], s.color.shape[0], color_k, color_frame)))
            if color_conn is not None and s.color is not None:
                tc = t + color_lag
                if color_encoding in ("jpeg", "png"):
                    ok, data = cv2.imencode("." + color_encoding.replace("jpeg", "jpg"), s.color[..., ::-1])
                    msg = MSG[compressed_type](header=_header(tc, color_frame),
                                               format=f"rgb8; {color_encoding} compressed bgr8", data=data.reshape(-1))
                    records.append((s.t + color_lag, color_conn, compressed_type, msg))
                else:
                    array = {"rgb8": s.color, "bgr8": s.color[..., ::-1],
                             "mono8": cv2.cvtColor(s.color, cv2.COLOR_RGB2GRAY)}[color_encoding]
                    records.append((s.t + color_lag, color_conn, image_type,
                                    image_msg(tc, array, color_encoding, color_frame)))
            if gt_conn:
                records.append((s.t, gt_conn, gt_type, pose_msg(t, s.pose, gt, s.numbers)))
        for t, conn, msgtype, msg in sorted(records, key=lambda r: r[0]):
            data = STORE1.serialize_ros1(ros1_msg(msg), msgtype) if ros1 else STORE.serialize_cdr(msg, msgtype)
            w.write(conn, round(t * 1e9), data)
    return path


def small_shots(rng, n: int = 4, t0: float = 1700000000.0, size=(40, 30)) -> list[Shot]:
    """``n`` frames of ``size`` (40×30) at 30 Hz with random depth and colour."""
    shots = []
    for i in range(n):
        depth = rng.uniform(0.5, 3.0, size[::-1]).astype(np.float32)
        color = rng.integers(0, 256, (*size[::-1], 3), dtype=np.uint8)
        shots.append(Shot(t0 + i / 30.0, depth, color, make_pose(so3_exp(np.array([0, 0.01 * i, 0])), [0.01 * i, 0, 0])))
    return shots


def small_cfg(path: Path, **kw) -> DatasetConfig:
    return DatasetConfig(path=str(path), **kw)


# --------------------------------------------------------------------------------------------------
# The synthetic sequence as bags: the same trajectory as from its TUM copy
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory):
    from ti_fusion.backend import init_backend
    from ti_fusion.cli.synth import write_tum_sequence
    from ti_fusion.synthetic.scene import SyntheticSequence

    init_backend("cpu")
    root = tmp_path_factory.mktemp("synthetic") / "tum"
    write_tum_sequence(SyntheticSequence(SynthConfig(frames=FRAMES, width=320, height=240, fx=K[0])), root)
    return root


@pytest.fixture(scope="module")
def synthetic_shots(tum_sequence) -> list[Shot]:
    """The TUM copy's frames as written: depth read as the TUM loader reads it (5000 units per metre), and the
    ground truth file's numbers as they are (a pose's quaternion made again from its matrix is ulps off them)."""
    stamps, poses = read_tum(tum_sequence / "groundtruth.txt")
    rows = [tuple(float(x) for x in line.split()[1:]) for line in
            (tum_sequence / "groundtruth.txt").read_text().splitlines() if line and not line.startswith("#")]
    assert len(rows) == len(poses)
    shots = []
    for line, T, numbers in zip((tum_sequence / "associations.txt").read_text().splitlines(), poses, rows):
        t, rgb, _, depth = line.split()
        raw = cv2.imread(str(tum_sequence / depth), cv2.IMREAD_UNCHANGED)
        color = cv2.cvtColor(cv2.imread(str(tum_sequence / rgb)), cv2.COLOR_BGR2RGB)
        shots.append(Shot(float(t), raw.astype(np.float32) / np.float32(5000.0), color, T, numbers))
    return shots


def slam(dataset_cfg: DatasetConfig, out: Path, cfg: Config | None = None) -> dict:
    from ti_fusion.backend import current_backend
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    cfg = cfg or Config()
    cfg.dataset = dataset_cfg
    cfg.log.progress = False
    summary = SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, RunDir("slam", out), current_backend(),
                           show_progress=False).run()
    summary["trajectory"] = read_tum(out / "trajectory.tum")
    return summary


@pytest.fixture(scope="module")
def tum_run(tum_sequence, tmp_path_factory):
    return slam(DatasetConfig(path=str(tum_sequence)), tmp_path_factory.mktemp("runs") / "tum")


@pytest.mark.slow
def test_a_32fc1_bag_gives_the_tum_runs_trajectory(cpu, synthetic_shots, tum_run, tmp_path):
    """Depth in metres as 32FC1 (the TUM loader's float32 values), intrinsics from CameraInfo, ground truth
    from a PoseStamped topic: the same trajectory, with the header stamps as its times."""
    bag = write_bag(tmp_path / "bag", synthetic_shots, depth_encoding="32FC1")
    run = slam(small_cfg(bag, gt_topic=GT), tmp_path / "run")
    d = run["dataset"]
    assert d["format"] == "rosbag" and d["frames"] == FRAMES and d["depth_encoding"] == "32FC1"
    assert d["topics"] == {"depth": DEPTH, "color": COLOR, "camera_info": INFO, "ground_truth": GT}
    assert d["intrinsics"]["source"] == f"{INFO} (CameraInfo K)" and d["color_registered"] is True
    stamps, poses = run["trajectory"]
    tum_stamps, tum_poses = tum_run["trajectory"]
    np.testing.assert_array_equal(stamps, tum_stamps)
    # the same frames, stamps (header stamps read back as the TUM text's floats) and code in this process: the same
    # poses, bit for bit (a tolerance would be a guess: tracking's iterations turn any input difference into an
    # output difference of no bounded size)
    np.testing.assert_array_equal(poses, tum_poses)
    assert run["ate_rmse_m"] == tum_run["ate_rmse_m"]


@pytest.mark.slow
def test_a_16uc1_mcap_file_with_lagging_bgr_color_from_the_command_line(cpu, synthetic_shots, tum_run, tmp_path):
    """Millimetres (REP 118), a bare .mcap file, colour 8 ms behind depth, ground truth from Odometry."""
    bag = write_bag(tmp_path / "bag", synthetic_shots, depth_encoding="16UC1", color_encoding="bgr8",
                    color_lag=0.008, gt="odom")
    mcap = shutil.move(next(bag.glob("*.mcap")), tmp_path / "recording.mcap")
    out = tmp_path / "run"
    assert main(["slam", str(mcap), "--gt-topic", GT, "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    d = summary["dataset"]
    assert d["format_from"] == "detected from a .mcap file" and d["depth_scale"] == 1000
    assert d["notes"] == [] and d["color"] is True  # every depth frame found its colour
    assert summary["tracking_failures"] == 0
    assert summary["ate_rmse_m"] < 0.01 and abs(summary["ate_rmse_m"] - tum_run["ate_rmse_m"]) < 1e-3
    stamps, _ = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(stamps, [s.t for s in synthetic_shots], atol=1e-6)


# --------------------------------------------------------------------------------------------------
# Small bags: topics, encodings, stamps, damage
# --------------------------------------------------------------------------------------------------
def test_frames_color_intrinsics_and_ground_truth(tmp_path, rng):
    shots = small_shots(rng)
    ds = open_dataset(small_cfg(write_bag(tmp_path / "bag", shots, gt="pose"), gt_topic=GT))
    assert isinstance(ds, RosbagDataset) and len(ds) == 4 and ds.intrinsics.as_tuple() == K_SMALL
    for i, s in enumerate(shots):
        frame = ds[i]
        assert frame.timestamp == pytest.approx(s.t, abs=1e-6)
        np.testing.assert_array_equal(frame.depth, np.where(s.depth > 4.0, 0, s.depth))
        np.testing.assert_array_equal(frame.color, s.color)
        np.testing.assert_allclose(frame.gt_pose, s.pose, atol=1e-9)


@pytest.mark.parametrize("encoding", ["bgr8", "mono8", "jpeg"])
def test_color_encodings_come_out_rgb(tmp_path, rng, encoding):
    shots = small_shots(rng, n=2)
    ds = open_dataset(small_cfg(write_bag(tmp_path / "bag", shots, color_encoding=encoding)))
    color = ds[1].color
    assert color.shape == (30, 40, 3) and color.dtype == np.uint8
    if encoding == "bgr8":
        np.testing.assert_array_equal(color, shots[1].color)
    elif encoding == "mono8":
        np.testing.assert_array_equal(color[..., 0], cv2.cvtColor(shots[1].color, cv2.COLOR_RGB2GRAY))
    else:  # JPEG is lossy; random noise is its worst case
        assert np.abs(color.astype(int) - shots[1].color).mean() < 60


def test_frames_in_header_stamp_order_and_a_repeated_stamp_left_out(tmp_path, rng):
    shots = small_shots(rng, n=4)
    shots[3].t = shots[2].t  # a driver that stamped two images alike
    # frame 1's image recorded after frame 2's
    bag = write_bag(tmp_path / "bag", shots, color_encoding=None, gt=None, log_delays=[0, 0.05, 0, 0])
    ds = open_dataset(small_cfg(bag))
    assert len(ds) == 3 and ds.dropped_frames == 1
    assert [f.timestamp for f in ds] == sorted(f.timestamp for f in ds)
    notes = " ".join(ds.describe()["notes"])
    assert "not in header-stamp order" in notes and "1 depth messages repeat the header stamp" in notes


def test_16uc1_is_millimetres_unless_the_depth_scale_says_otherwise(tmp_path, rng):
    shots = small_shots(rng, n=2)
    bag = write_bag(tmp_path / "bag", shots, depth_encoding="16UC1")
    ds = open_dataset(small_cfg(bag))
    expected = np.round(shots[0].depth * 1000) / 1000
    np.testing.assert_allclose(ds[0].depth, np.where(expected > 4, 0, expected), rtol=1e-6)
    assert ds.describe()["depth_scale_from"] == "REP 118 for 16UC1"
    ds = open_dataset(small_cfg(bag, depth_scale=500.0, depth_max=0))
    np.testing.assert_allclose(ds[0].depth, expected * 2, rtol=1e-6)


def test_32fc1_nan_and_inf_are_no_depth():
    msg = image_msg(0.0, np.array([[1.5, np.nan], [np.inf, -np.inf]], dtype=np.float32), "32FC1")
    np.testing.assert_array_equal(depth_image(msg, 1.0, 4.0, "test"), [[1.5, 0], [0, 0]])


def test_rows_with_padding_and_big_endian_depth():
    raw = np.array([[1000, 2000, 3000], [4000, 5000, 6000]], dtype=">u2")
    padded = np.zeros((2, 8), dtype=np.uint8)
    padded[:, :6] = raw.view(np.uint8).reshape(2, 6)
    msg = MSG["sensor_msgs/msg/Image"](header=_header(0.0, "c"), height=2, width=3, encoding="16UC1", is_bigendian=1,
                                       step=8, data=padded.reshape(-1))
    np.testing.assert_allclose(depth_image(msg, 1000.0, 0, "test"), raw.astype(np.float32) / 1000)


def test_two_depth_topics_are_listed_with_the_option(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), depth_topics=(DEPTH, "/other/depth"))
    with pytest.raises(InputError) as info:
        open_dataset(small_cfg(bag))
    message = str(info.value)
    assert "\n" not in message
    assert f"depth: {DEPTH}, /other/depth (--depth-topic TOPIC)" in message
    ds = open_dataset(small_cfg(bag, depth_topic="/other/depth"))
    assert ds.topics["depth"] == "/other/depth" and len(ds) == 2
    with pytest.raises(InputError, match="--depth-topic /nothing: no such topic"):
        open_dataset(small_cfg(bag, depth_topic="/nothing"))
    with pytest.raises(InputError, match=f"--depth-topic {COLOR}: a sensor_msgs/msg/Image topic in rgb8, not a depth"):
        open_dataset(small_cfg(bag, depth_topic=COLOR))


def test_the_command_line_lists_the_candidates_in_one_line(tmp_path, rng, capsys):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), depth_topics=(DEPTH, "/other/depth"))
    assert main(["slam", str(bag), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--depth-topic TOPIC" in err and "/other/depth" in err


def test_color_outside_the_window_is_left_out_and_counted(tmp_path, rng, caplog):
    shots = small_shots(rng, n=4)
    bag = write_bag(tmp_path / "bag", shots, color_lag=0.015)
    ds = open_dataset(small_cfg(bag))  # 15 ms: within the 20 ms window
    assert all(ds[i].color is not None for i in range(4)) and ds.describe()["notes"] == []
    ds = open_dataset(small_cfg(bag, max_time_difference=0.01))
    assert all(ds[i].color is None for i in range(4)) and len(ds) == 4
    assert "4 of 4 depth images have no colour image within 0.01 s" in ds.describe()["notes"][0]
    ds = open_dataset(small_cfg(bag, color_topic="none"))
    assert ds[0].color is None and ds.topics["color"] is None


def test_color_in_another_frame_is_not_registered(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), color_frame="camera_color_optical")
    d = open_dataset(small_cfg(bag)).describe()
    assert d["color_registered"] is False and "not registered" in d["notes"][0]


def test_intrinsics_without_camera_info(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), info=False)
    with pytest.raises(InputError, match="no sensor_msgs/msg/CameraInfo topic to give the intrinsics: pass --intrinsics"):
        open_dataset(small_cfg(bag))
    ds = open_dataset(small_cfg(bag, intrinsics="30,30,19.5,14.5"))
    assert ds.intrinsics.as_tuple() == (30.0, 30.0, 19.5, 14.5)


def test_ground_truth_from_a_tum_file(tmp_path, rng):
    shots = small_shots(rng, n=3)
    bag = write_bag(tmp_path / "bag", shots, gt=None)
    lines = [f"{s.t:.6f} {s.pose[0, 3]} 0 0 0 0 0 1\n" for s in shots]
    (tmp_path / "gt.txt").write_text("".join(lines))
    ds = open_dataset(small_cfg(bag, ground_truth=str(tmp_path / "gt.txt")))
    assert ds[2].gt_pose[0, 3] == pytest.approx(shots[2].pose[0, 3])
    (bag / "groundtruth.txt").write_text("".join(lines))  # beside the bag's files: found
    assert open_dataset(small_cfg(bag)).describe()["ground_truth_frames"] == 3


def test_an_odometry_topic_is_ground_truth_only_when_named(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), gt="odom")
    assert open_dataset(small_cfg(bag)).has_ground_truth is False
    assert open_dataset(small_cfg(bag, gt_topic=GT)).has_ground_truth is True
    with pytest.raises(InputError, match=f"--gt-topic {INFO}: a sensor_msgs/msg/CameraInfo topic, not a ground truth"):
        open_dataset(small_cfg(bag, gt_topic=INFO))


def test_a_cut_off_recording_is_read_up_to_the_cut(tmp_path, rng):
    # rosbags writes chunks of 1 MiB: frames of 320×240 fill one every two frames
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=8, size=(320, 240)), info=False)
    whole = next(bag.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    ds = open_dataset(small_cfg(cut, intrinsics="262.5,262.5,159.5,119.5"))
    assert ds.describe()["truncated"] is True and 0 < len(ds) < 8
    assert "ends without MCAP's footer" in ds.describe()["notes"][0]
    full = open_dataset(small_cfg(bag, intrinsics="262.5,262.5,159.5,119.5"))
    for i in range(len(ds)):  # what is there is read as it was written
        np.testing.assert_array_equal(ds[i].depth, full[i].depth)
        np.testing.assert_array_equal(ds[i].color, full[i].color)
    cut.write_bytes(data[:20])  # nothing past the header
    with pytest.raises(InputError, match="cannot read the bag"):
        open_dataset(small_cfg(cut))


def test_a_rosbag2_folder_without_metadata_reads_its_mcap_file(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2))
    (bag / "metadata.yaml").unlink()
    assert detect(bag)[0] == "rosbag"
    ds = open_dataset(small_cfg(bag))
    assert len(ds) == 2 and "no metadata.yaml" in ds.describe()["notes"][0]


def test_sqlite3_storage(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=3), storage="sqlite3")
    assert detect(bag) == ("rosbag", "metadata.yaml (rosbag2)")
    assert len(open_dataset(small_cfg(bag))) == 3


def test_what_is_not_a_bag_is_one_line(tmp_path):
    from ti_fusion.io.mcap_log import RunLogger

    with RunLogger(tmp_path / "log.mcap") as log:  # an MCAP of Foxglove messages without depth images
        log.log_stats(1.0, {"frame": 0})
    with pytest.raises(InputError, match="not a folder, nor a ROS bag file"):
        open_dataset(small_cfg(tmp_path / "log.mcap"))
    with pytest.raises(InputError, match="not a ROS 2 bag .*--format log"):
        open_dataset(small_cfg(tmp_path / "log.mcap", format="rosbag"))
    with pytest.raises(InputError, match="no /camera/depth images in the log"):
        open_dataset(small_cfg(tmp_path / "log.mcap", format="log"))
    (tmp_path / "notes.txt").write_text("hello\n")
    with pytest.raises(InputError, match="not a folder, nor a ROS bag file"):
        open_dataset(small_cfg(tmp_path / "notes.txt"))
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(InputError, match="cannot read the bag"):
        open_dataset(small_cfg(tmp_path / "empty.mcap"))


@pytest.mark.slow
def test_a_run_log_with_every_depth_image_replays(cpu, tmp_path):
    """ti-fusion's own log.mcap (log.depth_every = 1) replays as a sequence: the run's frames, times,
    intrinsics and ground truth; depth in whole millimetres, so the same accuracy within a millimetre."""
    cfg = Config()
    cfg.synth.width, cfg.synth.height, cfg.synth.fx, cfg.synth.frames = 320, 240, 262.5, 12
    cfg.log.depth_every, cfg.log.progress = 1, False
    run = slam(cfg.dataset, tmp_path / "run", cfg)
    assert detect(tmp_path / "run") == ("log", "log.mcap (a ti-fusion run log)")
    assert detect(tmp_path / "run" / "log.mcap")[0] == "log"
    replay = slam(small_cfg(tmp_path / "run"), tmp_path / "replay")
    d = replay["dataset"]
    assert d["format"] == "log" and d["frames"] == 12 and d["ground_truth_frames"] == 12 and d["color"]
    assert d["intrinsics"]["source"] == "/camera/calibration in the log"
    np.testing.assert_allclose(replay["trajectory"][0], run["trajectory"][0], atol=1e-6)
    assert replay["tracking_failures"] == 0 and abs(replay["ate_rmse_m"] - run["ate_rmse_m"]) < 1e-3


def test_a_run_log_with_some_depth_images_says_so(cpu, tmp_path):
    from ti_fusion.io.mcap_log import RunLogger

    K_ = Intrinsics(*K_SMALL, width=40, height=30)
    with RunLogger(tmp_path / "log.mcap", {"dataset": {"frames": 9}}) as log:
        log.log_calibration(1.0, K_)
        for i in range(3):  # every third frame of nine
            log.log_depth(1.0 + i / 10, np.full((30, 40), 1.0 + i, dtype=np.float32))
    ds = open_dataset(small_cfg(tmp_path / "log.mcap"))
    assert len(ds) == 3 and ds[2].depth[0, 0] == 3.0 and ds[2].timestamp == pytest.approx(1.2)
    assert "the run had 9 frames and logged the depth of 3" in ds.describe()["notes"][0]


def _log_of_three(path: Path, finalised: bool = True) -> Path:
    from ti_fusion.io.mcap_log import RunLogger

    with RunLogger(path, chunk_size=1) as log:  # a chunk per message
        log.log_calibration(1.0, Intrinsics(*K_SMALL, width=40, height=30))
        for i in range(4):
            log.log_depth(1.0 + i / 10, np.full((30, 40), 1.0 + i, dtype=np.float32))
            log.log_image(1.0 + i / 10, np.full((30, 40, 3), 40 * i, dtype=np.uint8), fmt="png")
    if not finalised:  # as a killed run leaves it: the first chunks, no summary
        data = path.read_bytes()
        path.write_bytes(data[: len(data) * 6 // 10])
    return path


@pytest.mark.parametrize("kind", ["ros2", "ros1", "sqlite3", "cut mcap", "log", "unfinalised log"])
def test_bags_and_logs_read_in_a_reader_process_as_in_place(tmp_path, rng, kind):
    """The bag or log pickled to a reader process (``ti_fusion.io.prefetch``) opens itself again there and
    hands out the frames read in place, in order, with no process left behind."""
    from ti_fusion.io.prefetch import Prefetcher, read_mode

    if kind in ("log", "unfinalised log"):
        path = _log_of_three(tmp_path / "log.mcap", finalised=kind == "log")
    else:
        bag = write_bag(tmp_path / ("bag.bag" if kind == "ros1" else "bag"),
                        small_shots(rng, n=8, size=(320, 240) if kind == "cut mcap" else (40, 30)),
                        ros1=kind == "ros1", storage="sqlite3" if kind == "sqlite3" else "mcap")
        path = bag
        if kind == "cut mcap":
            data = next(bag.glob("*.mcap")).read_bytes()
            path = tmp_path / "cut.mcap"
            path.write_bytes(data[: len(data) // 2])
    ds = open_dataset(small_cfg(path, intrinsics="262.5,262.5,159.5,119.5" if kind == "cut mcap" else ""))
    assert read_mode(ds) == "processes" and len(ds) >= 2
    with Prefetcher.for_dataset(ds) as frames:
        got = list(frames)
    assert [i for i, _, _ in got] == list(range(len(ds)))
    for i, frame, _ in got:
        want = ds[i]
        assert frame.timestamp == want.timestamp
        np.testing.assert_array_equal(frame.depth, want.depth)
        np.testing.assert_array_equal(frame.color, want.color)


def test_selection_and_downsampling_apply(tmp_path, rng):
    bag = write_bag(tmp_path / "bag", small_shots(rng, n=6))
    ds = open_dataset(small_cfg(bag, start=1, stride=2, downsample=2))
    assert len(ds) == 3 and ds[0].depth.shape == (15, 20) and ds[0].color.shape == (15, 20, 3)
    assert ds.intrinsics.fx == K_SMALL[0] / 2


# --------------------------------------------------------------------------------------------------
# ROS 1 bags, compressed topics, RealSense recordings
# --------------------------------------------------------------------------------------------------
REALSENSE_BAG = Path(__file__).resolve().parents[3] / "shared/data/realsense-d435-2frames/single_depth_color_640x480.bag"


@pytest.mark.slow
@pytest.mark.parametrize("compressed", [False, True])
def test_the_synthetic_sequence_as_a_ros1_bag_tracks_as_its_tum_copy(cpu, synthetic_shots, tum_run, tmp_path,
                                                                    compressed):
    """Millimetres in a ROS 1 .bag (raw 16UC1, or compressedDepth PNG with JPEG colour): the TUM run's
    trajectory within the millimetre quantisation (TUM's PNGs hold fifths of a millimetre)."""
    bag = write_bag(tmp_path / "seq.bag", synthetic_shots, depth_encoding="16UC1", ros1=True,
                    compressed_depth=compressed, color_encoding="jpeg" if compressed else "rgb8",
                    depth_topics=(DEPTH + "/compressedDepth",) if compressed else (DEPTH,))
    out = tmp_path / "run"
    assert main(["slam", str(bag), "--gt-topic", GT, "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    d = summary["dataset"]
    assert d["format_from"] == "detected from a .bag file (ROS 1)" and d["depth_scale"] == 1000
    assert d["topics"]["camera_info"] == INFO and d["notes"] == [] and summary["tracking_failures"] == 0
    assert abs(summary["ate_rmse_m"] - tum_run["ate_rmse_m"]) < 1e-3


# the colour camera of the offset-colour bags: 2.5 cm beside the depth camera, turned about 1.3 degrees
T_OFFSET = make_pose(so3_exp(np.array([0.01, -0.02, 0.01])), [0.025, 0.003, -0.002])
K_COLOR = Intrinsics(fx=300.0, fy=301.0, cx=165.0, cy=118.0, width=320, height=240)


def offset_color_shots(shots: list[Shot], scene: str = "room") -> list[Shot]:
    """``shots`` with their colour rendered by a camera at T_OFFSET from the depth camera, K_COLOR."""
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig(scene=scene, frames=len(shots), width=320, height=240, fx=K[0]))
    return [Shot(s.t, s.depth, seq.render_offset_color(s.pose, T_OFFSET, K_COLOR), s.pose) for s in shots]


@pytest.mark.slow
def test_unregistered_color_with_its_extrinsics_tracks_as_registered_color(cpu, synthetic_shots, tum_sequence,
                                                                              tmp_path):
    """The synthetic sequence as a ROS 1 bag, millimetres, its colour from a camera 2.5 cm aside (its own
    camera_info, --color-extrinsics a file): registered to depth in the loop, the photometric term (on by
    default) uses it and the run tracks as the TUM folder with registered colour does (within the millimetre
    quantisation). Depth alone would track the same whatever the colour: not a test of the registration."""
    cfg = Config()
    tum = slam(DatasetConfig(path=str(tum_sequence)), tmp_path / "tum", copy.deepcopy(cfg))
    bag = write_bag(tmp_path / "seq.bag", offset_color_shots(synthetic_shots), depth_encoding="16UC1", ros1=True,
                    color_frame="camera_color_optical", color_k=K_COLOR.as_tuple())
    T = T_OFFSET
    (tmp_path / "extrinsics.txt").write_text("\n".join(" ".join(f"{x:.12g}" for x in row) for row in T) + "\n")
    run = slam(small_cfg(bag, gt_topic=GT, color_extrinsics=str(tmp_path / "extrinsics.txt")), tmp_path / "run", cfg)
    d = run["dataset"]
    assert d["notes"] == [] and d["color_camera"]["source"].endswith("(--color-extrinsics)")
    assert run["tracking_failures"] == 0 and abs(run["ate_rmse_m"] - tum["ate_rmse_m"]) < 1e-3


@pytest.mark.slow
def test_compressed_depth_on_ros2_tracks_as_the_raw_images(cpu, synthetic_shots, tmp_path):
    """compressedDepth 16UC1 is lossless: the same trajectory as the raw 16UC1 images, JPEG colour and all
    (depth-only tracking: JPEG's lossy colour would move the photometric term's result)."""
    depth_only = Config()
    depth_only.icp.color_weight = 0.0
    raw = slam(small_cfg(write_bag(tmp_path / "raw", synthetic_shots, depth_encoding="16UC1"), gt_topic=GT),
               tmp_path / "raw_run", copy.deepcopy(depth_only))
    bag = write_bag(tmp_path / "png", synthetic_shots, depth_encoding="16UC1", compressed_depth=True,
                    color_encoding="jpeg", depth_topics=(DEPTH + "/compressedDepth",))
    run = slam(small_cfg(bag, gt_topic=GT), tmp_path / "png_run", depth_only)
    assert run["dataset"]["depth_encoding"] == "16UC1"
    np.testing.assert_allclose(run["trajectory"][1], raw["trajectory"][1], atol=1e-6)
    assert run["ate_rmse_m"] == pytest.approx(raw["ate_rmse_m"], abs=1e-6)


@pytest.mark.parametrize("ros1", [False, True])
def test_compressed_depth_and_color_decode(tmp_path, rng, ros1):
    """compressedDepth 16UC1 is the raw millimetres; 32FC1 is within its quantisation of inverse depth
    (z² / (A) with A = 100·101: 0.9 mm at 3 m); PNG colour is exact."""
    shots = small_shots(rng, n=2)
    path = tmp_path / ("b.bag" if ros1 else "b")
    ds = open_dataset(small_cfg(write_bag(path, shots, depth_encoding="16UC1", compressed_depth=True,
                                          color_encoding="png", depth_topics=(DEPTH + "/compressedDepth",),
                                          ros1=ros1)))
    assert ds.topics["depth"] == DEPTH + "/compressedDepth" and ds.topics["camera_info"] == INFO
    expected = np.round(shots[1].depth * 1000) / 1000
    np.testing.assert_allclose(ds[1].depth, np.where(expected > 4, 0, expected), rtol=1e-6)
    np.testing.assert_array_equal(ds[1].color, shots[1].color)
    path = tmp_path / ("f.bag" if ros1 else "f")
    ds = open_dataset(small_cfg(write_bag(path, shots, depth_encoding="32FC1", compressed_depth=True,
                                          depth_topics=(DEPTH + "/compressedDepth",), ros1=ros1)))
    z = shots[1].depth
    assert ds.encoding == "32FC1" and np.all(np.abs(ds[1].depth - np.where(z > 4, 0, z)) <= z**2 / 10100 + 1e-6)


def test_compressed_depth_that_cannot_be_read_is_one_line(tmp_path, rng):
    from ti_fusion.io.datasets.compressed import decode_compressed_depth, encode_compressed_depth

    with pytest.raises(InputError, match="RVL.*not supported"):
        decode_compressed_depth("16UC1; compressedDepth rvl", np.zeros(20, np.uint8), "t")
    with pytest.raises(InputError, match="holds no PNG image"):
        decode_compressed_depth("16UC1; compressedDepth png", np.zeros(20, np.uint8), "t")
    data = encode_compressed_depth(np.full((3, 4), np.nan, np.float32), "32FC1")
    depth, encoding = decode_compressed_depth("32FC1; compressedDepth png", np.frombuffer(data, np.uint8), "t")
    assert encoding == "32FC1" and np.all(np.isnan(depth))
    bag = write_bag(tmp_path / "b", small_shots(rng, n=2), compressed_depth=True, depth_topics=("/d/compressedDepth",))
    with pytest.raises(InputError, match="--color-topic /d/compressedDepth: a sensor_msgs/msg/CompressedImage topic "
                                         "in format '32FC1; compressedDepth png', not a colour topic"):
        open_dataset(small_cfg(bag, color_topic="/d/compressedDepth"))


def write_realsense_bag(path: Path, shots: list[Shot], units: float = 0.0001, T_color_depth=None,
                        color_k=(30.0, 30.0, 20.0, 15.0)) -> Path:
    """A ROS 1 bag laid out as librealsense records one: the SDK's topics, mono16 depth in ``units`` metres
    per unit, rgb8 colour, both with frame_id "0", and each stream's extrinsics from depth as its tf/0."""
    from rosbags import rosbag1

    dev = "/device_0"
    d, c = f"{dev}/sensor_0/Depth_0", f"{dev}/sensor_1/Color_0"
    T = np.eye(4) if T_color_depth is None else T_color_depth

    def transform(M):
        q, p = rot_to_quat(M[:3, :3]), M[:3, 3]
        return MSG["geometry_msgs/msg/Transform"](translation=MSG["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                                                  rotation=MSG["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2],
                                                                                               w=q[3]))
    h, w = shots[0].depth.shape
    with rosbag1.Writer(path) as bag:
        def put(topic, msgtype, msg, t):
            conn = conns.get(topic) or conns.setdefault(topic, bag.add_connection(topic, msgtype, typestore=STORE1))
            bag.write(conn, round(t * 1e9), STORE1.serialize_ros1(ros1_msg(msg), msgtype))

        conns = {}
        t0 = shots[0].t
        put(f"{d}/info/camera_info", "sensor_msgs/msg/CameraInfo", info_msg(0.0, w, h), t0)
        put(f"{c}/info/camera_info", "sensor_msgs/msg/CameraInfo", info_msg(0.0, w, h, color_k), t0)
        put(f"{dev}/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", MSG["std_msgs/msg/Float32"](data=units), t0)
        put(f"{d}/tf/0", "geometry_msgs/msg/Transform", transform(np.eye(4)), t0)
        put(f"{c}/tf/0", "geometry_msgs/msg/Transform", transform(T), t0)
        for s in shots:
            put(f"{d}/image/data", "sensor_msgs/msg/Image",
                image_msg(s.t, np.round(s.depth / units).astype(np.uint16), "mono16", "0"), s.t)
            put(f"{c}/image/data", "sensor_msgs/msg/Image", image_msg(s.t, s.color, "rgb8", "0"), s.t)
    return path


def test_a_realsense_recording_takes_its_units_intrinsics_and_extrinsics(tmp_path, rng):
    """The SDK's topic names: depth units from the recorded option (0.1 mm here, not REP 118's mm), the
    depth stream's camera_info among two, the colour camera and the depth-to-colour extrinsics from tf/0;
    frame_id "0" on both does not make the colour registered."""
    shots = small_shots(rng, n=3)
    T = make_pose(so3_exp(np.array([0.0, 0.02, 0.01])), [0.015, 0.001, 0.0])
    ds = open_dataset(small_cfg(write_realsense_bag(tmp_path / "rs.bag", shots, T_color_depth=T)))
    d = ds.describe()
    assert d["realsense"] is True and d["depth_scale"] == 10000 and "Depth Units/value (0.0001 m per unit" in \
        d["depth_scale_from"]
    assert d["topics"]["camera_info"] == "/device_0/sensor_0/Depth_0/info/camera_info"
    assert d["color_registered"] is False and d["color_for_tracking"] is False
    np.testing.assert_allclose(ds.color_extrinsics, T, atol=1e-6)
    assert ds.color_intrinsics.as_tuple() == (30.0, 30.0, 20.0, 15.0)
    expected = np.round(shots[2].depth / 0.0001).astype(np.uint16) / 10000  # as written
    np.testing.assert_allclose(ds[2].depth, np.where(expected > 4, 0, expected), rtol=1e-6)
    assert "colour camera fx 30" in ds.describe_format() and "translation (0.0150, 0.0010, 0.0000)" in \
        ds.describe_format()


@pytest.mark.skipif(not REALSENSE_BAG.is_file(), reason=f"the shared RealSense recording is absent ({REALSENSE_BAG})")
def test_the_shared_realsense_d435_recording():
    """What pyrealsense2's playback reports for this file: z16 in 0.001 m units, the depth camera fx 390.431,
    depth-to-colour translation (0.01431, 0.00060, 0.00061) m."""
    ds = open_dataset(small_cfg(REALSENSE_BAG))
    d = ds.describe()
    assert d["format_from"] == "detected from a .bag file (ROS 1)" and d["frames"] == 2 and d["depth_scale"] == 1000
    assert d["intrinsics"]["fx"] == pytest.approx(390.431, abs=1e-3) and d["depth_encoding"] == "mono16"
    np.testing.assert_allclose(ds.color_extrinsics[:3, 3], [0.014311, 0.000602, 0.000611], atol=1e-6)
    assert ds.color_intrinsics.fx == pytest.approx(613.204, abs=1e-3)
    depth = ds[0].depth
    assert depth.shape == (480, 640) and 0.3 < np.median(depth[depth > 0]) < 3.5 and (depth > 0).mean() > 0.9


# --------------------------------------------------------------------------------------------------
# Bags that are not what they seem: a calibration that changes, stamps that cannot order the frames, colour of
# another size
# --------------------------------------------------------------------------------------------------
def test_a_camera_info_that_changes_mid_recording_is_refused_unless_the_selection_avoids_it(tmp_path, rng):
    shots = small_shots(rng, n=5)
    infos = [(32.8125, 32.8125, 19.5, 14.5)] * 3 + [(50.0, 50.0, 19.5, 14.5)] * 2
    bag = write_bag(tmp_path / "b", shots, infos=infos)
    with pytest.raises(InputError) as info:
        open_dataset(small_cfg(bag))
    message = str(info.value)
    assert "\n" not in message and "changes during the recording: fx 32.8125" in message
    assert "fx 50 fy 50 cx 19.5 cy 14.5 from frame 3" in message and "--stop 3" in message and "--start 3" in message
    assert open_dataset(small_cfg(bag, stop=3)).intrinsics.fx == 32.8125
    assert open_dataset(small_cfg(bag, start=3)).intrinsics.fx == 50.0
    assert open_dataset(small_cfg(bag, intrinsics="40,40,19.5,14.5")).intrinsics.fx == 40.0


def test_all_zero_header_stamps_fall_back_to_the_receive_times(tmp_path, rng):
    shots = small_shots(rng, n=6)
    bag = write_bag(tmp_path / "b", shots, stamps=[0.0] * 6, gt=None)
    ds = open_dataset(small_cfg(bag))
    assert len(ds) == 6 and ds.dropped_frames == 0
    assert [f.timestamp for f in ds] == pytest.approx([s.t for s in shots], abs=1e-6)
    assert all(f.color is not None for f in ds)  # colour paired by receive time too
    assert "header stamps of /camera/depth/image_rect_raw are all zero: the bag's receive times" in ds.notes[0]
    assert ds.describe()["times_from"].startswith("receive times")


def test_color_of_another_size_in_the_depths_frame_is_resized_with_a_warning(tmp_path, rng, capsys):
    shots = small_shots(rng, n=3)
    for s in shots:
        s.color = cv2.resize(s.color, (80, 60))
    bag = write_bag(tmp_path / "b", shots)
    ds = open_dataset(small_cfg(bag))
    assert ds.describe()["color_registered"] is False and ds[0].color.shape == (30, 40, 3)
    assert "are 80x60 in the depth's frame (camera_optical) and the depth images 40x30" in ds.notes[0]
    assert "--color-topic none" in ds.notes[0]
    shots[2].color = shots[2].color[:50]  # one colour image of yet another size: refused, with the way out
    bag = write_bag(tmp_path / "c", shots)
    with pytest.raises(InputError, match="colour image of frame 2 is 80x50, the first 80x60 .--color-topic none"):
        open_dataset(small_cfg(bag))[2]


def test_color_extrinsics_from_a_file_or_a_topic_and_what_is_refused(tmp_path, rng):
    from ti_fusion.io.datasets.extrinsics import read_extrinsics_file

    T = make_pose(so3_exp(np.array([0.0, 0.05, 0.0])), [0.02, 0.0, 0.001])
    q = rot_to_quat(T[:3, :3])
    (tmp_path / "q.txt").write_text(f"# tx ty tz qx qy qz qw\n0.02 0 0.001 {q[0]} {q[1]} {q[2]} {q[3]}\n")
    (tmp_path / "m.txt").write_text("\n".join(" ".join(map(str, row)) for row in T[:3]))
    for name in ("q.txt", "m.txt"):
        np.testing.assert_allclose(read_extrinsics_file(tmp_path / name), T, atol=1e-9)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="3 numbers; expected a 4x4 or 3x4 matrix"):
        read_extrinsics_file(tmp_path / "bad.txt")
    (tmp_path / "mm.txt").write_text("1 0 0 25\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(InputError, match="25.00 m from the depth camera: metres are expected"):
        read_extrinsics_file(tmp_path / "mm.txt")
    (tmp_path / "skew.txt").write_text("1 0.5 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(InputError, match="not a rotation"):
        read_extrinsics_file(tmp_path / "skew.txt")
    shots = small_shots(rng, n=2)
    bag = write_bag(tmp_path / "b", shots, color_frame="camera_color_optical", color_k=K_SMALL)
    ds = open_dataset(small_cfg(bag, color_extrinsics=str(tmp_path / "q.txt")))
    np.testing.assert_allclose(ds.color_extrinsics, T, atol=1e-9)
    assert ds.notes == [] and ds[0].meta["color_camera"][0].fx == K_SMALL[0] and ds[0].color_registered is False
    with pytest.raises(InputError, match="--color-extrinsics /tf_static: neither a file nor a topic of the bag"):
        open_dataset(small_cfg(bag, color_extrinsics="/tf_static"))
    with pytest.raises(InputError, match=f"--color-extrinsics {INFO}: a sensor_msgs/msg/CameraInfo topic, not a "
                                         "transform"):
        open_dataset(small_cfg(bag, color_extrinsics=INFO))
    bag = write_bag(tmp_path / "c", shots, color_frame="camera_color_optical")
    with pytest.raises(InputError, match="no /camera/color/camera_info beside /camera/color/image_raw"):
        open_dataset(small_cfg(bag, color_extrinsics=str(tmp_path / "q.txt")))


def test_a_pose_topic_not_named_is_hinted(tmp_path, rng, caplog):
    """A bag with a pose topic and no --gt-topic: no ground truth (a bag's poses may be odometry), and one
    line names the topic, the option, and where the trajectory starts either way."""
    import logging

    bag = write_bag(tmp_path / "bag", small_shots(rng, n=2), gt="pose")
    with caplog.at_level(logging.INFO, logger="ti_fusion"):
        assert open_dataset(small_cfg(bag)).has_ground_truth is False
    (hint,) = [r.getMessage() for r in caplog.records if "pose topics" in r.getMessage()]
    assert hint.startswith(f"the bag has pose topics ({GT} (geometry_msgs/msg/PoseStamped)): --gt-topic {GT} "
                           "evaluates the run against one")
    assert "starts at the identity" in hint
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ti_fusion"):
        assert open_dataset(small_cfg(bag, gt_topic=GT)).has_ground_truth is True
    assert not [r for r in caplog.records if "pose topics" in r.getMessage()]
