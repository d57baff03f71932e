"""``python -m ti_fusion``: the same as the ``ti-fusion`` command."""

import sys

from ti_fusion.cli.main import main

sys.exit(main())
