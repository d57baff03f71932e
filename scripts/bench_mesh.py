#!/usr/bin/env python3
"""The mesh against the truth on a synthetic scene, beside Open3D's TSDF + marching cubes on the same frames.

    python scripts/bench_mesh.py [--scene room] [--frames N] [--voxel 0.01] [--poses gt,tracked]
                                 [--open3d-python PY] [--sdf-trunc VOXELS] [--out DIR] [--reuse]

The synthetic scenes' geometry is known exactly, so each mesh is measured against it with the standard
surface-reconstruction metrics (Knapitsch et al. 2017, Tanks and Temples):
- accuracy: mean distance from the mesh to the true surface (mm; points sampled uniformly on the mesh,
  one per 2 mm × 2 mm, measured analytically against the scene's primitives);
- precision@τ: the share of those points within τ of the truth;
- completeness@τ (recall): the share of the observed truth within τ of the mesh. The observed truth is every
  valid pixel of noiseless renders at the ground-truth poses of every ``--truth-stride``-th frame (within
  the sensor's range), thinned to one point per 5 mm voxel; its distance to the mesh is to the nearest mesh
  sample (over-estimated by at most ~1.4 mm, the same for every mesh);
- F@τ = 2PR / (P + R), at τ = 1 cm and 5 cm.

Rows:
- ti-fusion, gt poses: ``ti-fusion fuse`` (the surfel map at the ground-truth poses), then the mesh of its
  map.ply (``ti_fusion.mapping.mesh``) at ``--voxel``;
- ti-fusion, tracked poses: ``ti-fusion slam`` (its own poses, anchored at the first ground-truth pose), then
  the mesh;
- each with ``--method``: ``surfels`` meshes the run's map.ply; ``depth`` integrates the dataset's frames at the
  run's poses (the ground truth, or the slam run's trajectory.tum) into a truncated signed-distance grid
  (``ti_fusion.mapping.mesh.DepthFusion``, what ``slam --mesh --set mesh.method=depth`` does during the run);
- Open3D TSDF (optional peer, never a dependency: ``pip install open3d-cpu``, here or in the interpreter
  ``--open3d-python`` names): a ``o3d.t.geometry.VoxelBlockGrid`` TSDF (its reconstruction system's, as in
  ``o3d.t.pipelines.slam.Model``) at the same voxel size, truncation ``--sdf-trunc`` voxels (4: Open3D's
  examples' 0.04 m at 1 cm), depth cut at the sensor's maximum range, the same frames (the dataset's
  full-resolution depth and colour) at the ground-truth poses, then ``extract_triangle_mesh`` (marching
  cubes over voxels of weight ≥ 3, its default). (The legacy ``ScalableTSDFVolume`` of open3d-cpu 0.20
  extracted no triangle from these frames.) It runs in a child process on frames this script writes to a
  temporary .npz.
``mesh s`` is the wall time of making the mesh from the map (ti-fusion: splat + marching cubes, without
reading map.ply; Open3D: integration + extraction, with neither the frames' reading nor the interpreter's
start): machine-dependent, a ratio within one run only.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()

O3D_WORKER = r'''
import json, sys, time
import numpy as np
import open3d as o3d
import open3d.core as o3c
frames, out, voxel, trunc_voxels, depth_max = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
d = np.load(frames)
depth, color, poses, K = d["depth"], d["color"], d["poses"], d["K"]
t0 = time.perf_counter()
vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                    attr_dtypes=(o3c.float32, o3c.float32, o3c.float32), attr_channels=((1), (1), (3)),
                                    voxel_size=voxel, block_resolution=8, block_count=200000, device=o3c.Device("CPU:0"))
intr = o3c.Tensor(np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1]]), o3c.float64)
for i in range(len(depth)):
    dt = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth[i][:, :, None])))
    ct = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color[i].astype(np.float32) / 255.0)))
    extr = o3c.Tensor(np.linalg.inv(poses[i]), o3c.float64)
    blocks = vbg.compute_unique_block_coordinates(dt, intr, extr, 1.0, depth_max, trunc_voxels)
    vbg.integrate(blocks, dt, ct, intr, intr, extr, 1.0, depth_max, trunc_voxels)
t1 = time.perf_counter()
mesh = vbg.extract_triangle_mesh().to_legacy()  # marching cubes over voxels seen at least 3 times (the default)
t2 = time.perf_counter()
mesh.compute_vertex_normals()
o3d.io.write_triangle_mesh(out, mesh)
print(json.dumps({"integrate_s": t1 - t0, "extract_s": t2 - t1, "version": o3d.__version__,
                  "triangles": len(mesh.triangles)}))
'''


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, spacing: float, rng, max_points: int = 6_000_000):
    """Points uniformly on the triangles, about one per ``spacing``² of area (at most ``max_points``)."""
    v = vertices.astype(np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    n = int(min(max_points, max(1000, area.sum() / spacing ** 2)))
    tri = rng.choice(len(faces), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]


def observed_truth(dataset, stride: int, voxel: float = 0.005) -> np.ndarray:
    """The surface the cameras saw: noiseless renders at every ``stride``-th ground-truth pose, back-projected
    within the sensor's range, one point per ``voxel``."""
    from ti_fusion.mapping.pointcloud import backproject, transform

    seq, cfg = dataset.sequence, dataset.synth
    pts = []
    for i in range(0, len(dataset), stride):
        raw = dataset.indices[i]
        depth, _ = seq.render(seq.poses[raw], noise=False)
        depth = np.where((depth >= cfg.min_range) & (depth <= cfg.max_range), depth, 0)
        xyz, _ = backproject(depth, seq.intrinsics)
        pts.append(transform(seq.poses[raw], xyz))
    p = np.concatenate(pts)
    _, first = np.unique(np.floor(p / voxel).astype(np.int64), axis=0, return_index=True)
    return p[first]


