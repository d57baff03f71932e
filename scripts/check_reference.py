#!/usr/bin/env python
"""Check reference poses (and optionally an estimated trajectory) against direct frame-pair ICP.

ATE measures agreement with the reference, so it is only as good as the reference. This script asks the
depth images themselves: for frame pairs (i, i + gap) it aligns frame i to frame i + gap by the project's
coarse-to-fine point-to-plane ICP, started from the reference's relative pose, and reports how far the
reference's relative motion lies from that direct alignment (and, with ``--trajectory``, how far the
estimate's does). A direct alignment has no accumulated drift, so a reference that disagrees with it much
more than the estimate does is the one that drifts. Pairs whose ICP keeps less than ``--min-inlier-ratio``
of the points (little overlap) are skipped.

It also lists the consecutive frames where the reference is inconsistent with the depth: the
point-to-plane residual (RMS, no robust weight, correspondences within 5 cm) at the reference's relative
pose exceeds the residual after ICP by more than ``--jump-mm``.

Redkitchen (7-Scenes, KinectFusion reference), 500 frames, with a ti-fusion run's trajectory: reference vs
direct ICP 3.5 / 12.6 / 25.3 mm RMS at gaps 1 / 10 / 30, ti-fusion 0.9 / 4.9 / 9.1 mm; the reference
jumps 36 mm at frame 122 (residual 15.4 mm at its pose, 2.2 mm after ICP) and 10–30 mm around 447–451.

With ``--pair I:J`` (repeatable) it looks at one pair of frames instead, e.g. a loop's two frames: the
relative pose of the reference and of each ``--trajectory`` (repeatable), each as a start of ICP, the pose
each start converges to, and each relative pose's offset from the best-aligned ICP result and its residual
(``--set fusion.level=0`` aligns at the full 640x480). Redkitchen's one loop (frames 262 and 499, found
with ``slam.loop_closure=true slam.active_window=200``): docs/LOOP_CLOSURE.md "Redkitchen's loop".

usage: scripts/check_reference.py [DATA] [--trajectory RUN/trajectory.tum ...] [--gaps 1,10,30] [--stride 5]
                                  [--frames N] [--pair I:J ...] [--set section.key=value ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"


def relative_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation in mm, rotation in degrees) of inv(T_a) · T_b."""
    from ti_fusion.geometry import invert, rotation_angle_deg

    E = invert(T_a) @ T_b
    return float(np.linalg.norm(E[:3, 3]) * 1e3), rotation_angle_deg(E[:3, :3])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA) if DEFAULT_DATA.is_dir() else "")
    parser.add_argument("--trajectory", action="append", default=[],
                        help="a TUM trajectory of the same frames (e.g. a run's trajectory.tum); repeatable")
    parser.add_argument("--pair", action="append", default=[], metavar="I:J",
                        help="only this pair of frames: every relative pose as an ICP start (repeatable)")
    parser.add_argument("--gaps", default="1,10,30", help="frame gaps of the pairs (comma separated)")
    parser.add_argument("--stride", type=int, default=5, help="first frames of the pairs every N frames (gap 1: all)")
    parser.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    parser.add_argument("--min-inlier-ratio", type=float, default=0.5)
    parser.add_argument("--jump-mm", type=float, default=1.0)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args()

    from ti_fusion.backend import current_backend, init_backend
    from ti_fusion.config import load_config
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.trajectory import read_tum

    cfg = load_config(None, args.set)
    cfg.dataset.path, cfg.dataset.stop = args.data, args.frames
    init_backend("cpu")
    from ti_fusion.geometry import invert
    from ti_fusion.tracking.icp import ICP
    from ti_fusion.kernels.icp import PointToPlane, unpack_sums
    from ti_fusion.tracking.terms.point_to_plane import point_to_plane
    from ti_fusion.kernels.pyramid import FramePyramid

    dataset = open_dataset(cfg.dataset, cfg.synth)
    n = len(dataset)
    reference = [dataset[i].gt_pose for i in range(n)]
    if any(T is None for T in reference):
        print("the dataset has no reference poses", file=sys.stderr)
        return 1
    estimates = []
    for path in args.trajectory:
        stamps, poses = read_tum(path)
        by_stamp = {round(float(t), 6): T for t, T in zip(stamps, poses)}
        estimates.append([by_stamp.get(round(float(dataset[i].timestamp), 6)) for i in range(n)])
    estimate = estimates[0] if estimates else None

    K, icp_cfg = dataset.intrinsics, cfg.icp
    level = cfg.frame_input_level(K.width)
    pyramids = [FramePyramid(cfg.pyramid, K.height, K.width, len(icp_cfg.iterations), input_level=level)
                for _ in range(2)]
    icp = ICP(icp_cfg)
    backend = current_backend()
    kernels = PointToPlane(pyramids[0].shapes[0][0] * pyramids[0].shapes[0][1], backend.has_f64)

    def compute(m, i):
        frame = dataset[i]
        m.compute(frame.depth, frame.intrinsics)

    def system(T, a, b) -> dict:
        """The point-to-plane sums of a at pose T against b: correspondences within 5 cm, no robust weight."""
        return unpack_sums(kernels.reduce(a.vertex[0], a.normal[0], b.vertex[0], b.normal[0], T,
                                          b.intrinsics[0].as_tuple(), 0.05, icp_cfg.normal_threshold_deg,
                                          [point_to_plane()]))

    def residual_mm(T, a, b) -> float:
        s = system(T, a, b)
        return float(np.sqrt(s["r2"] / s["inliers"]) * 1e3) if s["inliers"] else float("nan")

    print(f"{dataset.describe()['name']}: {n} frames, pairs aligned at {pyramids[0].width}x{pyramids[0].height}")
    if args.pair:
        for pair in args.pair:
            i, j = (int(x) for x in pair.split(":"))
            compute(pyramids[0], i)
            compute(pyramids[1], j)
            starts = {"reference": invert(reference[j]) @ reference[i]}
            for path, est in zip(args.trajectory, estimates):
                if est[i] is not None and est[j] is not None:
                    starts[path] = invert(est[j]) @ est[i]
            _pair_report(i, j, starts, icp, pyramids, lambda T: residual_mm(T, *pyramids),
                         lambda T: system(T, *pyramids))
        return 0
    print(f"{'gap':>4} {'pairs':>6}  reference vs ICP (mm, deg RMS)" + ("   estimate vs ICP" if estimate else ""))
    jumps = []
    for gap in (int(g) for g in args.gaps.split(",")):
        ref_err, est_err = [], []
        for i in range(0, n - gap, 1 if gap == 1 else args.stride):
            j = i + gap
            compute(pyramids[0], i)
            compute(pyramids[1], j)
            T_ref = invert(reference[j]) @ reference[i]
            result = icp.align(pyramids[0], pyramids[1], init=T_ref)
            if result.failure or result.inlier_ratio < args.min_inlier_ratio:
                continue
            ref_err.append(relative_error(T_ref, result.pose))
            if estimate is not None and estimate[i] is not None and estimate[j] is not None:
                est_err.append(relative_error(invert(estimate[j]) @ estimate[i], result.pose))
            if gap == 1:
                at_ref, at_icp = residual_mm(T_ref, *pyramids), residual_mm(result.pose, *pyramids)
                if at_ref - at_icp > args.jump_mm:
                    jumps.append((i, j, at_ref, at_icp, ref_err[-1][0]))
        line = f"{gap:>4} {len(ref_err):>6}  {_rms(ref_err)}"
        print(line + (f"   {_rms(est_err)}" if est_err else ""))
    if jumps:
        print("reference inconsistent with the depth (residual at its pose vs after ICP, and its offset):")
        for i, j, at_ref, at_icp, offset in jumps:
            print(f"  {i:>5} -> {j:<5} {at_ref:6.2f} vs {at_icp:5.2f} mm residual, {offset:6.1f} mm off")
    return 0


