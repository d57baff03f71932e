"""The run of a per-frame command (``slam``, ``vo``, ``fuse``): the loop over a dataset and all around it.

    summary = Pipeline(dataset, config, run_dir, step, backend).run()

The pipeline owns the loop over the frames, the progress bar, the stage timing, the MCAP log,
``trajectory.tum``, the evaluation against ground truth and ``trajectory.png``. A command gives only its
``step`` (see ``Step``): ``register_frame`` does one frame, ``outputs`` writes the command's own files.
Whatever ends the loop (its normal end, bad input in frame 300, Ctrl-C), the frames done so far leave a
finalised ``log.mcap`` and a ``trajectory.tum``.
"""

from __future__ import annotations

import copy
import logging
from typing import Any, Protocol

import numpy as np

from ti_fusion import __version__
from ti_fusion.backend import BackendInfo
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.evaluation.metrics import held_trajectory, tracked_ate, trajectory_metrics
from ti_fusion.frontend import CLOCK
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.mcap_log import RunLogger, software_versions
from ti_fusion.io.outputs import RunDir, progress
from ti_fusion.io.prefetch import Prefetcher
from ti_fusion.io.datasets.realsense_live import StreamEnded
from ti_fusion.io.registration import ColorRegistrar
from ti_fusion.io.trajectory import write_tum
from ti_fusion.slam.checks import check_first_frames
from ti_fusion.timing import StageTimer, Stopwatch, process_age_s

# The log's record of a run without a Taichi backend (feature odometry runs in OpenCV).
NO_BACKEND = {"arch": "none (OpenCV on the CPU)"}
# Frames read ahead of the one being processed, in reader processes or a thread (ti_fusion.io.prefetch); at least
# one per reader.
READ_AHEAD = 3


