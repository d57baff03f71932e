"""Point clouds as binary little-endian PLY: x y z nx ny nz (float32) red green blue (uint8).

The layout MeshLab, CloudCompare and Open3D (``o3d.io.read_point_cloud``) read without options.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.io.outputs import atomic_write

VERTEX_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
    ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
    ("red", "u1"), ("green", "u1"), ("blue", "u1"),
])

_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
              "uint8": "u1", "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2",
              "int16": "<i2", "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def write_ply(path: str | Path, position: np.ndarray, normal: np.ndarray | None = None,
              color: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Write N points; ``color`` is RGB in [0, 255] (any numeric dtype, rounded and clipped); ``extra``:
    more float32 vertex properties after blue, by name (a map's confidence and radius, which viewers ignore).

    The file appears whole or not at all (``outputs.atomic_path``); a failed write raises ``OutputError``.
    """
    path = Path(path)
    n = len(position)
    extra = extra or {}
    dtype = np.dtype(VERTEX_DTYPE.descr + [(name, "<f4") for name in extra])
    data = np.zeros(n, dtype=dtype)
    data["x"], data["y"], data["z"] = np.asarray(position, dtype=np.float32).T
    if normal is not None:
        data["nx"], data["ny"], data["nz"] = np.asarray(normal, dtype=np.float32).T
    if color is not None:
        rgb = np.clip(np.rint(np.asarray(color, dtype=np.float64)), 0, 255).astype(np.uint8)
    else:
        rgb = np.full((n, 3), 200, dtype=np.uint8)
    data["red"], data["green"], data["blue"] = rgb.T
    for name, values in extra.items():
        data[name] = np.asarray(values, dtype=np.float32).reshape(n)
    header = ["ply", "format binary_little_endian 1.0", "comment written by ti-fusion",
              f"element vertex {n}"]
    header += [f"property {'float' if dtype[name].kind == 'f' else 'uchar'} {name}"
               for name in dtype.names]
    header.append("end_header")
    with atomic_write(path, "wb") as f:  # never a truncated map that looks complete
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.data)  # the array's own buffer: no second copy of a million-point map
    return path


def read_ply(path: str | Path) -> np.ndarray:
    """The vertex element of a binary little-endian PLY as a NumPy structured array (fields by name)."""
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file")
        fmt, count, fields, in_vertex = None, None, [], False
        while True:
            line = f.readline()
            if not line:
                raise InputError(path, "PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                in_vertex = words[1] == "vertex"
                if in_vertex:
                    if len(words) < 3 or not words[2].isdigit():
                        raise InputError(path, f"PLY header line {line.decode('ascii', 'replace').strip()!r}: "
                                               "expected 'element vertex COUNT'")
                    count = int(words[2])
                elif count is not None:
                    break  # vertex data comes first: later elements are not needed
            elif words[0] == "property" and in_vertex:
                if words[1] == "list" or words[1] not in _PLY_TYPES:
                    raise InputError(path, f"unsupported vertex property {' '.join(words[1:])}")
                fields.append((words[2], _PLY_TYPES[words[1]]))
        if fmt != "binary_little_endian" or count is None:
            raise InputError(path, f"expected a binary_little_endian PLY with vertices (format {fmt})")
        while line and line.strip() != b"end_header":
            line = f.readline()
        dtype = np.dtype(fields)
        raw = f.read(dtype.itemsize * count)
    whole = len(raw) // dtype.itemsize if dtype.itemsize else 0
    if whole != count:  # a file cut short (a copy or a disk that stopped): refuse rather than read part of it
        raise InputError(path, f"PLY truncated: it holds {whole} of the {count} vertices its header declares "
                               f"({len(raw)} of {dtype.itemsize * count} bytes)")
    return np.frombuffer(raw, dtype=dtype)
