"""Readers shared by the dataset loaders: images, depth conversion, small text files.

Every reader raises ``InputError`` naming the file and the problem, so a bad dataset ends in one
clear line rather than a traceback from inside OpenCV or NumPy.
"""

from __future__ import annotations

import os
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.errors import InputError
from ti_fusion.io.tables import parse_floats, read_table


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "image file not found")
    # cv2.imread does not understand every path on every platform; decoding the bytes always works.
    data = np.fromfile(str(path), dtype=np.uint8)
    image = None
    if data.size:
        # Our InputError says it in one line; OpenCV's log lines and libpng's and libjpeg's own messages
        # about a broken file (written straight to the process's stderr) would be noise.
        with _opencv_silenced(), _stderr_silenced():
            image = cv2.imdecode(data, flags)
    if image is None:
        raise InputError(path, "unreadable or corrupt image")
    return image


_SILENCED = {"depth": 0, "level": None}  # readers inside ``_opencv_silenced``, and the level to give back
_SILENCED_LOCK = threading.Lock()


@contextmanager
def _opencv_silenced():
    """OpenCV's own log silenced for the duration, where this build exposes its log level (some OpenCV 4
    wheels have no ``cv2.utils.logging``; their messages then reach stderr, which is silenced too).

    The level is the process's: with several reader threads (``ti_fusion.io.prefetch``) the first one in
    silences it and the last one out restores it, so that no thread restores another's "silent"."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        yield
        return
    with _SILENCED_LOCK:
        if _SILENCED["depth"] == 0:
            _SILENCED["level"] = logging.getLogLevel()
            logging.setLogLevel(logging.LOG_LEVEL_SILENT)
        _SILENCED["depth"] += 1
    try:
        yield
    finally:
        with _SILENCED_LOCK:
            _SILENCED["depth"] -= 1
            if _SILENCED["depth"] == 0:
                logging.setLogLevel(_SILENCED["level"])


@contextmanager
def _stderr_silenced():
    """File descriptor 2 pointed at the null device for the duration (C libraries write there directly).

    On the main thread only: fd 2 is the whole process's, so silencing it on the pipeline's reader thread
    (``ti_fusion.io.prefetch``) would swallow what the main thread writes meanwhile (warnings, the last
    line of a run); a damaged image read ahead may then let libpng or libjpeg add their own line."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def read_depth_png(path: str | Path) -> np.ndarray:
    """The raw 16-bit depth image (H×W uint16), refusing 8-bit and multi-channel files."""
    path = Path(path)
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise InputError(path, f"depth image has {raw.shape[2]} channels, expected a single-channel 16-bit PNG")
    if raw.dtype != np.uint16:
        bits = raw.dtype.itemsize * 8
        raise InputError(path, f"depth image is {bits}-bit ({raw.dtype}), expected a 16-bit PNG")
    return raw


