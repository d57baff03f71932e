"""The outputs of a run, one ``Sink`` per file (``base.py``), registered in ``SINKS``.

An output is one module here with a ``Sink`` subclass, and one line in ``SINKS``: the pipeline runs it for
the commands it names, and a sink with a ``flag`` gets that switch on those commands' command lines
(docs/ARCHITECTURE.md, "How to add an output").
"""

from __future__ import annotations

from importlib import import_module

from ti_fusion.sinks.base import Sink

# module:class of each sink, in the order the pipeline calls them: trajectory.tum first (the one file every
# end of a run keeps), the log last (the others add to it before it closes).
SINKS: tuple[str, ...] = (
    "trajectory:TrajectorySink",
    "evaluation:EvaluationSink",
    "map:MapSink",
    "saved_map:SavedMapSink",
    "views:ViewsSink",
    "cloud:CloudSink",
    "mesh:MeshSink",
    "splats:SplatSink",
    "log:LogSink",
)


def sink_classes(command: str | None = None) -> list[type[Sink]]:
    """The registered sinks (of ``command``, where given), in order."""
    classes = []
    for entry in SINKS:
        module, name = entry.split(":")
        cls = getattr(import_module(f"ti_fusion.sinks.{module}"), name)
        if command is None or command in cls.commands:
            classes.append(cls)
    return classes


def make_sinks(command: str, config, outputs: dict[str, bool] | None = None) -> list[Sink]:
    """A new instance of every sink a run of ``command`` has with ``config`` and ``outputs`` (name → on/off,
    e.g. {"splats": True} from ``--splats``; unknown names are refused)."""
    outputs = dict(outputs or {})
    known = {cls.name for cls in sink_classes()}
    if unknown := sorted(set(outputs) - known):
        raise ValueError(f"no output named {', '.join(unknown)} (outputs: {', '.join(sorted(known))})")
    return [cls() for cls in sink_classes(command) if cls.wanted(command, config, outputs)]


def add_switches(parser, command: str) -> None:
    """The command-line switch of each of ``command``'s sinks that has one (``Sink.flag``, or ``Sink.off_flag``)."""
    for cls in sink_classes(command):
        if cls.flag or cls.off_flag:
            parser.add_argument(cls.flag or cls.off_flag, action="store_true", dest=f"output_{cls.name}",
                                help=cls.help)


def chosen(args, command: str) -> dict[str, bool]:
    """name → True (False for an ``off_flag``) for each of ``command``'s switched sinks whose switch ``args``
    (argparse) has."""
    return {cls.name: cls.off_flag is None for cls in sink_classes(command)
            if (cls.flag or cls.off_flag) and getattr(args, f"output_{cls.name}")}
