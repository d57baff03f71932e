"""What every output of a run implements: ``Sink`` (start, frame, finish), and ``Run``, what a sink reads.

    class SplatSink(Sink):
        name, commands, flag, help = "splats", ("slam",), "--splats", "also splats.ply: ..."

        def finish(self, run: Run) -> dict:
            ...write run.out.file("splats.ply") from run.step.mapper...
            return {"splats": count}       # summary.json fields

The pipeline (``ti_fusion/slam/pipeline.py``) calls ``start`` on each sink before the first frame,
``frame`` after each frame's ``register_frame``, and ``finish`` after the last, always in the order of
``ti_fusion.sinks.SINKS``. A sink reads the run (its results, the step's map) and writes; it never
changes what the next frame computes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from pathlib import Path

    import numpy as np

    from ti_fusion.config import Config
    from ti_fusion.frame import Frame
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.timing import StageTimer


class Step(Protocol):
    """What the sinks read of a command's system (``SLAMStep``, ``VOStep``, ``FuseStep``)."""

    name: str                 # the command
    stats_channel: str        # the log channel of the per-frame stats, e.g. "/slam/stats"
    stats_schema: dict        # the JSON Schema of its messages
    estimates_poses: bool     # poses are estimates: evaluated against ground truth and plotted
    mapper: Any               # the surfel map (``SurfelMapper``), or None for a command without one

    def stats(self, result: Any) -> dict:
        """The frame's message on ``stats_channel``."""

    def map_points(self, max_points: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(positions, uint8 RGB) of the map so far for /map/points (``max_points`` is a hint), or None."""

    def loop_edges(self) -> list:
        """Every loop candidate checked so far, as (from, to, applied) world points ([] without loop closure)."""

    def plot_title(self, run: Run) -> str:
        """The title of trajectory.png."""


class Run(Protocol):
    """What a sink reads of the run (the ``Pipeline``)."""

    config: Config
    out: RunDir               # the output folder: ``out.file(name)`` is a path to write
    dataset: Any
    step: Step
    results: list             # each frame's result so far: index, timestamp, pose (None: no pose), ms, loop
    gt: list                  # each frame's ground-truth pose or None
    timer: StageTimer
    live: Any                 # a LiveServer (--live) or None
    backend: Any
    log: Any                  # the open RunLogger from the log sink's start to its finish (other sinks add to it)
    frame_clock: float        # frontend.CLOCK's seconds of first launches when the frame being done began

    def trajectory(self) -> tuple[list[float], list[np.ndarray]]:
        """(timestamps, camera-to-world poses) of the frames done that got a pose."""

    def in_background(self, fn) -> None:
        """From ``finish``: run ``fn`` (no Taichi) on an outputs' thread while the later sinks finish; a dict
        it returns joins summary.json, what it raises is this sink's failure."""


class Sink:
    """One output of a run. Subclasses set ``name`` and ``commands``, and override what they need of
    ``start``, ``frame`` and ``finish``."""

    name: str = ""                      # what it writes, in a word; also its key in Pipeline(outputs=...)
    commands: tuple[str, ...] = ()      # the commands it serves ("slam", "vo", "fuse")
    flag: str | None = None             # a switch of those commands that turns it on (off without it), e.g. "--splats"
    off_flag: str | None = None         # a switch that turns it off (on without it), e.g. "--no-save-map"
    help: str = ""                      # the switch's help line
    on_stop: bool = False               # finished after a stop (Ctrl-C, SIGTERM) too: what an interrupted run keeps

    @classmethod
    def wanted(cls, command: str, config: Config, outputs: dict[str, bool]) -> bool:
        """Whether a run of ``command`` has this output: ``outputs[name]`` where given (a switch, an API
        caller), else on unless it has a switch that turns it on."""
        return command in cls.commands and outputs.get(cls.name, cls.flag is None)

    def start(self, run: Run) -> None:
        """Before the first frame."""

    def frame(self, run: Run, frame: Frame, result: Any) -> None:
        """After ``register_frame`` returned ``result`` for ``frame`` (added to ``run.results`` once every
        sink has had it)."""

    def finish(self, run: Run) -> dict:
        """After the last frame (or an error in the loop: then every sink; or a stop: those with
        ``on_stop``): write the files; return this output's summary.json fields."""
        return {}

    def close(self) -> None:
        """After ``finish`` and its background work, or instead of them (a stop, a failure): free what
        ``start`` took (a process), whatever ended the run."""

