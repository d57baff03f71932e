"""Per-step translation errors and each frame's weakest geometric direction, for telling the slide of a sequence
(docs/TRACKING.md, real cameras): DenseSLAM driven directly on DATA (or the synthetic scene), one line a frame.

    python scripts/slide_steps.py ../shared/data/tum-fr3-cabinet-keyframes --set slam.slide_ratio=0
    python scripts/slide_steps.py --set synth.scene=cabinet --set synth.frames=29 --set synth.exposure=0.035

Prints the step errors (mm), λmin/λmax of the winning alignment's geometric AᵀA (×10⁻³), the start that won
(m motion, l last, s slide, ...), then ATE, the step percentiles and the ratio's median.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from ti_fusion.config import load_config
    from ti_fusion.errors import TiFusionError
    from ti_fusion.evaluation.metrics import ate_errors
    from ti_fusion.geometry import invert, pose_error
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.slam.dense import DenseSLAM

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default="", help="a dataset folder; none = the synthetic scene")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        cfg = load_config(None, args.set)
        cfg.dataset.path = args.data
        dataset = open_dataset(cfg.dataset, cfg.synth)
    except TiFusionError as e:  # one line naming the option or file
        print(f"slide_steps.py: {e}", file=sys.stderr)
        return 2
    slam = DenseSLAM(cfg, dataset.intrinsics)
    frames = list(dataset)
    results = [slam.register_frame(f) for f in frames]
    steps = [pose_error(invert(a.pose) @ b.pose, invert(f.gt_pose) @ g.gt_pose)[1] * 1e3
             for a, b, f, g in zip(results, results[1:], frames, frames[1:])]
    ratios = [(((r.icp.degeneracy or {}).get("weakest") or {}).get("ratio", np.nan) if r.icp else np.nan) * 1e3
              for r in results[1:]]
    ate = np.sqrt(np.mean(ate_errors(np.array([r.pose for r in results]),
                                     np.array([f.gt_pose for f in frames]))[0] ** 2)) * 100
    print(f"{args.data or 'synthetic ' + cfg.synth.scene}, {len(frames)} frames, {' '.join(args.set)} "
          f"({time.perf_counter() - start:.0f} s)")
    print("steps mm:  " + " ".join(f"{s:.0f}" for s in steps))
    print("ratio e-3: " + " ".join(f"{r:.1f}" for r in ratios))
    print("start:     " + " ".join((r.hypothesis or "-")[0] for r in results[1:]))
    print(f"lost {sum(r.lost for r in results)}, ATE {ate:.2f} cm, step p50/p90/max "
          f"{np.percentile(steps, 50):.1f}/{np.percentile(steps, 90):.1f}/{max(steps):.1f} mm, "
          f"ratio median {np.nanmedian(ratios):.2f}e-3")
    return 0


if __name__ == "__main__":
    sys.exit(main())
