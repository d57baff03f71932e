"""trajectory.tum: the camera-to-world pose of every frame done that got one, at its current estimate
(after any loop closure), written whatever ended the run."""

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
        return {}
