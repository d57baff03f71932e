r"""Loop closure on a synthetic scene, on and off: ATE, and whether the walls of the first and the last pass
coincide (docs/LOOP_CLOSURE.md).

    .venv/bin/python scripts/loop_consistency.py --scene loop --first 300 --last 100 \
        --set slam.active_window=200 --set icp.color_weight=0.01 --set synth.depth_noise_scale=4.5 --keep RUNS

For each setting, a slam run of the whole scene (320×240 with --downsample 2), then: the last ``--last``
frames' depth (every 4th pixel), back-projected at the run's final (corrected) poses, against the map's
first-pass surfels (created while fusing the first ``--first`` frames): the point-to-plane distance to
the nearest such surfel (points further than 0.5 m from every one are left out: none left, no statistics),
beside the sensor's depth noise σ(z) at those points (× ``synth.depth_noise_scale``); and the map's distance to
the true surfaces (every confirmed surfel); and the final trajectory's unaligned position error every 100
frames. Prints one JSON object per setting.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ti_fusion.backend import init_backend
from ti_fusion.config import load_config
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.outputs import RunDir
from ti_fusion.sensor import depth_sigma
from ti_fusion.slam.pipeline import SLAMPipeline

STEP = 4  # pixels between the back-projected points of a frame, in u and v
NEAR = 0.5  # metres: a point further than this from every first-pass surfel sees no first-pass wall


def measure(overrides: list[str], first: int, last: int, out: Path) -> dict:
    cfg = load_config(None, overrides)
    cfg.log.progress = False
    dataset = open_dataset(cfg.dataset, cfg.synth)
    pipeline = SLAMPipeline(dataset, cfg, RunDir("slam", out, overwrite=True), None, show_progress=False)
    summary = pipeline.run()
    slam = pipeline.step.slam
    surfels = slam.mapper.to_numpy()
    fused_by_first = sum(r.tracked for r in pipeline.results[:first])
    keep = (surfels["t_created"] < fused_by_first) & (surfels["weight"] >= cfg.fusion.unstable_weight)
    pos, nrm = surfels["position"][keep].astype(np.float64), surfels["normal"][keep].astype(np.float64)
    tree = cKDTree(pos)
    distances, sigmas, points = [], [], []
    for i in range(len(dataset) - last, len(dataset)):
        result = pipeline.results[i]
        if result.pose is None:
            continue
        frame = dataset[i]
        K = frame.intrinsics
        v, u = np.mgrid[0:frame.depth.shape[0]:STEP, 0:frame.depth.shape[1]:STEP]
        z = frame.depth[v, u].astype(np.float64)
        ok = z > 0
        p = np.column_stack([(u[ok] - K.cx) * z[ok] / K.fx, (v[ok] - K.cy) * z[ok] / K.fy, z[ok]])
        world = p @ result.pose[:3, :3].T + result.pose[:3, 3]
        points.append(world.astype(np.float32))
        d, j = tree.query(world)
        near = d < NEAR
        distances.append(np.abs(np.einsum("ij,ij->i", world[near] - pos[j[near]], nrm[j[near]])))
        sigmas.append(cfg.synth.depth_noise_scale * depth_sigma(z[ok][near]))
    dist, sig = np.concatenate(distances), np.concatenate(sigmas)
    np.savez_compressed(out / "surfels.npz", anchor=slam.mapper.anchors(), first_pass_frames=fused_by_first,
                        fused_frames=sum(r.tracked for r in pipeline.results), last_points=np.concatenate(points),
                        last_pass_frames=sum(r.tracked for r in pipeline.results[-last:]), **surfels)
    truth_poses = dataset.sequence.poses
    errors_cm = [None if r.pose is None else round(100 * float(np.linalg.norm(r.pose[:3, 3] - gt[:3, 3])), 1)
                 for r, gt in zip(pipeline.results, truth_poses)]
    all_pos = surfels["position"][surfels["weight"] >= cfg.fusion.unstable_weight].astype(np.float64)
    truth = dataset.sequence.surface_distance(all_pos)
    return {"overrides": overrides, "frames": summary["frames"], "ate_rmse_m": summary.get("ate_rmse_m"),
            "ate_max_m": summary.get("ate_max_m"), "ate_percent_of_path": summary.get("ate_percent_of_path"),
            "path_length_m": summary.get("path_length_m"), "error_every_100_cm": errors_cm[::100],
            "error_last_cm": errors_cm[-1],
            "tracking_failures": summary["tracking_failures"],
            "fps_processing": summary["fps_processing"], "keyframes": summary["keyframes"],
            "loop_candidates": summary["loop_candidates"], "loops_applied": summary["loops_applied"],
            "loop_ms": summary.get("loop_ms"), "loops": summary.get("loops"),
            "loops_refused": summary.get("loops_refused"),
            "last_vs_first_pass": {"points": int(len(dist)), **({} if len(dist) == 0 else {
                "median_mm": round(1e3 * float(np.median(dist)), 2),
                "rms_mm": round(1e3 * float(np.sqrt(np.mean(dist ** 2))), 2),
                "p90_mm": round(1e3 * float(np.percentile(dist, 90)), 2),
                "sensor_sigma_median_mm": round(1e3 * float(np.median(sig)), 2),
                "within_3_sigma": round(float(np.mean(dist < 3 * sig)), 3)})},
            "map_to_truth": {"surfels": int(len(truth)), "median_mm": round(1e3 * float(np.median(truth)), 2),
                             "p90_mm": round(1e3 * float(np.percentile(truth, 90)), 2),
                             "p99_mm": round(1e3 * float(np.percentile(truth, 99)), 2)}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="loop")
    parser.add_argument("--downsample", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], help="SECTION.KEY=VALUE for both runs")
    parser.add_argument("--first", type=int, default=300, help="frames of the first pass")
    parser.add_argument("--last", type=int, default=60, help="last frames compared with the first pass")
    parser.add_argument("--only", choices=("on", "off"), help="one setting only")
    parser.add_argument("--keep", help="keep each run's folder under this folder instead of a temporary one, with "
                                       "surfels.npz: the map's surfels and anchors, the frames fused in all, in "
                                       "the first and in the last pass, and the last frames' points "
                                       "(scripts/plot_loop_map.py draws the map from it)")
    args = parser.parse_args()
    init_backend("cpu")
    base = [f"synth.scene={args.scene}", f"dataset.downsample={args.downsample}", *args.set]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = args.keep or tmp
        for setting in ("off", "on"):
            if args.only and setting != args.only:
                continue
            flag = f"slam.loop_closure={'true' if setting == 'on' else 'false'}"
            print(json.dumps({"loop_closure": setting, **measure([*base, flag], args.first, args.last,
                                                                   Path(tmp) / setting)}), flush=True)


if __name__ == "__main__":
    main()
