"""CLI sub-commands, one module each.

A command module defines:
    HELP: str                         one line for ``ti-fusion --help``
    USES_DATASET: bool                takes a DATA argument and the dataset options
    USES_TAICHI: bool                 needs a Taichi backend (``--arch``)
    add_arguments(parser) -> None     its own options
    run(ctx) -> dict                  does the work; returns the command's own summary fields
"""

COMMAND_NAMES = ("synth", "icp", "fuse", "slam", "vo", "inspect", "bench")