class Step(Protocol):
    """What a command gives the pipeline: the work on one frame, and the command's own outputs."""

    name: str                 # the command: the progress bar's label
    stats_channel: str        # the log channel of the per-frame stats, e.g. "/slam/stats"
    stats_schema: dict        # the JSON Schema of its messages, every field (the pipeline adds ms.load, ms.log)
    stages: tuple[str, ...]   # the keys of ``result.ms`` that fps_processing counts (with the pipeline's "log")
    warmup_frames: int        # the first frames, which compile kernels: left out of fps_processing and ms_per_stage
    estimates_poses: bool     # poses are estimates: evaluated against ground truth and plotted

    def register_frame(self, frame: Frame) -> Any:
        """One frame. The result has ``timestamp``, ``pose`` (camera-to-world, None when the frame got no
        pose: it is then left out of trajectory.tum) and ``ms`` (stage → milliseconds, a dict that the
        pipeline adds "log" and "load" to)."""

    def stats(self, result: Any) -> dict:
        """The frame's message on ``stats_channel``."""

    def map_points(self, max_points: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(positions, uint8 RGB) of the map so far for /map/points (``max_points`` is a hint), or None."""

    def current_poses(self) -> dict[int, np.ndarray]:
        """Frame index → the current pose of each frame whose pose moved or may have moved since its result
        (loop closure); the pipeline takes them into the results once, before it writes any output."""

    def plot_title(self, run: Pipeline) -> str:
        """The title of trajectory.png."""

    def outputs(self, run: Pipeline) -> dict:
        """After the loop: write the command's own files; return its summary fields."""


class Pipeline:
    """Runs a ``Step`` over every frame of a dataset and writes the run's outputs into ``run_dir``."""

    def __init__(self, dataset: Dataset, config: Config, run_dir: RunDir, step: Step,
                 backend: BackendInfo | None = None, show_progress: bool = True, live=None):
        self.dataset = dataset
        self.live = live  # a LiveServer (ti_fusion.io.live) that the log feeds too, or None
        self.config = config
        self.out = run_dir
        self.step = step
        self.backend = backend
        self.show_progress = show_progress and config.log.progress
        self.timer = StageTimer()
        self.results: list = []  # the step's result of every frame done
        self.gt: list[np.ndarray | None] = []  # and the frame's ground-truth pose
        self.first_frames_s: list[float] = []  # the process's age when each of the first two frames was done
        self._calibration = None  # the intrinsics last logged on /camera/calibration
        self.read_workers = 0  # processes (or the thread) that read the frames ahead (0: the loop's own thread)
        self.read_mode = "inline"  # how: "processes", "thread" or "inline" (ti_fusion.io.prefetch.read_mode)
        self._ran = False  # one run per pipeline: a second would mix two runs' frames in one folder

    def run(self) -> dict:
        if self._ran:
            raise InputError(None, "this pipeline has run already: one run per Pipeline (its results, log and "
                                   "output folder are that run's); make a new one, with a new RunDir, for another run")
        self._ran = True
        if len(self.dataset) == 0:
            raise InputError(self.dataset.root, "no frames selected (check --start/--stop/--frames)")
        check_first_frames(self.dataset, self.config)  # what can be refused before the first frame is, here
        run_watch = Stopwatch()
        error = None
        with RunLogger(self.out.file("log.mcap"), self._metadata(), live=self.live) as log:
            log.declare_json(self.step.stats_channel, self._stats_schema())
            try:
                self._loop(log)
            except Exception as exc:  # bad input in frame 300: the frames done so far still give their outputs
                error = exc
            finally:  # whatever ended the loop: keep the trajectory so far, and the map in the log
                self._take_current_poses()
                poses = self._write_trajectory()
                if self.results:
                    self._log_map(log, self.results[-1].timestamp)
                    if self.step.estimates_poses and poses:
                        log.log_trajectory(self.results[-1].timestamp, poses)
                    if hasattr(self.step, "log_end"):  # slam --mesh: the mesh, while the log is open
                        self.step.log_end(log, self.results[-1].timestamp)
        if error is not None:
            self._outputs_after_error(error, run_watch.ms / 1e3)
            raise error
        nothing = self._nothing_done()
        if nothing:
            raise InputError(self.dataset.root, nothing)
        wall = run_watch.ms / 1e3
        with self.timer.stage("export"):
            summary = self._summary(wall)
            summary.update(self._evaluate())
            summary.update(self.step.outputs(self))
        summary["ms_per_stage"] = self.timer.summary(skip_first=self.step.warmup_frames)
        summary["process_s"] = process_age_s()  # from the process's start: interpreter, imports, compiling
        return summary

    def _take_current_poses(self) -> None:
        """Each result holds its frame's pose as registered; where the step has moved it since (a loop
        applied), the current one replaces it here, the one place every output after the loop reads."""
        current = self.step.current_poses()
        for r in self.results:
            if r.index in current:
                r.pose = current[r.index]

    def _outputs_after_error(self, error: Exception, wall: float) -> None:
        """After an error in the loop: the evaluation, the plot and the step's files (the map, its views) of
        the frames done, where they can still be written; the error itself is what the run reports, and
        carries their summary (``partial_summary``: the CLI writes it to summary.json with the error)."""
        if not self.results:
            return
        try:
            summary = self._summary(wall)
            summary.update(self._evaluate())
            summary.update(self.step.outputs(self))
            summary["ms_per_stage"] = self.timer.summary(skip_first=self.step.warmup_frames)
            error.partial_summary = summary
        except Exception as exc:  # the first error is the one to report; this one only limits what is kept
            logging.getLogger(__name__).warning(f"after the error, not every output of the {len(self.results)} "
                                                f"frames done could be written: {exc}")

    def _nothing_done(self) -> str | None:
        """The line for a run in which no frame got a pose (nothing to map or evaluate), else None."""
        if not self.step.estimates_poses or not self.results or any(r.pose is not None for r in self.results):
            return None
        status = [getattr(r, "status", None) or getattr(getattr(r, "vo", None), "status", None) for r in self.results]
        reasons = sorted({str(s).removeprefix("skipped: ") for s in status if s})
        line = f"none of the {len(self.results)} frames got a pose ({'; '.join(reasons[:2]) or 'no reason given'})"
        if not any("depth" in r for r in reasons):
            return line
        scale = self.dataset.depth_scale
        stated = f"depth scale {scale:g} units per metre (--depth-scale), " if scale else ""
        return (f"{line}: nothing was mapped. Check the depth's units and range: {stated}dataset.depth_max = "
                f"{self.config.dataset.depth_max:g} m")

    # -- the loop -------------------------------------------------------------------------------
    def _loop(self, log: RunLogger) -> None:
        n = len(self.dataset)
        # colour of a separate camera, reprojected here (Taichi's thread)
        register_color = ColorRegistrar(getattr(self.dataset, "color_camera", None))
        prefetcher = Prefetcher.for_dataset(self.dataset, self.config.dataset.read_workers, READ_AHEAD)
        self.read_workers, self.read_mode = prefetcher.workers, prefetcher.mode
        with prefetcher as frames:
            for i in progress(range(n), n, self.step.name, self.show_progress):
                with self.timer.stage("load"):  # the wait for the frame: what reading it did not overlap
                    try:
                        _, frame, read_ms = next(frames)
                    except StreamEnded:  # a camera's played-back recording ended: the run ends here
                        break
                    frame = register_color(frame)
                self.timer.add("read", read_ms)
                first_launches = CLOCK.seconds
                result = self.step.register_frame(frame)
                with Stopwatch(result.ms, "log"):
                    self._log_frame(log, i, frame, result)
                for name, value in result.ms.items():
                    self.timer.add(name, value)
                result.ms["load"] = self.timer.last["load"]
                stats = self.step.stats(result)
                # kernels compiled (or loaded) in this frame: the layout's ms plot leaves such frames out
                stats["first_launch_ms"] = round((CLOCK.seconds - first_launches) * 1e3, 1)
                log.log_stats(frame.timestamp, stats, channel=self.step.stats_channel)
                self.results.append(result)
                self.gt.append(frame.gt_pose)
                if len(self.first_frames_s) < 2:
                    self.first_frames_s.append(process_age_s())

    def _log_frame(self, log: RunLogger, i: int, frame: Frame, result) -> None:
        cfg = self.config.log
        if frame.intrinsics != self._calibration:
            log.log_calibration(frame.timestamp, frame.intrinsics)
            self._calibration = frame.intrinsics
        if result.pose is not None:
            log.log_pose(frame.timestamp, result.pose, frame.gt_pose)
        if hasattr(self.step, "log_frame"):  # the step's own channels (slam: loop edges)
            self.step.log_frame(log, frame, result)
        if cfg.depth_every > 0 and i % cfg.depth_every == 0:
            log.log_depth(frame.timestamp, frame.depth)
            if frame.color is not None:
                log.log_image(frame.timestamp, frame.color)
        to_file = cfg.map_every > 0 and i > 0 and i % cfg.map_every == 0
        to_live = self.live is not None and self.live.map_due()
        if to_file or to_live:
            self._log_map(log, frame.timestamp, to_file, to_live)

    def _log_map(self, log: RunLogger, t: float, file: bool = True, live: bool = True) -> None:
        max_points = self.config.log.map_max_points if file else min(self.config.log.map_max_points,
                                                                      self.live.max_points)
        points = self.step.map_points(max_points)
        if points is not None:
            log.log_points(t, *points, max_points=self.config.log.map_max_points, file=file, live=live)

    def _stats_schema(self) -> dict:
        """The step's stats schema with the two stages the pipeline times itself."""
        schema = copy.deepcopy(self.step.stats_schema)
        schema["properties"]["ms"]["properties"].update(
            load={"type": "number", "description": "reading the frame from the dataset, milliseconds"},
            log={"type": "number", "description": "logging the frame's poses, images and map (to the file and "
                                                  "any live view), milliseconds"})
        schema["properties"]["first_launch_ms"] = {
            "type": "number", "description": "milliseconds of this frame spent in kernels' first launches (compiling "
                                             "them or loading them from the cache; 0 on a frame that ran compiled "
                                             "kernels only)"}
        return schema

    def _metadata(self) -> dict:
        backend = NO_BACKEND if self.backend is None else {
            "arch": self.backend.arch, "requested": self.backend.requested, "reason": self.backend.reason}
        return {"config": self.config.to_dict(), "dataset": self.dataset.describe(), "backend": backend,
                "versions": {**software_versions(), "ti-fusion": __version__}}

    def _write_trajectory(self) -> list[np.ndarray]:
        """trajectory.tum of the frames done that got a pose; returns those poses (the log's /trajectory)."""
        stamps, poses = self.trajectory()
        if stamps:
            write_tum(self.out.file("trajectory.tum"), stamps, np.stack(poses))
        return poses

    # -- after the loop -------------------------------------------------------------------------
    def trajectory(self) -> tuple[list[float], list[np.ndarray]]:
        """(timestamps, camera-to-world poses) of the frames done that got a pose."""
        posed = [r for r in self.results if r.pose is not None]
        return [r.timestamp for r in posed], [r.pose for r in posed]

    def _frame_rate(self) -> tuple[float | None, float]:
        """(frames per second of processing after warm-up, ms of the warm-up frames). Processing is the
        step's stages and logging, not loading the images (I/O, reported as ``load`` on its own)."""
        stages = (*self.step.stages, "log")
        per_frame = np.array([sum(r.ms.get(name, 0.0) for name in stages) for r in self.results])
        warmup = self.step.warmup_frames
        steady = per_frame[warmup:]
        fps = round(1e3 * len(steady) / steady.sum(), 2) if len(steady) and steady.sum() > 0 else None
        return fps, round(float(per_frame[:warmup].sum()), 1)

    def _summary(self, wall: float) -> dict:
        """``fps_wall`` counts every second of the loop (waiting for frames, logging, compiling);
        ``fps_processing`` the step's stages and logging after warm-up; ``first_frame_s`` and
        ``second_frame_s`` are the process's age when frames 0 and 1 were done (for slam, frame 1 is the
        first one tracked)."""
        fps, warmup_ms = self._frame_rate()
        first = dict(zip(("first_frame_s", "second_frame_s"), self.first_frames_s))
        return {"frames": len(self.results), "wall_s": wall,
                "fps_wall": round(len(self.results) / wall, 2) if wall > 0 else None, "fps_processing": fps,
                "warmup_ms": warmup_ms, **first, "read_workers": self.read_workers,
                "read_mode": self.read_mode,
                "dataset": self.dataset.describe()}

    def _evaluate(self) -> dict:
        """ATE/RPE of the posed frames that have ground truth (``gt_frames`` of them; ``gt_note`` says so when
        that is not every posed frame), and trajectory.png."""
        if not self.step.estimates_poses:
            return {}
        if all(r.pose is None for r in self.results):
            return {}
        # every frame from the first posed one (a rejected or failed frame holds the pose reported for it):
        # no headline from the tracked minority; that one is ate_tracked_only_rmse_m, with the counts
        stamps, poses, gt, tracked = held_trajectory(self.results, self.gt)
        pairs = [(p, g) for p, g in zip(poses, gt) if g is not None]
        tracked = [t for t, g in zip(tracked, gt) if g is not None]
        fields, metrics = {"gt_frames": len(pairs)}, None
        if pairs and 2 * len(pairs) < len(poses):  # a few matches, maybe by chance: no figure to quote as the run's
            fields["gt_note"] = (f"no ATE or RPE: only {len(pairs)} of the {len(poses)} posed frames have ground "
                                 "truth, fewer than half (are its times on the frames' clock?)")
            pairs = []
        if len(pairs) >= 2:
            est, ref = (np.stack(x) for x in zip(*pairs))
            metrics = trajectory_metrics(est, ref)
            fields.update({k: metrics[k] for k in ("ate_rmse_m", "ate_mean_m", "ate_max_m", "rpe_trans_m",
                                                   "rpe_rot_deg", "pairs")})
            path_length = float(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1).sum())
            fields["path_length_m"] = round(path_length, 3)
            fields["ate_percent_of_path"] = round(100 * metrics["ate_rmse_m"] / max(path_length, 1e-9), 3)
            fields.update(tracked_ate(est, ref, tracked))
        if pairs and len(pairs) < len(poses):  # some frames lack ground truth: say what the figures are over
            fields["gt_note"] = (f"ATE and RPE are over the {len(pairs)} of {len(poses)} posed frames that have "
                                 "ground truth" if metrics is not None else
                                 f"no ATE or RPE: 1 of the {len(poses)} posed frames has ground truth, they need 2")
        from ti_fusion.evaluation.plots import plot_trajectory  # Matplotlib: only once there is a plot to draw

        with_gt = len(pairs) == len(poses) and metrics is not None  # else the estimate alone
        title = self.step.plot_title(self) + (f"\n({fields['gt_note']})" if "gt_note" in fields else "")
        edges = self.step.loop_edges() if hasattr(self.step, "loop_edges") else None
        plot_trajectory(self.out.file("trajectory.png"), np.stack(poses), np.stack(gt) if with_gt else None,
                        timestamps=stamps, title=title, metrics=metrics, **({"loop_edges": edges} if edges else {}))
        return fields


class SLAMPipeline(Pipeline):
    """The run of ``ti-fusion slam``: the pipeline with dense SLAM (``SLAMStep``) as its step."""

    def __init__(self, dataset: Dataset, config: Config, run_dir: RunDir, backend: BackendInfo | None,
                 show_progress: bool = True, live=None):
        from ti_fusion.slam.slam_step import SLAMStep  # Taichi: imported by the commands that use it only

        super().__init__(dataset, config, run_dir, SLAMStep(config, dataset), backend, show_progress, live)
