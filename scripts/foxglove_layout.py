"""Writes docs/foxglove-layout.json: a layout for ti-fusion's logs and live runs that Foxglove and Lichtblick
both import.

    .venv/bin/python scripts/foxglove_layout.py [OUT.json]

The classic layout form (``configById``, ``layout``, ``globalVariables``, ``userNodes``, ``playbackConfig``),
the one Foxglove Studio, Lichtblick and current Foxglove all import; the Foxglove SDK's newer ``{version,
content}`` form fails to import in Studio ("Cannot read properties of undefined (reading 'speed')") and in
Lichtblick. Only panel types and settings that exist in both clients: ``3D``; ``ImageViewPanel``, the image
panel of Studio, which Lichtblick and current Foxglove turn into their ``Image`` panel on import; ``Plot``
with one x path per plot (``xAxisPath``), since a per-series x path exists in current Foxglove only.

The 3D panel in ``world``: the map in its own colours (``colorMode`` "rgba-fields" with a ``colorField``
named: without one the client picks a colour field itself and colours the map by x with a colour map), the
estimated and ground-truth poses, the camera frustum with the colour image in it, and the loop edges. Below
it the colour and depth images; on the right plots of the stage milliseconds, the ICP inlier ratio (with, for a
session against a saved map, whether it has found itself in it), the surfel count, and each trajectory in the
world's x-y plane (seen from above where z is up, as in the synthetic scenes).

To add a panel: make it with ``panel(TYPE, NAME, CONFIG)`` and put the returned id into the tree in
``layout()``; a 3D topic is one more entry of ``SCENE_TOPICS``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

OUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
EST, GT = "#4e98e2", "#f5a623"  # estimate blue, ground truth orange, in the 3D panel and the plots
TITLE = "foxglovePanelTitle"  # the panel title's config key in both clients

# The 3D panel's topics and their settings (the keys of the clients' renderers).
SCENE_TOPICS = {
    # colorField: any field name; it keeps the client from choosing one and switching to a colour map
    "/map/points": {"visible": True, "colorMode": "rgba-fields", "colorField": "red", "pointSize": 2,
                    "pointShape": "circle", "decayTime": 0},
    "/camera/pose": {"visible": True, "type": "arrow", "color": EST},
    "/gt/pose": {"visible": True, "type": "arrow", "color": GT},
    # the colour image in its camera: the client draws the frustum from the calibration
    "/camera/color": {"visible": True, "cameraInfoTopic": "/camera/calibration", "distance": 0.3},
    "/camera/calibration": {"visible": True, "distance": 0.3, "color": EST},
    # loop edges (slam.loop_closure), in the messages' own colours: the loops applied (green) shown, the
    # candidates not applied (red, hundreds a lap) hidden: the client draws them over the map and the loops
    "/loop_closures": {"visible": True},
    "/loop_closures/refused": {"visible": False},
    # slam --mesh: the mesh of the map at the end of the run, its own vertex colours
    "/map/mesh": {"visible": True},
    # the trajectory as written at the end (loop closure's corrections included), as a line
    "/trajectory": {"visible": True, "type": "line", "lineWidth": 0.02, "gradient": [EST, EST]},
}
# Looking down at the scene from 8 m, 45 degrees off vertical (every key: the clients replace the whole state).
CAMERA = {"distance": 8, "perspective": True, "phi": 45, "thetaOffset": 45, "target": [0, 0, 0],
          "targetOffset": [0, 0, 0], "targetOrientation": [0, 0, 0, 1], "fovy": 45, "near": 0.01, "far": 5000}


class Layout:
    """The panels' configs by id, built up by ``panel``."""

    def __init__(self):
        self.configs: dict[str, dict] = {}

    def panel(self, kind: str, name: str, config: dict) -> str:
        """A panel of type ``kind``; its id is ``kind!name`` (the clients read the type from the id)."""
        panel_id = f"{kind}!{name}"
        if panel_id in self.configs:
            raise ValueError(f"two panels named {panel_id}")
        self.configs[panel_id] = config
        return panel_id

    def plot(self, name: str, title: str, *series: tuple[str, str], x_path: str | None = None,
             color: str | None = None) -> str:
        """A plot of message paths over the log's time, or against ``x_path`` (each message's values paired
        with the y path's by their order)."""
        config = {TITLE: title, "paths": [
            {"value": value, "label": label, "enabled": True, "timestampMethod": "receiveTime",
             **({"color": color} if color else {})} for value, label in series],
            "showLegend": True, "legendDisplay": "floating", "showPlotValuesInLegend": False,
            "showXAxisLabels": True, "showYAxisLabels": True, "isSynced": x_path is None,
            "xAxisVal": "timestamp", "sidebarDimension": 240}
        if x_path is not None:
            config.update(xAxisVal="custom", xAxisPath={"value": x_path, "enabled": True})
        return self.panel("Plot", name, config)


