"""The end of a run with outputs written on the outputs' threads (``Pipeline.in_background``): fields join
summary.json in the sinks' order, a failure there is the sink's, and a full disk stays one line naming every
output it refused, whichever thread met it first. No Taichi: the sinks here are stand-ins."""

from __future__ import annotations

import threading
from pathlib import Path

from ti_fusion.errors import OutputError
from ti_fusion.sinks.base import Sink
from ti_fusion.slam.pipeline import Pipeline
from ti_fusion.timing import StageTimer


def _pipeline() -> Pipeline:
    run = Pipeline.__new__(Pipeline)  # only what _finish reads
    run.timer, run.results, run._background = StageTimer(), [], None
    return run


class _Stand(Sink):
    def __init__(self, name: str, now: dict | Exception | None = None, later=None, on_stop: bool = False):
        self.name, self.now, self.later, self.on_stop = name, now, later, on_stop
        self.thread = None

    def finish(self, run) -> dict:
        if self.later is not None:
            def later():
                self.thread = threading.current_thread()
                if isinstance(self.later, Exception):
                    raise self.later
                return self.later
            run.in_background(later)
        if isinstance(self.now, Exception):
            raise self.now
        return self.now or {}


def test_fields_come_in_the_sinks_order_from_the_outputs_threads():
    sinks = [_Stand("a", {"a": 1}, later={"a_late": 2}), _Stand("b", {"b": 3}), _Stand("c", later={"c": 4})]
    fields, failure = _pipeline()._finish(sinks, only_kept=False, error=None)
    assert failure is None and list(fields) == ["a", "a_late", "b", "c"] and fields["c"] == 4
    assert sinks[0].thread is not threading.current_thread() and sinks[0].thread.name.startswith("outputs")


def test_a_full_disk_is_one_error_naming_every_output_in_the_sinks_order():
    full = "cannot be written: No space left on device"
    sinks = [_Stand("map", {"ply": "map.ply"}, later=OutputError(Path("/run/map.ply"), full)),
             _Stand("saved", later=OutputError(Path("/run/map/map.json"), full)),
             _Stand("other", later=OutputError(Path("/run/x.png"), "cannot encode"))]
    fields, failure = _pipeline()._finish(sinks, only_kept=False, error=None)
    assert fields == {"ply": "map.ply"}
    assert str(failure) == f"/run/map.ply: {full} (nor {Path('map') / 'map.json'})"


def test_after_a_stop_only_the_kept_outputs_finish():
    sinks = [_Stand("trajectory", {"t": 1}, on_stop=True), _Stand("plot", later={"p": 2}),
             _Stand("log", {"log": 3}, on_stop=True)]
    fields, failure = _pipeline()._finish(sinks, only_kept=True, error=None)
    assert failure is None and fields == {"t": 1, "log": 3} and sinks[1].thread is None
