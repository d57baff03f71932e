"""The ``ti-fusion`` command line: ``main`` parses and dispatches; one module per sub-command."""

from ti_fusion.cli.main import command, main

__all__ = ["command", "main"]
