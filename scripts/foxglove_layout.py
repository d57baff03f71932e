"""Writes docs/foxglove-layout.json: a Foxglove layout for ti-fusion's logs and live runs.

    .venv/bin/python scripts/foxglove_layout.py [OUT.json]

Built with the Foxglove SDK's typed layout classes (``foxglove.layouts``), so that its panel settings are
the ones Foxglove reads: a 3D panel in ``world`` with the map coloured by its RGBA fields, the estimated
and ground-truth poses, the camera frustum and the loop edges; the colour and depth images; plots of the
track and fuse milliseconds, the ICP inlier ratio, the surfel count, and both trajectories seen from above.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import foxglove.layouts as fl

OUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
EST, GT = "#4e98e2", "#f5a623"  # estimate blue, ground truth orange, in the 3D panel and the plots


def layout() -> fl.Layout:
    scene = fl.ThreeDeePanel(title="map and poses", config=fl.ThreeDeeConfig(
        follow_tf="world", fixed_frame="world", follow_mode="follow-none",
        topics={
            "/map/points": fl.BaseRendererPointCloudTopicSettings(visible=True, color_mode="rgba-fields",
                                                                  point_size=2, decay_time=0),
            "/camera/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color=EST),
            "/gt/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color=GT),
            # the colour image in its camera: Foxglove draws the frustum from the calibration
            "/camera/color": fl.BaseRendererImageTopicSettings(visible=True, camera_info_topic="/camera/calibration",
                                                               distance=0.3),
            "/camera/calibration": fl.BaseRendererCameraTopicSettings(visible=True, distance=0.3, color=EST),
            # loop edges (slam.loop_closure): the colours are the message's own (accepted green, rejected red)
            "/loop_closures": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        }))
    colour = fl.ImagePanel(title="colour", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic="/camera/color", calibration_topic="/camera/calibration")))
    depth = fl.ImagePanel(title="depth (mm)", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic="/camera/depth", calibration_topic="/camera/calibration", color_mode="colormap",
        color_map="turbo", min_value=0, max_value=5000)))

    def plot(title: str, *series: tuple[str, str], y_label: str) -> fl.PlotPanel:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=value, label=label, enabled=True) for value, label in series],
            show_legend=True, legend_display="floating", x_axis_val="timestamp", y_axis_label=y_label))

    stages = plot("ms per frame", ("/slam/stats.ms.track", "track"), ("/slam/stats.ms.fuse", "fuse"),
                  ("/slam/stats.ms.maps", "maps"), ("/slam/stats.ms.log", "log"), y_label="ms")
    inliers = plot("ICP inlier ratio", ("/slam/stats.icp.inlier_ratio", "inlier ratio"), y_label="0 to 1")
    surfels = plot("surfels", ("/slam/stats.surfels", "surfels"), y_label="surfels")
    trajectory = fl.PlotPanel(title="trajectory from above (x, y in metres)", config=fl.PlotConfig(
        paths=[fl.PlotSeries(value="/camera/pose.pose.position.y", x_value_path="/camera/pose.pose.position.x",
                             label="estimate", color=EST, enabled=True),
               fl.PlotSeries(value="/gt/pose.pose.position.y", x_value_path="/gt/pose.pose.position.x",
                             label="ground truth", color=GT, enabled=True)],
        x_axis_val="custom", show_legend=True, legend_display="floating", x_axis_label="x (m)",
        y_axis_label="y (m)", axis_scales_mode="lockedScales"))

    def column(*panels, proportions=None) -> fl.SplitContainer:
        proportions = proportions or [1] * len(panels)
        return fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=p, content=c) for p, c in zip(proportions, panels)])

    images = fl.SplitContainer(direction="row", items=[fl.SplitItem(content=colour), fl.SplitItem(content=depth)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=column(scene, images, proportions=[2, 1])),
        fl.SplitItem(proportion=2, content=column(stages, inliers, surfels, trajectory)),
    ]))


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    out.write_text(json.dumps(json.loads(layout().to_json()), indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
