"""trajectory.tum: the camera-to-world pose of every frame done that got one, at its current estimate
(after any loop closure), written whatever ended the run. A session that extends a saved map (``slam --map``,
not ``--localize``) also writes map_trajectory.tum: every posed frame of the map, the earlier sessions' as this
run's loops moved them, then its own, in the map's frame (docs/MAPS.md)."""

from __future__ import annotations

import numpy as np

from ti_fusion.io.trajectory import write_tum
from ti_fusion.sinks.base import Run, Sink


class TrajectorySink(Sink):
    name = "trajectory"
    commands = ("slam", "vo", "fuse")
    on_stop = True  # an interrupted run keeps the trajectory so far

    def finish(self, run: Run) -> dict:
        stamps, poses = run.trajectory()
        if stamps:
            write_tum(run.out.file("trajectory.tum"), stamps, np.stack(poses))
        slam = getattr(run.step, "slam", None)
        if slam is None or slam.loaded_map is None or run.config.map.localize:
            return {}
        stamps, poses = slam.map_trajectory()
        if len(stamps):
            write_tum(run.out.file("map_trajectory.tum"), stamps, poses)
        return {"map_trajectory": {"frames": len(stamps), "earlier_sessions_frames": len(slam.loaded_map.trajectory)}}
