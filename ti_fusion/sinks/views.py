"""map_color.png and map_normals.png: the surfel map seen from behind the first posed camera
(``fusion.view_back`` metres)."""

from __future__ import annotations

import logging

from ti_fusion.sinks.base import Run, Sink

log = logging.getLogger(__name__)


class ViewsSink(Sink):
    name = "views"
    commands = ("slam", "fuse")

    def finish(self, run: Run) -> dict:
        from ti_fusion.mapping.views import save_views, view_pose  # OpenCV: only once there is a view to write

        first = next((r for r in run.results if r.pose is not None), None)
        if first is None:
            log.warning("no frame got a pose: the map is empty, and there are no views of it")
            return {}
        views = save_views(run.step.mapper, view_pose(first.pose, run.config.fusion.view_back), run.out.path,
                           later=run.in_background)  # rendered here, encoded and written beside
        return {"views": {k: str(v) for k, v in views.items()}}

