"""The run of a per-frame command (``slam``, ``vo``, ``fuse``): the loop over a dataset, one way.

    summary = Pipeline(dataset, config, run_dir, step, backend).run()

Each frame goes one way: read (``ti_fusion.io.prefetch``), ``step.register_frame`` (the command's system:
for slam, ``DenseSLAM`` with tracking, mapping and loop closure inside), then every sink's ``frame`` in the
order of ``ti_fusion.sinks.SINKS`` (the log, the mesh, ...). After the loop each sink's ``finish`` writes its
files. Whatever ends the loop (its normal end, bad input in frame 300, Ctrl-C), the frames done so far leave a
finalised ``log.mcap`` and a ``trajectory.tum`` (the sinks with ``on_stop``); after an error every other
output is still attempted, and the error is what the run reports. An endless stream (a live camera) ends at
the first Ctrl-C after the frame being done, as a recording ends: the run then finishes normally.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from ti_fusion.backend import BackendInfo
from ti_fusion.config import Config
from ti_fusion.errors import InputError, NotLocalised, OutputError
from ti_fusion.frontend import CLOCK
from ti_fusion.interrupts import stream_end
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.outputs import RunDir, progress
from ti_fusion.io.prefetch import Prefetcher
from ti_fusion.io.datasets.realsense_live import StreamEnded
from ti_fusion.io.registration import ColorRegistrar
from ti_fusion.sinks import make_sinks
from ti_fusion.sinks.base import Sink
from ti_fusion.slam.checks import check_first_frames
from ti_fusion.timing import StageTimer, Stopwatch, process_age_s

# Frames read ahead of the one being processed, in reader processes or a thread (ti_fusion.io.prefetch); at least
# one per reader.
READ_AHEAD = 3


class Step(Protocol):
    """What a command gives the pipeline: its system, whose ``register_frame`` does one frame; the sinks read
    the rest (``ti_fusion.sinks.base.Step``)."""

    name: str                 # the command: the progress bar's label, and which sinks run
    stages: tuple[str, ...]   # the keys of ``result.ms`` that fps_processing counts (with the log sink's "log")
    warmup_frames: int        # the first frames, which compile kernels: left out of fps_processing and ms_per_stage
    estimates_poses: bool     # poses are estimates: evaluated against ground truth and plotted

    def register_frame(self, frame: Frame) -> Any:
        """One frame. The result has ``index``, ``timestamp``, ``pose`` (camera-to-world, None when the frame
        got no pose: it is then left out of trajectory.tum), ``ms`` (stage → milliseconds, a dict that the
        pipeline adds "load" to and the log sink "log") and ``loop`` (a loop closure report or None)."""

    def current_poses(self) -> dict[int, np.ndarray]:
        """Frame index → the current pose of each frame whose pose moved or may have moved since its result
        (loop closure); the pipeline takes them into the results once, before any sink finishes."""

    def summary(self, run: Pipeline) -> dict:
        """After the loop: the command's own summary.json fields (no files: those are the sinks')."""


class Pipeline:
    """Runs a ``Step`` over every frame of a dataset, then its sinks, which write into ``run_dir``."""

    def __init__(self, dataset: Dataset, config: Config, run_dir: RunDir, step: Step,
                 backend: BackendInfo | None = None, show_progress: bool = True, live=None,
                 outputs: dict[str, bool] | None = None):
        self.dataset = dataset
        self.live = live  # a LiveServer (ti_fusion.io.live) that the log feeds too, or None
        self.config = config
        self.out = run_dir
        self.step = step
        self.backend = backend
        self.show_progress = show_progress and config.log.progress
        # the outputs, in order (ti_fusion.sinks.SINKS); ``outputs`` turns sinks on or off by name
        self.sinks: list[Sink] = make_sinks(step.name, config, outputs)
        self.log = None  # the open RunLogger, from the log sink's start to its finish
        self.timer = StageTimer()
        self.results: list = []  # the step's result of every frame done
        self.gt: list[np.ndarray | None] = []  # and the frame's ground-truth pose
        self.first_frames_s: list[float] = []  # the process's age when each of the first two frames was done
        self.read_workers = 0  # processes (or the thread) that read the frames ahead (0: the loop's own thread)
        self.read_mode = "inline"  # how: "processes", "thread" or "inline" (ti_fusion.io.prefetch.read_mode)
        self.frame_clock = 0.0  # seconds of kernels' first launches (frontend.CLOCK) when the frame being done began
        self._background = None  # during a sink's finish: (the outputs' threads, what it handed to them)
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
        error = stop = None
        started: list[Sink] = []
        try:
            for sink in self.sinks:
                sink.start(self)
                started.append(sink)
            self._loop(started)
        except Exception as exc:  # bad input in frame 300: the frames done so far still give their outputs
            error = exc
        except BaseException as exc:  # Ctrl-C, SIGTERM: what a stop keeps (trajectory, log), then the stop
            stop = exc
        wall = run_watch.ms / 1e3
        self._take_current_poses()
        nothing = None if error is not None or stop is not None else self._nothing_done()
        only_kept = stop is not None or nothing is not None or (error is not None and not self.results)
        try:
            fields, failure = self._finish(started, only_kept, error)
        finally:
            for sink in started:
                sink.close()
        if stop is not None:
            raise stop
        if error is not None:
            if self.results:  # the summary of the frames done goes with the error (the CLI writes it)
                try:
                    error.partial_summary = self._whole_summary(wall, fields)
                except Exception as exc:  # the first error is the one to report
                    logging.getLogger(__name__).warning(f"after the error, no summary of the {len(self.results)} "
                                                        f"frames done: {exc}")
            raise error
        if nothing and self._unlocalised():  # a session against a saved map that never found itself in it
            error = NotLocalised(self.dataset.root, nothing)
            error.partial_summary = self._whole_summary(wall, fields)
            raise error
        if nothing:
            raise InputError(self.dataset.root, nothing)
        if failure is not None:
            raise failure
        summary = self._whole_summary(wall, fields)
        summary["process_s"] = process_age_s()  # from the process's start: interpreter, imports, compiling
        return summary

    def _whole_summary(self, wall: float, fields: dict) -> dict:
        """The pipeline's figures, the sinks' ``fields`` and the step's own."""
        summary = self._summary(wall)
        summary.update(fields)
        summary.update(self.step.summary(self))
        summary["ms_per_stage"] = self.timer.summary(skip_first=self.step.warmup_frames)
        return summary

    def _finish(self, sinks: list[Sink], only_kept: bool, error: Exception | None) -> tuple[dict, Exception | None]:
        """Every started sink's ``finish``, in order; with ``only_kept`` (a stop, a run that did nothing) those
        with ``on_stop`` only. A sink that fails does not keep the later ones from finishing: after an error
        in the loop its failure is a warning (that error is what the run reports), else the first failure is
        returned. A stop while finishing leaves only the ``on_stop`` sinks to finish, and is raised after.
        What a sink hands to ``in_background`` runs on the outputs' threads beside the later sinks; its
        fields and failure count as the sink's, in the sinks' order, once every sink has finished."""
        outcomes: list[tuple[Sink, dict | Exception | None, list[Future]]] = []
        stop: BaseException | None = None
        with self.timer.stage("export"):
            # the encoding, writing and fsync of the files (GIL-free) and the plot overlap the next sinks' work
            pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="outputs")
            try:
                for sink in sinks:
                    if (only_kept or stop is not None) and not sink.on_stop:
                        continue
                    self._background = later = (pool, [])
                    try:
                        outcome = sink.finish(self)
                    except Exception as exc:
                        outcome = exc
                    except BaseException as exc:  # a stop while finishing: the trajectory and the log still
                        stop, outcome = stop or exc, None
                    outcomes.append((sink, outcome, later[1]))
                    self._background = None
            finally:
                self._background = None
                try:
                    pool.shutdown(wait=True)
                except BaseException as exc:  # a stop while the last files are written: they finish on their own
                    pool.shutdown(wait=False, cancel_futures=True)
                    stop = stop or exc
        fields: dict = {}
        failure: Exception | None = None
        also: list[Path] = []  # outputs refused for the same reason as the one reported
        for sink, outcome, futures in outcomes:
            parts = [outcome] + [(f.exception() or f.result()) if f.done() and not f.cancelled() else None
                                 for f in futures]
            for part in parts:
                if part is None:
                    continue
                if isinstance(part, BaseException) and not isinstance(part, Exception):
                    stop = stop or part
                elif not isinstance(part, Exception):
                    fields.update(part if isinstance(part, dict) else {})  # a function's own return value: none
                elif error is None and failure is None:
                    failure = part
                elif _same_cause(error or failure, part):  # a full disk refuses every output: one line
                    also.append(part.path)
                else:  # the first error is the one to report; this one only limits what is kept
                    logging.getLogger(__name__).warning(
                        f"after the error, {sink.name} of the {len(self.results)} frames done could not be "
                        f"written: {part}")
        if also:
            _name_also(error or failure, also)
        if stop is not None:
            raise stop
        return fields, failure

    def in_background(self, fn: Callable[[], dict | None]) -> None:
        """From a sink's ``finish``: run ``fn`` (no Taichi: it reads only what the sink handed it) on an outputs'
        thread beside the later sinks; a dict it returns joins summary.json after the sink's own fields, what
        it raises is the sink's failure."""
        pool, futures = self._background
        futures.append(pool.submit(fn))

    def _take_current_poses(self) -> None:
        """Each result holds its frame's pose as registered; where the step has moved it since (a loop
        applied), the current one replaces it here, the one place every output after the loop reads."""
        current = self.step.current_poses()
        for r in self.results:
            if r.index in current:
                r.pose = current[r.index]

    def _nothing_done(self) -> str | None:
        """The line for a run in which no frame got a pose (nothing to map or evaluate), else None."""
        if not self.step.estimates_poses or not self.results or any(r.pose is not None for r in self.results):
            return None
        if self._unlocalised():
            return (f"none of the {len(self.results)} frames found itself in the map (--map; the last: "
                    f"{self.results[-1].status.removeprefix('unlocalised: ')}): not localised. The data may not see "
                    "the mapped place; --unfound map-anyway maps it in its own frame instead")
        reasons = sorted({r.status.removeprefix("skipped: ") for r in self.results if r.status})
        line = f"none of the {len(self.results)} frames got a pose ({'; '.join(reasons[:2]) or 'no reason given'})"
        if not any("depth" in r for r in reasons):
            return line
        scale = self.dataset.depth_scale
        stated = f"depth scale {scale:g} units per metre (--depth-scale), " if scale else ""
        return (f"{line}: nothing was mapped. Check the depth's units and range: {stated}dataset.depth_max = "
                f"{self.config.dataset.depth_max:g} m")

    def _unlocalised(self) -> bool:
        """Every frame done was a session's that did not find itself in its saved map."""
        return bool(self.results) and all(r.status.startswith("unlocalised") for r in self.results)

    # -- the loop -------------------------------------------------------------------------------
    def _loop(self, sinks: list[Sink]) -> None:
        n = len(self.dataset)
        # colour of a separate camera, reprojected here (Taichi's thread)
        register_color = ColorRegistrar(getattr(self.dataset, "color_camera", None))
        prefetcher = Prefetcher.for_dataset(self.dataset, self.config.dataset.read_workers, READ_AHEAD,
                                            self.backend.arch if self.backend is not None else None)
        self.read_workers, self.read_mode = prefetcher.workers, prefetcher.mode
        # an endless stream's loop ends at the first Ctrl-C (the CLI's handler sets ``end.requested``)
        endless = self.dataset.endless
        with prefetcher as frames, (stream_end() if endless else nullcontext()) as end:
            warm_up = getattr(self.step, "warm_up", None)
            if prefetcher.renders_elsewhere and warm_up is not None:  # meanwhile, the first frame's own kernels
                warm_up(self.dataset)
            # a session against a saved map, until it has found itself in it, and a localisation off the map
            note = lambda: "" if not self.results else "not localised" if self.results[-1].status.startswith(
                "unlocalised") else "off the map: odometry" if self.results[-1].status.startswith("odometry") else ""
            for i in progress(range(n), None if endless else n, self.step.name, self.show_progress, note):
                with self.timer.stage("load"):  # the wait for the frame: what reading it did not overlap
                    try:
                        _, frame, read_ms = next(frames)
                    except StreamEnded:  # a camera's played-back recording ended: the run ends here
                        break
                    frame = register_color(frame)
                self.timer.add("read", read_ms)
                self.frame_clock = CLOCK.seconds
                result = self.step.register_frame(frame)
                for name, value in result.ms.items():
                    self.timer.add(name, value)
                result.ms["load"] = self.timer.last["load"]
                for sink in sinks:
                    sink.frame(self, frame, result)
                # done once every sink has it: a stop inside the log's write leaves it out of trajectory.tum too
                self.results.append(result)
                self.gt.append(frame.gt_pose)
                if len(self.first_frames_s) < 2:
                    self.first_frames_s.append(process_age_s())
                if end is not None and end.requested:  # Ctrl-C: this stream ends here, like a recording's
                    break

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


class SLAMPipeline(Pipeline):
    """The run of ``ti-fusion slam``: the pipeline with dense SLAM (``SLAMStep``) as its step."""

    def __init__(self, dataset: Dataset, config: Config, run_dir: RunDir, backend: BackendInfo | None,
                 show_progress: bool = True, live=None, outputs: dict[str, bool] | None = None):
        from ti_fusion.slam.slam_step import SLAMStep  # Taichi: imported by the commands that use it only

        super().__init__(dataset, config, run_dir, SLAMStep(config, dataset), backend, show_progress, live, outputs)


def _same_cause(reported: Exception, later: Exception) -> bool:
    """Both outputs refused for one reason (a full disk, a folder gone read-only)."""
    return isinstance(reported, OutputError) and isinstance(later, OutputError) and reported.problem == later.problem


def _name_also(reported: Exception, paths: list[Path]) -> None:
    """The reported line also names the other outputs refused for the same reason."""
    base = reported.path.parent
    names = ", ".join(str(p.relative_to(base)) if p.is_relative_to(base) else str(p) for p in paths)
    reported.args = (f"{reported} (nor {names})",)