def split(direction: str, *items: tuple[float, str | dict]) -> str | dict:
    """Panels (ids) or splits side by side ("row") or stacked ("column"), each with its share of the space:
    the clients' binary splits, nested."""
    (share, first), rest = items[0], items[1:]
    if not rest:
        return first
    return {"first": first, "second": split(direction, *rest), "direction": direction,
            "splitPercentage": round(100 * share / sum(s for s, _ in items), 2)}


def layout() -> dict:
    ui = Layout()
    scene = ui.panel("3D", "map", {
        TITLE: "map and poses", "followTf": "world", "followMode": "follow-none", "cameraState": CAMERA,
        "scene": {}, "transforms": {}, "topics": SCENE_TOPICS, "layers": {}})
    color = ui.panel("ImageViewPanel", "color", {TITLE: "color", "cameraTopic": "/camera/color",
                                                 "enabledMarkerTopics": [], "mode": "fit", "synchronize": False})
    depth = ui.panel("ImageViewPanel", "depth", {TITLE: "depth (mm, 0 to 5000)", "cameraTopic": "/camera/depth",
                                                 "enabledMarkerTopics": [], "mode": "fit", "synchronize": False,
                                                 "minValue": 0, "maxValue": 5000})
    # Frames that compiled kernels (the first ones take seconds) are left out: on their scale the rest lie flat.
    steady = "/slam/stats{first_launch_ms==0}"
    stages = ui.plot("ms", "ms per frame (frames that compiled kernels left out)", (f"{steady}.ms.track", "track"),
                     (f"{steady}.ms.fuse", "fuse"), (f"{steady}.ms.pyramid", "pyramid"), (f"{steady}.ms.log", "log"))
    # a session against a saved map (--map): 0 until it found itself in the map, then 1
    inliers = ui.plot("inliers", "ICP inlier ratio; localised in a saved map (0/1)",
                      ("/slam/stats.icp.inlier_ratio", "inlier ratio"), ("/slam/stats.localised", "localised (--map)"))
    surfels = ui.plot("surfels", "surfels", ("/slam/stats.surfels", "surfels"))
    estimate = ui.plot("trajectory-estimate", "estimate, y against x (m)",
                       ("/camera/pose.pose.position.y", "estimate"), x_path="/camera/pose.pose.position.x", color=EST)
    truth = ui.plot("trajectory-truth", "ground truth, y against x (m)",
                    ("/gt/pose.pose.position.y", "ground truth"), x_path="/gt/pose.pose.position.x",
                    color=GT)
    tree = split("row",
                 (3, split("column", (2, scene), (1, split("row", (1, color), (1, depth))))),
                 (2, split("column", (1, stages), (1, inliers), (1, surfels),
                           (1, split("row", (1, estimate), (1, truth))))))
    return {"configById": ui.configs, "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1.0},
            "layout": tree}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Write the Foxglove/Lichtblick layout for ti-fusion's logs.")
    parser.add_argument("out", nargs="?", type=Path, default=OUT,
                        help="the layout file (default: docs/foxglove-layout.json)")
    out = parser.parse_args(argv).out
    try:
        out.write_text(json.dumps(layout(), indent=1) + "\n")
    except OSError as exc:
        parser.exit(2, f"foxglove_layout.py: cannot write {out}: {exc.strerror or exc}\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
