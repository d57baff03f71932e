"""Triangle meshes as files: binary PLY (vertex positions, normals and colours; faces) and glTF binary (.glb).

Both are written here rather than through a mesh library: each is a header and a few packed arrays, and
the package stays without another dependency. The tests read them back with trimesh. Files appear whole
or not at all (``outputs.atomic_write``).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from ti_fusion.io.outputs import atomic_write

PLY_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
PLY_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def write_mesh_ply(path: str | Path, mesh) -> Path:
    """``mesh`` (``ti_fusion.mapping.mesh.Mesh``) as binary little-endian PLY: vertex x y z nx ny nz red green
    blue, face vertex_indices (uchar count, int indices): what MeshLab, Blender, Open3D and trimesh read."""
    path = Path(path)
    v = np.zeros(len(mesh.vertices), PLY_VERTEX)
    v["x"], v["y"], v["z"] = np.asarray(mesh.vertices, np.float32).T
    v["nx"], v["ny"], v["nz"] = np.asarray(mesh.normals, np.float32).T
    v["red"], v["green"], v["blue"] = np.asarray(mesh.colors, np.uint8).T
    f = np.zeros(len(mesh.faces), PLY_FACE)
    f["n"] = 3
    f["v"] = mesh.faces
    header = "\n".join([
        "ply", "format binary_little_endian 1.0", "comment written by ti-fusion mesh",
        f"element vertex {len(v)}",
        *(f"property {'float' if PLY_VERTEX[name].kind == 'f' else 'uchar'} {name}" for name in PLY_VERTEX.names),
        f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]) + "\n"
    with atomic_write(path, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(v.tobytes())
        out.write(f.tobytes())
    return path


# The map's world is its first camera's (or the ground truth's first pose): y points down the image, so the
# world's up is the first camera's -y, unless a caller knows better.
CAMERA_UP = (0.0, -1.0, 0.0)


def y_up_rotation(up) -> list[float]:
    """The quaternion (x, y, z, w) that turns the world vector ``up`` to glTF's +Y: 180° about x for the
    camera convention's -y (so the camera's forward +z becomes glTF's -z), else the shortest rotation."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    y = np.array([0.0, 1.0, 0.0])
    cos = float(u @ y)
    if cos < -1 + 1e-9:
        return [1.0, 0.0, 0.0, 0.0]
    axis = np.cross(u, y)
    q = np.array([*axis, 1.0 + cos])
    return (q / np.linalg.norm(q)).tolist()


def glb_bytes(mesh, generator: str = "ti-fusion", up=CAMERA_UP) -> bytes:
    """``mesh`` as one glTF 2.0 binary: one node, one primitive (POSITION, NORMAL, COLOR_0 as normalised
    unsigned bytes, uint32 indices), a matte material whose base colour is the vertex colour. The vertices
    are the map's own (metres, its world frame); the node's rotation turns the world's ``up`` to glTF's +Y,
    so viewers show the scene upright."""
    pos = np.ascontiguousarray(mesh.vertices, np.float32)
    nrm = np.ascontiguousarray(mesh.normals, np.float32)
    rgba = np.empty((len(pos), 4), np.uint8)
    rgba[:, :3] = mesh.colors
    rgba[:, 3] = 255
    idx = np.ascontiguousarray(mesh.faces, np.uint32).reshape(-1)
    chunks, views, offset = [], [], 0
    for data, target in ((pos, 34962), (nrm, 34962), (rgba, 34962), (idx, 34963)):
        raw = data.tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": target})
        pad = (-len(raw)) % 4
        chunks.append(raw + b"\0" * pad)
        offset += len(raw) + pad
    lo = pos.min(axis=0).tolist() if len(pos) else [0.0, 0.0, 0.0]
    hi = pos.max(axis=0).tolist() if len(pos) else [0.0, 0.0, 0.0]
    gltf = {
        "asset": {"version": "2.0", "generator": generator},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "surface", "rotation": y_up_rotation(up)}],
        "meshes": [{"name": "surface", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2}, "indices": 3, "mode": 4, "material": 0}]}],
        "materials": [{"name": "vertex colour", "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": len(pos), "type": "VEC3"},
            {"bufferView": 2, "componentType": 5121, "normalized": True, "count": len(pos), "type": "VEC4"},
            {"bufferView": 3, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
        ],
    }
    js = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    binary = b"".join(chunks)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total), struct.pack("<II", len(js), 0x4E4F534A), js,
                     struct.pack("<II", len(binary), 0x004E4942), binary])


