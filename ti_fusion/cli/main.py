"""``ti-fusion``: the command-line entry point.

Every sub-command shares the conventions: ``--out DIR`` (default ``logs/<command>-<timestamp>/``)
receives everything the run writes, ``summary.json`` holds its headline figures, ``--quiet`` turns off
the progress bar, ``--arch`` picks the Taichi backend, ``--config FILE`` and ``--set SECTION.KEY=VALUE``
change the typed config. Bad input ends the run with exit code 2 and one line naming the file and problem.
"""

from __future__ import annotations

import os

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")  # keep stdout for our own output

import argparse
import importlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from ti_fusion import __version__
from ti_fusion.backend import ARCH_CHOICES, BackendInfo, init_backend
from ti_fusion.config import Config, load_config
from ti_fusion.errors import TiFusionError
from ti_fusion.io.outputs import RunDir, base_summary


# A command module defines:
#     HELP: str                         one line for ``ti-fusion --help``
#     USES_DATASET: bool                takes a DATA argument and the dataset options
#     USES_TAICHI: bool                 needs a Taichi backend (``--arch``)
#     add_arguments(parser) -> None     its own options
#     run(ctx) -> dict                  does the work; returns the command's own summary fields
COMMAND_NAMES = ("synth", "icp", "fuse", "slam", "vo", "inspect")


@dataclass
class RunContext:
    """What a command's ``run`` gets: parsed arguments, config, output folder and backend."""

    command: str
    args: argparse.Namespace
    config: Config
    out: RunDir
    backend: BackendInfo | None
    quiet: bool

    def log(self, message: str) -> None:
        print(message, flush=True)


def _available_commands() -> dict[str, ModuleType]:
    modules = {}
    for name in COMMAND_NAMES:
        try:
            modules[name] = importlib.import_module(f"ti_fusion.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"ti_fusion.cli.{name}":
                raise
    return modules


def _add_common(parser: argparse.ArgumentParser, module: ModuleType) -> None:
    g = parser.add_argument_group("common options")
    g.add_argument("--out", metavar="DIR", help="output folder (default: logs/<command>-<YYYYmmdd-HHMMSS>/)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.add_argument("--config", metavar="FILE", help="config file (.toml, .yaml or .json)")
    g.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override one config value, e.g. --set icp.dist_threshold=0.05 (repeatable)")
    if getattr(module, "USES_TAICHI", False):
        g.add_argument("--arch", choices=ARCH_CHOICES, default="cpu",
                       help="Taichi backend; auto tries cuda, then vulkan, then cpu (default: cpu)")
    if getattr(module, "USES_DATASET", False):
        d = parser.add_argument_group("dataset options")
        d.add_argument("data", nargs="?", default="", metavar="DATA",
                       help="dataset folder (TUM, ICL-NUIM or 7-Scenes); omitted: the embedded synthetic sequence")
        d.add_argument("--format", choices=("auto", "tum", "iclnuim", "7scenes", "synthetic"), default=None,
                       help="dataset format (default: detected from the folder)")
        d.add_argument("--downsample", type=int, default=None, help="integer subsampling factor (2 → 320×240)")
        d.add_argument("--start", type=int, default=None, help="first frame")
        d.add_argument("--stop", type=int, default=None, help="one past the last frame")
        d.add_argument("--stride", type=int, default=None, help="take every N-th frame")
        d.add_argument("--frames", type=int, default=None, help="number of frames (from --start)")


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, ModuleType]]:
    parser = argparse.ArgumentParser(
        prog="ti-fusion",
        description="Dense RGB-D SLAM with point-to-plane ICP and surfel fusion on Taichi kernels.",
    )
    parser.add_argument("--version", action="version", version=f"ti-fusion {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = _available_commands()
    for name, module in modules.items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        _add_common(p, module)
    return parser, modules


def _apply_dataset_args(args: argparse.Namespace, config: Config) -> None:
    ds = config.dataset
    if getattr(args, "data", ""):
        ds.path = args.data
    for name in ("format", "downsample", "start", "stop", "stride"):
        value = getattr(args, name, None)
        if value is not None:
            setattr(ds, name, value)
    if getattr(args, "frames", None) is not None:
        ds.stop = ds.start + args.frames * ds.stride
        config.synth.frames = max(config.synth.frames, ds.stop) if ds.path == "" else config.synth.frames


def main(argv: list[str] | None = None) -> int:
    parser, modules = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 0
    module = modules[args.command]
    try:
        config = load_config(args.config, args.set)
        if getattr(module, "USES_DATASET", False):
            _apply_dataset_args(args, config)
        if args.quiet:
            config.log.progress = False
        backend = init_backend(args.arch) if getattr(module, "USES_TAICHI", False) else None
        if backend is not None and not args.quiet:
            print(f"backend: {backend.arch} ({backend.reason})", flush=True)
        positional = getattr(module, "OUT_FROM_POSITIONAL", None)  # a command whose positional names its output
        out = RunDir(args.command, getattr(args, positional) if positional else args.out)
        ctx = RunContext(args.command, args, config, out, backend, args.quiet)
        t0 = time.perf_counter()
        result = module.run(ctx) or {}
        wall = time.perf_counter() - t0
        summary = base_summary(args.command, result.pop("frames", 0), result.pop("wall_s", wall),
                               result.pop("ms_per_stage", {}))
        if backend is not None:
            summary["backend"] = backend.arch
        summary.update(result)
        path = out.write_summary(summary)
        print(f"outputs written to {out.path}/ (summary: {path})", flush=True)
        return 0
    except TiFusionError as exc:
        print(f"ti-fusion {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ti-fusion {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
