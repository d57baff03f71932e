"""``ti-fusion bench NAME``: run one of the benchmarks in scripts/ (icp, icp_ceiling, fusion, fusion_ceiling, slam, backends)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

from ..errors import InputError

NAMES = ("icp", "icp_ceiling", "fusion", "fusion_ceiling", "slam", "backends")
HELP = f"run a benchmark from scripts/ ({', '.join(NAMES)}); options after -- go to the script"
USES_DATASET = False
USES_TAICHI = False


def add_arguments(parser) -> None:
    parser.add_argument("name", choices=NAMES, help="which benchmark")
    parser.add_argument("script_args", nargs="*", help="arguments for the script (put them after --)")


def run(ctx) -> dict:
    script = Path(__file__).resolve().parents[2] / "scripts" / f"bench_{ctx.args.name}.py"
    if not script.is_file():
        raise InputError(script, "benchmark scripts come with a source checkout of ti-fusion, not with a wheel")
    saved = sys.argv
    sys.argv = [str(script), *ctx.args.script_args]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        if exc.code not in (None, 0):
            raise
    finally:
        sys.argv = saved
    return {"benchmark": ctx.args.name}