def read_color(path: str | Path) -> np.ndarray:
    """The colour image as H×W×3 uint8 RGB (OpenCV decodes to BGR; we swap)."""
    path = Path(path)
    bgr = _imread(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def depth_to_metres(raw: np.ndarray, scale: float, depth_max: float | None,
                    invalid: tuple[int, ...] = (0,)) -> np.ndarray:
    """float32 metres from raw integer depth: ``raw / scale``, 0 where invalid or beyond ``depth_max``.

    ``invalid`` lists raw values that mean "no measurement" (0 everywhere, 65535 in 7-Scenes).
    ``depth_max`` ≤ 0 or None keeps every range.
    """
    depth = raw.astype(np.float32) / np.float32(scale)
    # one comparison per invalid value: np.isin builds a lookup table over the whole uint16 range, which
    # made this conversion cost about as much as decoding the PNG on the frame reader's thread
    bad = np.zeros(raw.shape, dtype=bool)
    for value in invalid:
        bad |= raw == value
    if depth_max is not None and depth_max > 0:
        bad |= depth > depth_max
    depth[bad] = 0.0
    return depth


def check_same_size(color: np.ndarray, color_path: Path, depth: np.ndarray, depth_path: Path) -> None:
    if color.shape[:2] != depth.shape[:2]:
        ch, cw = color.shape[:2]
        dh, dw = depth.shape[:2]
        raise InputError(color_path, f"colour image is {cw}x{ch} but its depth image {Path(depth_path).name} is {dw}x{dh}")


def read_numbers(path: str | Path, what: str) -> np.ndarray:
    """All numbers of a small text file, in reading order (errors name the offending line)."""
    path = Path(path)
    if path.is_file():  # a file without comments and with only finite numbers: all its numbers in one parse
        try:
            text = path.read_text()
            if "#" not in text:
                values = np.array([float(f) for f in text.replace(",", " ").split()], dtype=np.float64)
                if np.all(np.isfinite(values)):
                    return values
        except (OSError, UnicodeDecodeError, ValueError):
            pass  # read line by line below, which says where and why
    rows = read_table(path, what)
    parsed = [parse_floats(fields, path, lineno) for lineno, fields in rows]
    return np.concatenate(parsed) if parsed else np.zeros(0)


def read_intrinsics_file(path: str | Path, width: int, height: int) -> Intrinsics:
    """Intrinsics from a calibration file: a text file holding "fx fy cx cy" or a 3×3 K matrix (9 numbers),
    or a YAML file (``.yaml``/``.yml``): a ROS ``camera_info`` (``k``/``K``: 9 numbers, or ``camera_matrix``
    with ``data``) or an OpenCV calibration (``camera_matrix: !!opencv-matrix``). A YAML file that states
    the image size must state the depth images' ``width`` × ``height``."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        return _intrinsics_from_yaml(path, width, height)
    values = read_numbers(path, "intrinsics file")
    if values.size not in (4, 9):
        raise InputError(path, f"expected 4 numbers (fx fy cx cy) or 9 (3x3 K), found {values.size}")
    return intrinsics_from_numbers(values, width, height, path)


def intrinsics_from_numbers(values, width: int, height: int, where: str | Path | None,
                            distortion=None, distortion_model: str = "") -> Intrinsics:
    """Intrinsics from (fx, fy, cx, cy) or a 3×3 K given row by row (its skew K[0,1] kept), with the lens
    ``distortion`` coefficients a calibration states (OpenCV's order) and their ``distortion_model``;
    ``where`` names the source in errors. Intrinsics that cannot be these images' camera are refused."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    skew = 0.0
    if values.size == 4:
        fx, fy, cx, cy = values
    elif values.size == 9:
        K = values.reshape(3, 3)
        fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise InputError(where, "3x3 intrinsics matrix must have last row [0 0 1] and K[1,0] = 0")
    else:
        raise InputError(where, f"expected 4 numbers (fx fy cx cy) or 9 (3x3 K), found {values.size}")
    if not np.all(np.isfinite(values)):
        raise InputError(where, "intrinsics contain NaN or infinite values")
    if fx <= 0 or fy <= 0:
        raise InputError(where, f"focal lengths must be positive (fx={fx:g}, fy={fy:g})")
    coefficients = _distortion(distortion, distortion_model, where)
    K = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height), skew=float(skew),
                   distortion=coefficients, distortion_model=distortion_model if coefficients else "")
    problem = K.implausibility()
    if problem:
        raise InputError(where, problem)
    return K


# Coefficients each distortion model takes (OpenCV's standard model: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
_COEFFICIENTS = {"plumb_bob": (4, 5, 8, 12, 14), "rational_polynomial": (4, 5, 8, 12, 14), "equidistant": (4,)}
_MODEL_NAMES = {"": "plumb_bob", "radtan": "plumb_bob", "radial-tangential": "plumb_bob", "opencv": "plumb_bob",
                "fisheye": "equidistant", "kannala_brandt": "equidistant"}


def _distortion(values, model: str, where) -> tuple[float, ...]:
    """The distortion coefficients as a tuple (() when there are none or all are 0), or InputError naming a
    model this reader does not undistort, or coefficients of the wrong count."""
    if values is None:
        return ()
    try:
        d = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(where, f"distortion coefficients are not a list of numbers: {values!r}") from None
    if not np.all(np.isfinite(d)):
        raise InputError(where, "distortion coefficients contain NaN or infinite values")
    if not d.size or not np.any(d):
        return ()
    name = _MODEL_NAMES.get(str(model).strip().lower(), str(model).strip().lower())
    if name not in _COEFFICIENTS:
        raise InputError(where, f"distortion model {model!r} is not supported (plumb_bob, rational_polynomial, "
                                "equidistant): undistort the images first and give a calibration without it")
    if d.size not in _COEFFICIENTS[name]:
        counts = " or ".join(str(n) for n in _COEFFICIENTS[name])
        raise InputError(where, f"{d.size} distortion coefficients for the {name} model, which takes {counts}")
    return tuple(float(x) for x in d)


def parse_intrinsics(spec, width: int, height: int, option: str = "--intrinsics") -> Intrinsics:
    """Intrinsics from ``--intrinsics`` (or ``dataset.intrinsics``): four numbers "fx,fy,cx,cy" (a list of
    them from a config file), or a calibration file (see ``read_intrinsics_file``)."""
    if isinstance(spec, (list, tuple)):
        spec = ",".join(str(v) for v in spec)
    text = str(spec).strip()
    fields = text.replace(",", " ").split()
    if len(fields) == 4 and not Path(text).is_file():
        try:
            values = [float(f) for f in fields]
        except ValueError:
            values = None
        if values is not None:
            return intrinsics_from_numbers(values, width, height, f"{option} {text}")
    path = Path(text)
    if not path.is_file():
        raise InputError(None, f"{option} {text}: neither four numbers fx,fy,cx,cy nor an existing file")
    return read_intrinsics_file(path, width, height)