def metrics(vertices, faces, scene, truth_pts, rng, taus=(0.01, 0.05)) -> dict:
    from scipy.spatial import cKDTree

    if len(faces) == 0:
        return {"triangles": 0}
    samples = sample_mesh(vertices, faces, 0.002, rng)
    d_acc = np.concatenate([scene.surface_distance(c) for c in np.array_split(samples, 1 + len(samples) // 200_000)])
    d_comp, _ = cKDTree(samples).query(truth_pts, workers=-1)
    out = {"triangles": int(len(faces)), "accuracy_mm": round(float(d_acc.mean()) * 1e3, 3),
           "accuracy_median_mm": round(float(np.median(d_acc)) * 1e3, 3)}
    for tau in taus:
        p, r = float((d_acc <= tau).mean()), float((d_comp <= tau).mean())
        cm = f"{tau * 100:g}cm"
        out[f"precision_{cm}"] = round(p, 6)
        out[f"completeness_{cm}"] = round(r, 6)
        out[f"f_{cm}"] = round(2 * p * r / (p + r) if p + r > 0 else 0.0, 6)
    return out


def slot_openings(vertices: np.ndarray, faces: np.ndarray, step: float = 0.001) -> dict:
    """How open the ``slats`` scene's slots are in a mesh: rays straight through the slats' plane (along +y),
    across each slot and 1 cm into the slats either side (every ``step`` metres) at every centimetre of height
    between the rails (3 cm clear of them); the clear width at each height is the longest run of rays that no
    triangle stops within 5 cm of the plane. ``width_cm``: the median of those widths (the truth: the slot,
    3 cm); ``open``: the share of the rays within the slot's middle 2 cm that pass."""
    from ti_fusion.synthetic.scenes import SLAT_HALF, SLATS_Y, SLATS_Z, SLOT, slot_xs

    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces)]
    near = (np.abs(tri[:, :, 1] - SLATS_Y) < 0.05).all(axis=1)
    widths, clear = [], []
    for x0 in slot_xs():
        xs = x0 + np.arange(-SLOT / 2 - 0.01, SLOT / 2 + 0.01 + step / 2, step)
        zs = SLATS_Z + np.arange(-SLAT_HALF[2] + 0.03, SLAT_HALF[2] - 0.03 + 1e-9, 0.01)
        box = near & (tri[:, :, 0].max(axis=1) >= xs[0]) & (tri[:, :, 0].min(axis=1) <= xs[-1])
        t = tri[box][:, :, [0, 2]]  # the triangles seen along y: their x, z
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        px, pz = np.meshgrid(xs, zs)
        q = np.stack([px.ravel(), pz.ravel()], axis=1)
        hit = np.zeros(len(q), bool)
        den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
        ok = np.abs(den) > 1e-15
        a, b, c, den = a[ok], b[ok], c[ok], den[ok]
        for chunk in np.array_split(np.arange(len(q)), 1 + len(q) // 2000):
            d = q[chunk, None, :]
            l1 = ((b[:, 1] - c[:, 1]) * (d[..., 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (d[..., 1] - c[:, 1])) / den
            l2 = ((c[:, 1] - a[:, 1]) * (d[..., 0] - c[:, 0]) + (a[:, 0] - c[:, 0]) * (d[..., 1] - c[:, 1])) / den
            hit[chunk] = ((l1 >= 0) & (l2 >= 0) & (1 - l1 - l2 >= 0)).any(axis=1)
        passed = ~hit.reshape(len(zs), len(xs))
        for row in passed:
            best = run = 0
            for ok_ray in row:
                run = run + 1 if ok_ray else 0
                best = max(best, run)
            widths.append(best * step)
        middle = np.abs(xs - x0) <= 0.01
        clear.append(passed[:, middle].mean())
    return {"width_cm": round(float(np.median(widths)) * 100, 2), "open": round(float(np.mean(clear)), 4)}


def run_ti_fusion(command: str, args, out: Path) -> dict:
    """``ti-fusion fuse|slam`` in this process, then the mesh of its map.ply; the mesh and its timing."""
    from ti_fusion.cli.main import main
    from ti_fusion.config import MeshConfig
    from ti_fusion.mapping.mesh import mesh_surfels, surfels_from_ply

    argv = [command, "--out", str(out), "--overwrite", "--quiet", "--set", f"synth.scene={args.scene}"]
    if args.frames:
        argv += ["--frames", str(args.frames)]
    if command == "fuse":
        argv.append("--no-views")
    for item in args.set:
        argv += ["--set", item]
    t0 = time.perf_counter()
    if not (args.reuse and (out / "map.ply").is_file()) and main(argv) != 0:
        raise SystemExit(f"ti-fusion {command} failed")
    run_s = time.perf_counter() - t0
    surfels = surfels_from_ply(out / "map.ply")
    stats: dict = {}
    t0 = time.perf_counter()
    mesh = mesh_surfels(surfels, MeshConfig(voxel_size=args.voxel), stats=stats)
    mesh_s = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    return {"mesh": mesh, "mesh_s": mesh_s, "run_s": run_s, "stats": stats,
            "ate_cm": None if summary.get("ate_rmse_m") is None else summary["ate_rmse_m"] * 100}


def depth_mesh(args, dataset, frames, poses) -> dict:
    """``mesh.method = "depth"``: the dataset's frames integrated at ``poses`` (one per frame, None: skipped), as
    ``slam --mesh --set mesh.method=depth`` integrates each tracked frame at its pose; the mesh and its timing."""
    from ti_fusion.config import MeshConfig
    from ti_fusion.mapping.mesh import DepthFusion

    cfg = MeshConfig(voxel_size=args.voxel, method="depth")
    for item in args.mesh_set:
        key, value = item.split("=", 1)
        setattr(cfg, key, type(getattr(cfg, key))(value))
    fusion = DepthFusion(cfg)
    t0 = time.perf_counter()
    for f, pose in zip(frames, poses):
        if pose is not None:
            fusion.integrate(f.depth, f.color, f.intrinsics, pose)
    t1 = time.perf_counter()
    stats: dict = {}
    mesh = fusion.mesh(stats)
    stats["integrate_s"] = round(t1 - t0, 2)
    return {"mesh": mesh, "mesh_s": time.perf_counter() - t0, "stats": stats}


def run_poses(run: Path, frames) -> list:
    """Each frame's pose in a run's trajectory.tum (matched by timestamp), None where the run gave it none."""
    from ti_fusion.io.trajectory import read_tum

    stamps, poses = read_tum(run / "trajectory.tum")
    out = []
    for f in frames:
        i = int(np.argmin(np.abs(stamps - f.timestamp)))
        out.append(poses[i] if abs(stamps[i] - f.timestamp) < 1e-4 else None)
    return out


def run_open3d(args, dataset, tmp: Path) -> dict:
    dataset.downsample = args.open3d_downsample
    frames = [dataset[i] for i in range(len(dataset))]
    dataset.downsample = 1
    K = frames[0].intrinsics
    npz = tmp / "frames.npz"
    np.savez(npz, depth=np.stack([f.depth for f in frames]).astype(np.float32),
             color=np.stack([f.color for f in frames]).astype(np.uint8),
             poses=np.stack([f.gt_pose for f in frames]), K=np.array([K.fx, K.fy, K.cx, K.cy]))
    out = tmp / "open3d.ply"
    python = args.open3d_python or sys.executable
    cmd = [python, "-c", O3D_WORKER, str(npz), str(out), str(args.voxel), str(args.sdf_trunc),
           str(dataset.synth.max_range)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"error": f"not available ({last}; pip install open3d-cpu, or --open3d-python PY)"}
    info = json.loads(proc.stdout.strip().splitlines()[-1])
    if not out.is_file():
        return {"error": f"Open3D wrote no mesh ({info['triangles']} triangles): {proc.stderr.strip()[-300:]}"}
    import trimesh

    m = trimesh.load(out, process=False)
    return {"vertices": np.asarray(m.vertices), "faces": np.asarray(m.faces),
            "mesh_s": info["integrate_s"] + info["extract_s"], "version": info["version"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="room")
    p.add_argument("--frames", type=int, default=0, help="frames of the scene's path (0: all)")
    p.add_argument("--voxel", type=float, default=0.01, help="metres, for every mesh")
    p.add_argument("--poses", default="gt,tracked", help="ti-fusion rows: gt, tracked or both")
    p.add_argument("--open3d-python", default=None, metavar="PY", help="the interpreter that has open3d")
    p.add_argument("--no-open3d", action="store_true")
    p.add_argument("--sdf-trunc", type=float, default=4.0, help="Open3D's truncation, in voxels")
    p.add_argument("--truth-stride", type=int, default=10)
    p.add_argument("--out", default=None, help="folder for the meshes (mesh_*.ply) and results.json")
    p.add_argument("--reuse", action="store_true", help="reuse the fuse and slam runs already in --out")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a config value for the ti-fusion runs (e.g. fusion.level=0), repeatable")
    p.add_argument("--method", default="surfels,depth",
                   help="ti-fusion's mesh methods (mesh.method): surfels (the map's), depth (the frames re-integrated)")
    p.add_argument("--mesh-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a [mesh] value for the depth method (e.g. truncation=3), repeatable")
    p.add_argument("--open3d-downsample", type=int, default=1, metavar="F",
                   help="Open3D integrates every F-th pixel (2: the 320x240 the surfel map is fused at by default)")
    args = p.parse_args()

    from ti_fusion.backend import init_backend
    from ti_fusion.config import DatasetConfig, SynthConfig
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.mesh_files import write_mesh_ply

    init_backend("cpu")
    synth = SynthConfig(scene=args.scene)
    ds_cfg = DatasetConfig()
    if args.frames:
        ds_cfg.stop = args.frames
        synth.frames = max(synth.frames, args.frames)
    dataset = open_dataset(ds_cfg, synth)
    out = Path(args.out or tempfile.mkdtemp(prefix="bench_mesh_"))
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    truth = observed_truth(dataset, args.truth_stride)
    scene = dataset.sequence.scene
    rows = []
    methods = [m.strip() for m in args.method.split(",")]
    frames = [dataset[i] for i in range(len(dataset))] if "depth" in methods else []
    for poses in args.poses.split(","):
        command = {"gt": "fuse", "tracked": "slam"}[poses.strip()]
        if methods == ["depth"] and poses.strip() == "gt":  # the frames at the truth's poses: no run needed
            r = {"ate_cm": None}
        else:
            r = run_ti_fusion(command, args, out / command)
        for method in methods:
            res = r
            if method == "depth":
                pose_list = [f.gt_pose for f in frames] if poses == "gt" else run_poses(out / command, frames)
                res = {**r, **depth_mesh(args, dataset, frames, pose_list)}
            m = res["mesh"]
            suffix = "" if method == "surfels" else f"_{method}"
            write_mesh_ply(out / f"mesh_ti-fusion_{poses}{suffix}.ply", m)
            extra = args.set + (args.mesh_set if method == "depth" else [])
            rows.append({"system": f"ti-fusion {method} ({poses} poses{', ' if extra else ''}{', '.join(extra)})",
                         "mesh_s": round(res["mesh_s"], 2), "ate_cm": res["ate_cm"], "stats": res["stats"],
                         **metrics(m.vertices, m.faces, scene, truth, rng),
                         **(slot_openings(m.vertices, m.faces) if args.scene == "slats" else {})})
    if not args.no_open3d:
        with tempfile.TemporaryDirectory() as tmp:
            o = run_open3d(args, dataset, Path(tmp))
            if "error" in o:
                rows.append({"system": "Open3D TSDF", "error": o["error"]})
            else:
                import shutil

                shutil.copy(Path(tmp) / "open3d.ply", out / "mesh_open3d.ply")
                size = f"{640 // args.open3d_downsample}x{480 // args.open3d_downsample}"
                rows.append({"system": f"Open3D {o['version']} TSDF (gt poses, {size}, trunc {args.sdf_trunc:g} voxels)",
                             "mesh_s": round(o["mesh_s"], 2), **metrics(o["vertices"], o["faces"], scene, truth, rng),
                             **(slot_openings(o["vertices"], o["faces"]) if args.scene == "slats" else {})})
    print(f"{args.scene}, {len(dataset)} frames, voxel {args.voxel * 100:g} cm, observed truth {len(truth)} points "
          f"(every {args.truth_stride}th frame, 5 mm)")
    cols = ["triangles", "accuracy_mm", "precision_1cm", "completeness_1cm", "f_1cm", "f_5cm", "mesh_s"]
    if args.scene == "slats":  # how open the slots are (slot_openings)
        cols += ["width_cm", "open"]
    print(f"{'system':48s} " + " ".join(f"{c:>16s}" for c in cols))
    for r in rows:
        if "error" in r:
            print(f"{r['system']:48s} {r['error']}")
            continue
        print(f"{r['system']:48s} " + " ".join(f"{r.get(c, ''):>16}" for c in cols))
    (out / "results.json").write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1, default=str))
    print(f"meshes and results.json in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