def write_glb(path: str | Path, mesh, up=CAMERA_UP) -> Path:
    """``mesh`` as a glTF binary file (``glb_bytes``): Blender, three.js, Unity (glTFast) and browsers open it."""
    path = Path(path)
    data = glb_bytes(mesh, up=up)
    with atomic_write(path, "wb") as out:
        out.write(data)
    return path


def write_run_mesh(out, mesh, up=None) -> dict:
    """mesh.ply and mesh.glb in the run folder ``out`` (``RunDir``); their paths, for summary.json. ``up``: the
    world's up (the first camera's -y); None: the first camera's world."""
    return {"mesh_ply": str(write_mesh_ply(out.file("mesh.ply"), mesh)),
            "mesh_glb": str(write_glb(out.file("mesh.glb"), mesh, CAMERA_UP if up is None else up))}


def camera_up(pose) -> tuple[float, float, float]:
    """The world's up as a camera-to-world ``pose`` held level sees it: the camera's -y."""
    return tuple(float(v) for v in -np.asarray(pose, np.float64)[:3, 1])


def write_mesh(path: str | Path, mesh) -> Path:
    """By extension: .ply or .glb."""
    path = Path(path)
    return write_glb(path, mesh) if path.suffix.lower() == ".glb" else write_mesh_ply(path, mesh)


# -- the mesh as a Foxglove scene entity -------------------------------------------------------------------------
# foxglove.TriangleListPrimitive's points and colors are repeated messages: built one by one with protobuf's
# classes, a 150 k-vertex mesh takes seconds. Their wire format has a fixed size per element when every field
# is written (proto3 parsers accept explicit zeros), so NumPy packs them as records instead; the result parses
# as the same message (tests/mapping/test_mesh.py reads it back with the generated classes).
_POINT = np.dtype([("tag", "u1"), ("len", "u1"), ("tx", "u1"), ("x", "<f8"), ("ty", "u1"), ("y", "<f8"),
                   ("tz", "u1"), ("z", "<f8")])
_COLOR = np.dtype([("tag", "u1"), ("len", "u1"), ("tr", "u1"), ("r", "<f8"), ("tg", "u1"), ("g", "<f8"),
                   ("tb", "u1"), ("b", "<f8"), ("ta", "u1"), ("a", "<f8")])


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited field (a message, packed numbers or a string)."""
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def triangle_list_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    """A serialised foxglove.TriangleListPrimitive: identity pose, the vertices as ``points``, one RGBA per
    vertex in ``colors`` (``colors`` uint8 RGB), ``indices`` three per triangle."""
    n = len(vertices)
    pts = np.zeros(n, _POINT)
    pts["tag"], pts["len"] = 2 << 3 | 2, _POINT.itemsize - 2  # points = 2
    pts["tx"], pts["ty"], pts["tz"] = 1 << 3 | 1, 2 << 3 | 1, 3 << 3 | 1  # x, y, z: fixed64 doubles
    pts["x"], pts["y"], pts["z"] = np.asarray(vertices, np.float64).T
    col = np.zeros(n, _COLOR)
    col["tag"], col["len"] = 4 << 3 | 2, _COLOR.itemsize - 2  # colors = 4
    col["tr"], col["tg"], col["tb"], col["ta"] = 1 << 3 | 1, 2 << 3 | 1, 3 << 3 | 1, 4 << 3 | 1
    rgb = np.asarray(colors, np.float64) / 255.0
    col["r"], col["g"], col["b"], col["a"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], 1.0
    pose = _field(1, _field(2, b"\x21" + struct.pack("<d", 1.0)))  # pose.orientation.w = 1 (field 4, fixed64)
    color = _field(3, b"".join(b + struct.pack("<d", 0.8) for b in (b"\x09", b"\x11", b"\x19", b"\x21")))
    indices = _field(5, np.ascontiguousarray(faces, "<u4").tobytes())  # packed fixed32
    return pose + pts.tobytes() + color + col.tobytes() + indices


def scene_update_bytes(entity_head: bytes, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    """A serialised foxglove.SceneUpdate of one entity: ``entity_head`` (the entity's own fields, serialised,
    without primitives) and one triangle list (entity field 12)."""
    entity = entity_head + _field(12, triangle_list_bytes(vertices, faces, colors))
    return _field(2, entity)  # SceneUpdate.entities = 2
