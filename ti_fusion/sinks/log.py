"""log.mcap (and with ``--live`` the same messages served to Foxglove): a map the run starts from (a saved
one) on the map topic at the first frame; per frame the calibration when it changes, the pose, the step's stats, loop edges, depth and colour every ``log.depth_every`` frames and the
map every ``log.map_every``; at the end the map and the trajectory (docs/LOGS.md)."""

from __future__ import annotations

import copy

from ti_fusion import __version__
from ti_fusion.frontend import CLOCK
from ti_fusion.io.mcap_log import RunLogger, software_versions
from ti_fusion.sinks.base import Run, Sink, Step
from ti_fusion.timing import Stopwatch

# The log's record of a run without a Taichi backend (feature odometry runs in OpenCV).
NO_BACKEND = {"arch": "none (OpenCV on the CPU)"}


def stats_schema(step: Step) -> dict:
    """The step's stats schema with the two stages the pipeline times itself."""
    schema = copy.deepcopy(step.stats_schema)
    schema["properties"]["ms"]["properties"].update(
        load={"type": "number", "description": "reading the frame from the dataset, milliseconds"},
        log={"type": "number", "description": "logging the frame's poses, images and map (to the file and "
                                              "any live view), milliseconds"})
    schema["properties"]["first_launch_ms"] = {
        "type": "number", "description": "milliseconds of this frame spent in kernels' first launches (compiling "
                                         "them or loading them from the cache; 0 on a frame that ran compiled "
                                         "kernels only)"}
    return schema


class LogSink(Sink):
    """The run's MCAP log; the last sink, so that the others can add to it (``run.log``) before it closes."""

    name = "log"
    commands = ("slam", "vo", "fuse")
    on_stop = True  # an interrupted run keeps a finalised log

    def __init__(self):
        self._calibration = None  # the intrinsics last logged on /camera/calibration
        self._loaded = None  # the map a run started from (a saved map, --map), logged at the first frame's time

    def start(self, run: Run) -> None:
        run.log = RunLogger(run.out.file("log.mcap"), metadata(run), live=run.live)
        run.log.declare_json(run.step.stats_channel, stats_schema(run.step))
        self._loaded = run.step.map_points(run.config.log.map_max_points)  # None: the run starts with no map

    def frame(self, run: Run, frame, result) -> None:
        log, cfg = run.log, run.config.log
        with Stopwatch(result.ms, "log"):
            if self._loaded is not None:  # on the map topic before anything of this run
                log.log_points(frame.timestamp, *self._loaded, max_points=run.config.log.map_max_points)
                self._loaded = None
            if frame.intrinsics != self._calibration:
                log.log_calibration(frame.timestamp, frame.intrinsics)
                self._calibration = frame.intrinsics
            if result.pose is not None:
                log.log_pose(frame.timestamp, result.pose, frame.gt_pose)
            if result.loop is not None and result.loop.candidates:  # the loop edges so far, at current poses
                log.log_loop_edges(frame.timestamp, run.step.loop_edges())
            i = len(run.results)  # this frame's place in the run: the frames done before it
            if cfg.depth_every > 0 and i % cfg.depth_every == 0:
                log.log_depth(frame.timestamp, frame.depth)
                if frame.color is not None:
                    log.log_image(frame.timestamp, frame.color)
            to_file = cfg.map_every > 0 and i > 0 and i % cfg.map_every == 0
            to_live = run.live is not None and run.live.map_due()
            if to_file or to_live:
                self._log_map(run, frame.timestamp, to_file, to_live)
        run.timer.add("log", result.ms["log"])
        stats = run.step.stats(result)
        # kernels compiled (or loaded) in this frame: the layout's ms plot leaves such frames out
        stats["first_launch_ms"] = round((CLOCK.seconds - run.frame_clock) * 1e3, 1)
        log.log_stats(frame.timestamp, stats, channel=run.step.stats_channel)

    def finish(self, run: Run) -> dict:
        try:
            if run.results:
                t = run.results[-1].timestamp
                self._log_map(run, t)
                _, poses = run.trajectory()
                if run.step.estimates_poses and poses:
                    run.log.log_trajectory(t, poses)
        finally:
            run.log.close()
        return {}

    def _log_map(self, run: Run, t: float, file: bool = True, live: bool = True) -> None:
        max_points = run.config.log.map_max_points if file else min(run.config.log.map_max_points,
                                                                     run.live.max_points)
        points = run.step.map_points(max_points)
        if points is not None:
            run.log.log_points(t, *points, max_points=run.config.log.map_max_points, file=file, live=live)


def metadata(run: Run) -> dict:
    backend = NO_BACKEND if run.backend is None else {
        "arch": run.backend.arch, "requested": run.backend.requested, "reason": run.backend.reason}
    return {"config": run.config.to_dict(), "dataset": run.dataset.describe(), "backend": backend,
            "versions": {**software_versions(), "ti-fusion": __version__}}
