"""Feeding ti-fusion frames from one's own code, one at a time, as a robot's driver hands them over.

    python scripts/example_stream.py [--frames 60] [--out logs/example-stream] [--arch cpu]

The "camera" here is the synthetic renderer, giving millimetre depth (uint16, as a RealSense does) and
RGB colour; replace ``camera()`` with your own source. Each frame goes through ``rgbd_frame`` (arrays to a
checked ``Frame`` in metres) into ``DenseSLAM.register_frame``, which returns the pose and the tracking
status; poses go to an MCAP log as they come (open it in Foxglove, or ``ti-fusion inspect``), and the map
and the trajectory are saved at the end.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ti_fusion.backend import init_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config, SynthConfig
from ti_fusion.io.datasets import rgbd_frame
from ti_fusion.io.mcap_log import RunLogger
from ti_fusion.io.trajectory import write_tum
from ti_fusion.slam.dense import DenseSLAM


def camera(frames: int):
    """(timestamp s, depth uint16 mm, colour uint8 RGB, ground-truth pose) per frame: a stand-in for a driver."""
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig(frames=frames, width=320, height=240, fx=262.5))
    for i in range(frames):
        depth, rgb = seq.frame(i)
        yield seq.timestamps[i], np.round(depth * 1000).astype(np.uint16), rgb, seq.poses[i]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--out", default="logs/example-stream")
    parser.add_argument("--arch", default="cpu")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    init_backend(args.arch)
    K = Intrinsics(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
    slam = DenseSLAM(Config(), K)
    stamps, poses, errors = [], [], []
    with RunLogger(out / "log.mcap") as log:
        for i, (t, depth_mm, rgb, gt) in enumerate(camera(args.frames)):
            frame = rgbd_frame(depth_mm, K, depth_scale=1000, color=rgb, timestamp=t, index=i, gt_pose=gt)
            result = slam.register_frame(frame)  # track against the map, then fuse
            if result.pose is None:  # no map yet (the first frames had too little depth)
                continue
            log.log_pose(t, result.pose, gt)
            log.log_stats(t, {"frame": i, "status": result.status, "surfels": slam.surfels})
            stamps.append(t)
            poses.append(result.pose)
            errors.append(np.linalg.norm(result.pose[:3, 3] - gt[:3, 3]))
    slam.mapper.export_ply(out / "map.ply")
    write_tum(out / "trajectory.tum", stamps, np.stack(poses))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    print(f"{len(poses)} frames, {slam.surfels} surfels, position error RMS {rms * 100:.2f} cm; wrote "
          f"{out}/log.mcap, map.ply, trajectory.tum")
    return {"frames": len(poses), "position_rms_m": rms, "surfels": slam.surfels}


if __name__ == "__main__":
    main()
