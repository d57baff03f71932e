"""``sensor_msgs/CompressedImage`` payloads as arrays: image_transport's ``compressedDepth`` depth and
``compressed`` (JPEG/PNG) colour, as robots record them in ROS 1 and ROS 2 bags.

compressedDepth (compressed_depth_image_transport's codec): the ``format`` field reads
``"16UC1; compressedDepth png"`` or ``"32FC1; compressedDepth png"`` (older recorders write only
``"16UC1; compressedDepth"``); the data is a 12-byte ``ConfigHeader`` (int32 format, float32
depthQuantA, float32 depthQuantB) followed by a 16-bit PNG. 16UC1 is the raw units, losslessly; 32FC1
stores quantised inverse depth, ``q = A / z + B`` (0 = no depth), decoded as ``z = A / (q - B)``. The
RVL format of newer ROS 2 releases is refused with one line (no Python decoder here).
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from ti_fusion.errors import InputError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CONFIG_HEADER = 12  # compressed_depth_image_transport's ConfigHeader: int32 format, float32 depthParam[2]


def is_compressed_depth(fmt: str) -> bool:
    return "compresseddepth" in (fmt or "").lower()


def compressed_depth_encoding(fmt: str) -> str:
    """The raw encoding a compressedDepth ``format`` names (``16UC1`` or ``32FC1``)."""
    return (fmt or "").split(";")[0].strip()


def decode_compressed_depth(fmt: str, data, where: str) -> tuple[np.ndarray, str]:
    """(array, encoding): uint16 raw units for 16UC1, float32 metres (NaN = no depth) for 32FC1."""
    encoding = compressed_depth_encoding(fmt)
    if encoding not in ("16UC1", "mono16", "32FC1"):
        raise InputError(None, f"{where}: compressedDepth of {encoding!r} (format {fmt!r}): only 16UC1 and 32FC1 "
                               "are compressedDepth encodings")
    if "rvl" in fmt.lower():
        raise InputError(None, f"{where}: compressedDepth format {fmt!r} (RVL) is not supported: record with the "
                               "png format (the compressed_depth_image_transport parameter format: png) or raw images")
    raw = np.asarray(data, dtype=np.uint8).reshape(-1).tobytes()
    # the header is absent in the first releases of the codec: the PNG then starts at byte 0
    start = CONFIG_HEADER if raw[CONFIG_HEADER:CONFIG_HEADER + 8] == PNG_MAGIC else 0
    if raw[start:start + 8] != PNG_MAGIC:
        raise InputError(None, f"{where}: compressedDepth data ({len(raw)} bytes, format {fmt!r}) holds no PNG image")
    image = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8, offset=start), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint16 or image.ndim != 2:
        what = "cannot be decoded" if image is None else f"is {image.dtype} with shape {image.shape}"
        raise InputError(None, f"{where}: compressedDepth PNG {what}, expected one 16-bit channel")
    if encoding != "32FC1":
        return image, encoding
    if start == 0:
        raise InputError(None, f"{where}: 32FC1 compressedDepth without its quantisation header")
    _, quant_a, quant_b = struct.unpack("<iff", raw[:CONFIG_HEADER])
    q = image.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(quant_a) / (q - np.float32(quant_b))
    depth[image == 0] = np.nan
    return depth.astype(np.float32), encoding


def encode_compressed_depth(depth: np.ndarray, encoding: str = "16UC1", depth_max: float = 10.0,
                            quantization: float = 100.0) -> bytes:
    """The codec's encoder (for tests and for writing bags): 16-bit raw units, or float32 metres quantised
    as compressed_depth_image_transport does (its defaults: depth_max 10 m, depth_quantization 100)."""
    if encoding == "32FC1":
        quant_a = quantization * (quantization + 1.0)
        quant_b = 1.0 - quant_a / depth_max
        valid = np.isfinite(depth) & (depth > 0) & (depth < depth_max)
        q = np.zeros(depth.shape, np.uint16)
        q[valid] = (np.float32(quant_a) / depth[valid] + np.float32(quant_b)).astype(np.uint16)
        header = struct.pack("<iff", 1, quant_a, quant_b)
        image = q
    else:
        header = struct.pack("<iff", 1, 0.0, 0.0)
        image = np.ascontiguousarray(depth, dtype=np.uint16)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return header + png.tobytes()


def decode_compressed_color(fmt: str, data, where: str) -> np.ndarray:
    """uint8 H×W×3 RGB of a JPEG or PNG CompressedImage (``format`` as image_transport writes it, e.g.
    ``"rgb8; jpeg compressed bgr8"``: the compressed image is in OpenCV's BGR order)."""
    bgr = cv2.imdecode(np.asarray(data, dtype=np.uint8).reshape(-1), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(None, f"{where}: compressed image ({fmt!r}) cannot be decoded")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
