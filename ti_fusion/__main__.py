"""``python -m ti_fusion``: the same as the ``ti-fusion`` command."""

from ti_fusion.cli.main import command

command()
