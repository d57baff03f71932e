"""cloud.ply (``ti-fusion vo``): the accepted frames' depth joined into one coloured cloud on a
``vo.voxel_size`` grid."""

from __future__ import annotations

from ti_fusion.io.ply import write_ply
from ti_fusion.sinks.base import Run, Sink


class CloudSink(Sink):
    name = "cloud"
    commands = ("vo",)

    def finish(self, run: Run) -> dict:
        xyz, rgb = run.step.cloud.points()
        write_ply(run.out.file("cloud.ply"), xyz, None, rgb)
        return {"cloud_points": int(len(xyz))}
