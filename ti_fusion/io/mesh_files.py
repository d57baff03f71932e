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
    v["red"], v["green"], v["blue"] = np.asarray(mesh.colours, np.uint8).T
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


def glb_bytes(mesh, generator: str = "ti-fusion") -> bytes:
    """``mesh`` as one glTF 2.0 binary: one node, one primitive (POSITION, NORMAL, COLOR_0 as normalised
    unsigned bytes, uint32 indices), a matte material whose base colour is the vertex colour. Coordinates are
    the map's own (metres, its world frame), not turned to glTF's +Y up."""
    pos = np.ascontiguousarray(mesh.vertices, np.float32)
    nrm = np.ascontiguousarray(mesh.normals, np.float32)
    rgba = np.empty((len(pos), 4), np.uint8)
    rgba[:, :3] = mesh.colours
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
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "surface"}],
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


def write_glb(path: str | Path, mesh) -> Path:
    """``mesh`` as a glTF binary file (``glb_bytes``): Blender, three.js, Unity (glTFast) and browsers open it."""
    path = Path(path)
    data = glb_bytes(mesh)
    with atomic_write(path, "wb") as out:
        out.write(data)
    return path


def write_mesh(path: str | Path, mesh) -> Path:
    """By extension: .ply or .glb."""
    path = Path(path)
    return write_glb(path, mesh) if path.suffix.lower() == ".glb" else write_mesh_ply(path, mesh)