def _pair_report(i: int, j: int, starts: dict, icp, pyramids, residual_mm, system) -> None:
    """Frames i and j: each relative pose (frame i's camera into frame j's) as an ICP start; every pose
    against the converged alignment with the lowest residual, the independent estimate: the offset, and how
    far it moves the surfaces along their normals (RMS over the alignment's inliers, δᵀAᵀAδ / n with AᵀA of
    the alignment: what depth sees of the offset), and that in the direction depth sees least."""
    from ti_fusion.geometry import invert, se3_log

    print(f"pair {i} -> {j}")
    results = {name: icp.align(pyramids[0], pyramids[1], init=T) for name, T in starts.items()}
    for name, r in results.items():
        print(f"  ICP from {name}: {r.failure or 'ok'}, inlier ratio {r.inlier_ratio:.3f}, "
              f"residual {residual_mm(r.pose):.2f} mm (5 cm gate, unweighted)")
    good = {k: r for k, r in results.items() if not r.failure}
    if not good:
        print("  no start converged")
        return
    best_name = min(good, key=lambda k: residual_mm(good[k].pose))
    best = good[best_name].pose
    for name, r in good.items():
        print(f"  ICP from {name} vs ICP from {best_name}: %.1f mm, %.3f deg" % relative_error(r.pose, best))
    at_best = system(best)
    AtA, n = at_best["AtA"], max(at_best["inliers"], 1)
    values, vectors = np.linalg.eigh(AtA)
    print(f"  AᵀA's weakest direction (ω, v): {np.round(vectors[:, 0], 3)}, "
          f"{np.sqrt(values[0] / n):.3f} mm RMS along the normals per mm or mrad, the strongest "
          f"{np.sqrt(values[-1] / n):.3f}")
    for name, T in starts.items():
        mm, deg = relative_error(T, best)
        d = se3_log(T @ invert(best))  # ICP's update is on the left: T = exp(d) · best
        seen = float(np.sqrt(d @ AtA @ d / n) * 1e3)
        weak = float(abs(vectors[:, 0] @ d) * 1e3)
        print(f"  {name}: {mm:.1f} mm, {deg:.3f} deg from ICP; moves the surfaces {seen:.2f} mm RMS along their "
              f"normals; {weak:.1f} mm/mrad of it in the weakest direction; residual at its pose {residual_mm(T):.2f} mm")


def _rms(errors: list[tuple[float, float]]) -> str:
    if not errors:
        return "-"
    e = np.asarray(errors)
    return f"{np.sqrt(np.mean(e[:, 0] ** 2)):6.2f} mm {np.sqrt(np.mean(e[:, 1] ** 2)):5.2f} deg"


if __name__ == "__main__":
    sys.exit(main())
