#!/usr/bin/env python3
"""A picture of a mesh file (.ply or .glb), read with trimesh and rasterised here: docs/images/mesh.png.

    python scripts/render_mesh.py MESH [MESH ...] --out PNG [--eye X,Y,Z] [--target X,Y,Z] [--up X,Y,Z]
                                  [--size 960x720] [--fov 60] [--titles A,B]

Each mesh becomes one panel, seen from ``--eye`` towards ``--target`` (default: from above and in front of
the mesh's centre, 1.2 × its extent away), shaded by the vertex colours times a headlight (0.35 + 0.65 ·
|n · view|: a triangle seen from behind is drawn too, darker), with a z-buffer. The picture is made from
the file alone, so it shows what a viewer (MeshLab, Blender) opens, not the map. Small triangles (a few
pixels) are rasterised directly; larger ones are first split in four until they fit ``MAX_BOX`` (screen-space
interpolation, exact for the flat triangles' depth up to perspective).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

MAX_BOX = 12  # pixels: the largest triangle bounding box rasterised


def load(path: str):
    import trimesh

    m = trimesh.load(path, process=False)
    if hasattr(m, "geometry"):  # a glTF scene: its one mesh
        (m,) = m.geometry.values()
    colors = None
    if getattr(m.visual, "kind", None) == "vertex":
        colors = np.asarray(m.visual.vertex_colors)[:, :3]
    elif "color" in getattr(m.visual, "vertex_attributes", {}):
        colors = np.asarray(m.visual.vertex_attributes["color"])[:, :3]
    if colors is None:
        colors = np.full((len(m.vertices), 3), 200)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces), colors.astype(np.float64), \
        np.asarray(m.vertex_normals, np.float64)


def look_at(eye, target, up):
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)  # image y down
    return np.stack([r, d, f])  # world → camera rotation (x right, y down, z forward)


def render(v, f, rgb, n, eye, target, up, size=(960, 720), fov=60.0, background=255.0) -> np.ndarray:
    w, h = size
    R = look_at(eye, target, up)
    pc = (v - eye) @ R.T
    focal = 0.5 * w / np.tan(np.radians(fov) / 2)
    z = pc[:, 2]
    uv = np.stack([focal * pc[:, 0] / np.maximum(z, 1e-6) + w / 2, focal * pc[:, 1] / np.maximum(z, 1e-6) + h / 2], 1)
    view = (v - eye) / np.linalg.norm(v - eye, axis=1, keepdims=True)
    shade = 0.35 + 0.65 * np.abs(np.sum(n * view, axis=1))
    col = rgb * shade[:, None]
    zbuf = np.full(w * h, np.inf)
    image = np.full((w * h, 3), background)
    f = f[(z[f] > 0.05).all(axis=1)]
    uv, z, col, f = _split_large(uv, z, col, f, w, h)
    for chunk in np.array_split(f, max(1, len(f) // 40000)):
        a, b, c = uv[chunk[:, 0]], uv[chunk[:, 1]], uv[chunk[:, 2]]
        lo = np.floor(np.minimum(np.minimum(a, b), c)).astype(int)
        hi = np.ceil(np.maximum(np.maximum(a, b), c)).astype(int)
        ok = ((hi - lo) <= MAX_BOX).all(1) & (hi[:, 0] >= 0) & (lo[:, 0] < w) & (hi[:, 1] >= 0) & (lo[:, 1] < h)
        chunk, a, b, c, lo = chunk[ok], a[ok], b[ok], c[ok], lo[ok]
        box = np.max(np.ceil(np.maximum(np.maximum(a, b), c)).astype(int) - lo) + 1 if len(chunk) else 0
        oy, ox = np.mgrid[0:box, 0:box]
        px = lo[:, None, 0] + ox.ravel()[None] + 0.5
        py = lo[:, None, 1] + oy.ravel()[None] + 0.5
        den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
        den = np.where(np.abs(den) < 1e-12, 1e-12, den)[:, None]
        l1 = ((b[:, None, 1] - c[:, None, 1]) * (px - c[:, None, 0]) + (c[:, None, 0] - b[:, None, 0]) * (py - c[:, None, 1])) / den
        l2 = ((c[:, None, 1] - a[:, None, 1]) * (px - c[:, None, 0]) + (a[:, None, 0] - c[:, None, 0]) * (py - c[:, None, 1])) / den
        l3 = 1 - l1 - l2
        inside = (l1 >= 0) & (l2 >= 0) & (l3 >= 0) & (px >= 0) & (px < w) & (py >= 0) & (py < h)
        t, k = np.nonzero(inside)
        if not len(t):
            continue
        tri = chunk[t]
        L = np.stack([l1[t, k], l2[t, k], l3[t, k]], 1)
        depth = np.einsum("ij,ij->i", L, z[tri])
        color = np.einsum("ij,ijk->ik", L, col[tri])
        pix = (py[t, k].astype(int)) * w + px[t, k].astype(int)
        order = np.lexsort((depth, pix))
        pix, depth, color = pix[order], depth[order], color[order]
        first = np.r_[True, pix[1:] != pix[:-1]]
        pix, depth, color = pix[first], depth[first], color[first]
        nearer = depth < zbuf[pix]
        zbuf[pix[nearer]] = depth[nearer]
        image[pix[nearer]] = color[nearer]
    return np.clip(image.reshape(h, w, 3), 0, 255).astype(np.uint8)


def _split_large(uv, z, col, f, w, h, levels: int = 8):
    """Triangles wider than ``MAX_BOX`` pixels on screen split in four at their edges' midpoints (screen
    position, depth and colour interpolated linearly), until every one fits or ``levels`` splits were made."""
    for _ in range(levels):
        span = np.ptp(uv[f], axis=1).max(axis=1)
        big = span > MAX_BOX - 1
        on = (uv[f].max(axis=1) >= 0).all(1) & (uv[f].min(axis=1) < [w, h]).all(1)
        big &= on
        if not big.any():
            break
        fb = f[big]
        n0 = len(uv)
        mids = []
        for a, b in ((0, 1), (1, 2), (2, 0)):
            i, j = fb[:, a], fb[:, b]
            mids.append((0.5 * (uv[i] + uv[j]), 0.5 * (z[i] + z[j]), 0.5 * (col[i] + col[j])))
        k = len(fb)
        uv = np.concatenate([uv] + [m[0] for m in mids])
        z = np.concatenate([z] + [m[1] for m in mids])
        col = np.concatenate([col] + [m[2] for m in mids])
        m01, m12, m20 = n0 + np.arange(k), n0 + k + np.arange(k), n0 + 2 * k + np.arange(k)
        f = np.concatenate([f[~big], np.stack([fb[:, 0], m01, m20], 1), np.stack([m01, fb[:, 1], m12], 1),
                            np.stack([m20, m12, fb[:, 2]], 1), np.stack([m01, m12, m20], 1)])
    return uv, z, col, f


def vec(text: str | None):
    return None if text is None else np.array([float(x) for x in text.split(",")])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("meshes", nargs="+")
    p.add_argument("--out", required=True)
    p.add_argument("--eye", action="append", default=[], help="X,Y,Z per mesh (repeat), world frame")
    p.add_argument("--target", action="append", default=[], help="X,Y,Z per mesh (repeat)")
    p.add_argument("--up", action="append", default=[], help="X,Y,Z per mesh (repeat; default 0,0,1)")
    p.add_argument("--size", default="960x720")
    p.add_argument("--fov", type=float, default=60.0)
    p.add_argument("--titles", default=None, help="comma-separated panel titles")
    args = p.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = (int(x) for x in args.size.split("x"))
    titles = args.titles.split(",") if args.titles else [Path(m).name for m in args.meshes]
    fig, axes = plt.subplots(1, len(args.meshes), figsize=(w / 100 * len(args.meshes), h / 100 + 0.4), dpi=100)
    for i, (path, ax) in enumerate(zip(args.meshes, np.atleast_1d(axes))):
        v, f, rgb, n = load(path)
        centre = 0.5 * (v.min(0) + v.max(0))
        extent = float(np.linalg.norm(v.max(0) - v.min(0)))
        target = vec(args.target[i]) if i < len(args.target) else centre
        eye = vec(args.eye[i]) if i < len(args.eye) else centre + extent * np.array([0.0, -0.9, 0.8])
        up = vec(args.up[i]) if i < len(args.up) else np.array([0.0, 0.0, 1.0])
        ax.imshow(render(v, f, rgb, n, eye, target, up, (w, h), args.fov))
        ax.set_title(f"{titles[i]} ({len(f):,} triangles)", fontsize=11)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