def _intrinsics_from_yaml(path: Path, width: int, height: int) -> Intrinsics:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read intrinsics file: {exc}") from None
    if text.lstrip().startswith("%YAML:1") or "!!opencv-matrix" in text:
        return _intrinsics_from_opencv(path, width, height)
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(path, f"cannot parse YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a YAML mapping with camera_matrix or k (a camera_info)")
    if isinstance(data.get("camera_matrix"), dict):
        values = data["camera_matrix"].get("data")
    elif "k" in data or "K" in data:
        values = data.get("k", data.get("K"))
    elif all(key in data for key in ("fx", "fy", "cx", "cy")):
        values = [data[key] for key in ("fx", "fy", "cx", "cy")]
    else:
        raise InputError(path, "no camera_matrix, k or fx/fy/cx/cy in this YAML file")
    try:
        numbers = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(path, f"camera matrix is not a list of numbers: {values!r}") from None
    size = (data.get("image_width", data.get("width")), data.get("image_height", data.get("height")))
    _check_calibration_size(path, size, width, height)
    distortion = data.get("distortion_coefficients", data.get("d", data.get("D")))
    if isinstance(distortion, dict):  # camera_calibration_parsers: rows, cols, data
        distortion = distortion.get("data")
    return intrinsics_from_numbers(numbers, width, height, path, distortion,
                                   str(data.get("distortion_model") or ""))


def _intrinsics_from_opencv(path: Path, width: int, height: int) -> Intrinsics:
    """An OpenCV FileStorage calibration (``cv::FileStorage`` YAML with ``camera_matrix``)."""
    try:
        with _opencv_silenced(), _stderr_silenced():
            storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error:
        raise InputError(path, "cannot parse OpenCV calibration file") from None
    try:
        if not storage.isOpened():
            raise InputError(path, "cannot parse OpenCV calibration file")
        K = storage.getNode("camera_matrix").mat()
        if K is None:
            raise InputError(path, "no camera_matrix in this OpenCV calibration file")
        size = tuple(storage.getNode(k).real() if not storage.getNode(k).empty() else None
                     for k in ("image_width", "image_height"))
        node = next((storage.getNode(k) for k in ("distortion_coefficients", "dist_coeffs", "D")
                     if not storage.getNode(k).empty()), None)
        distortion = None if node is None else node.mat()
        model_node = storage.getNode("distortion_model")
        model = "" if model_node.empty() else model_node.string()
    finally:
        storage.release()
    _check_calibration_size(path, size, width, height)
    return intrinsics_from_numbers(K, width, height, path, distortion, model)


def _check_calibration_size(path: Path, size, width: int, height: int) -> None:
    """A calibration made for another image size does not fit these images (it would need scaling, and a
    crop cannot be told from a scale)."""
    w, h = size
    if w and h and (int(w), int(h)) != (int(width), int(height)):
        raise InputError(path, f"calibration is for {int(w)}x{int(h)} images, the depth images are "
                               f"{width}x{height}")


def read_pose_matrix(path: str | Path) -> np.ndarray:
    """A 4×4 rigid transform from a text file of 16 numbers (7-Scenes ``pose.txt``), re-orthonormalised."""
    from ti_fusion.geometry import orthonormalize, rigidity_error

    path = Path(path)
    values = read_numbers(path, "pose file")
    if values.size != 16:
        raise InputError(path, f"expected a 4x4 matrix (16 numbers), found {values.size}")
    T = values.reshape(4, 4)
    problem = rigidity_error(T)
    if problem:
        raise InputError(path, f"pose is not a rigid transform: {problem}")
    T[:3, :3] = orthonormalize(T[:3, :3])
    return T


def read_rgbd(depth_path: Path, color_path: Path | None, scale: float, depth_max: float | None,
              size: tuple[int, int], invalid: tuple[int, ...] = (0,)) -> tuple[np.ndarray, np.ndarray | None]:
    """(depth in metres, RGB colour or None) of one frame, checking both against ``size`` = (width, height)."""
    raw = read_depth_png(depth_path)
    width, height = size
    if raw.shape != (height, width):
        raise InputError(depth_path, f"depth image is {raw.shape[1]}x{raw.shape[0]}, "
                                     f"the sequence's first is {width}x{height}")
    depth = depth_to_metres(raw, scale, depth_max, invalid)
    color = None
    if color_path is not None:
        color = read_color(color_path)
        check_same_size(color, color_path, depth, depth_path)
    return depth, color
