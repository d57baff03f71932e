"""map.ply: the surfel map as a point cloud with normals and colours, and each surfel's confidence and radius
(``ti-fusion mesh map.ply`` keeps the confirmed ones)."""

from __future__ import annotations

from ti_fusion.sinks.base import Run, Sink


class MapSink(Sink):
    name = "map"
    commands = ("slam", "fuse")

    def finish(self, run: Run) -> dict:
        path = run.out.file("map.ply")
        run.in_background(run.step.mapper.ply_writer(path))  # the map read here, the file written beside
        return {"ply": str(path)}
