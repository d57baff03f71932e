"""``ti-fusion``: the command-line entry point.

Every sub-command shares the conventions: ``--out DIR`` (default ``logs/<command>-<timestamp>/``)
receives everything the run writes and belongs to that run alone (an existing non-empty folder is
refused unless ``--overwrite`` replaces the earlier run in it; two runs cannot share one), ``summary.json``
holds its headline figures, ``--quiet`` turns off the progress bar and the informational lines,
``--arch`` picks the Taichi backend, ``--config FILE`` and ``--set SECTION.KEY=VALUE`` change the typed
config.

How a run ends, and its exit code:
    0        done; the last line says where the outputs are
    1        ``batch``: it ran, and one or more of its jobs failed (each failed row of its table says why)
    2        bad input or an output that cannot be written: one line on stderr naming the file or option
    130      Ctrl-C (SIGINT); a live camera's stream (no --frames) ends at the first Ctrl-C instead, and the run
             finishes as at a recording's end (0, with its map); a second Ctrl-C stops it (130)
    128 + n  stopped by signal n: SIGTERM (143) and SIGHUP (129) are handled as Ctrl-C is, so the run
             keeps what it has done (``slam`` and ``vo``: the trajectory so far and a finalised log)
    141      the reader of the output went away (``ti-fusion inspect LOG | head``): nothing more is said
"""

from __future__ import annotations

import os

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")  # keep stdout for our own output
# Taichi's ti.init starts a thread that asks Taichi's server for a newer release (once a day, every run where the
# request fails): its TLS set-up takes the GIL at the run's start, and the pinned Taichi is the one to use anyway
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

import argparse
import gc
import importlib
import logging
import re
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from ti_fusion import __version__
from ti_fusion.backend import ARCH_CHOICES, BackendInfo, init_backend
from ti_fusion.cli.options import add_flags, apply_flags
from ti_fusion.config import Config, load_config
from ti_fusion.errors import InputError, OutputError, TiFusionError
from ti_fusion.interrupts import after_import, end_stream, interrupt
from ti_fusion.io.outputs import RunDir, base_summary
from ti_fusion.timing import Stopwatch


# A command module defines:
#     HELP: str                         one line for ``ti-fusion --help``
#     USES_DATASET: bool                takes a DATA argument and the dataset options
#     USES_TAICHI: bool                 needs a Taichi backend (``--arch``)
#     OUT_FROM_POSITIONAL: str          (optional) the positional that names the output folder, instead of --out
#     writes_files(args) -> bool        (optional) False: this call writes nothing, and gets no folder (ctx.out None)
#     adds_to_run(args) -> str | None   (optional) a run folder this call adds its files to (no --out given)
#     RESUMES_OUT: bool                 (optional) an earlier run of this command in --out is continued, not refused
#     add_arguments(parser) -> None     its own options
#     run(ctx) -> dict                  does the work; returns the command's own summary fields (and, optionally,
#                                       exit_code: the process's, kept out of the summary)
COMMAND_NAMES = ("synth", "icp", "fuse", "slam", "vo", "inspect", "mesh", "batch")

# Signals that stop a run the way Ctrl-C does: what kill, timeout, systemd and container runtimes send
# (SIGTERM), and a closed terminal (SIGHUP).
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))

# What the first Ctrl-C during a live camera's stream says (ti_fusion.interrupts.end_stream).
FINISHING = "Ctrl-C: finishing the run (its outputs and summary.json); Ctrl-C again to stop at once"


class Stopped(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM or SIGHUP, so every ``finally`` and ``except KeyboardInterrupt``
    that keeps a Ctrl-C'd run's work keeps a stopped run's too."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@dataclass
class RunContext:
    """What a command's ``run`` gets: parsed arguments, config, output folder and backend."""

    command: str
    args: argparse.Namespace
    config: Config
    out: RunDir | None  # None for a command that writes nothing this time (writes_files)
    backend: BackendInfo | None
    quiet: bool

    def log(self, message: str) -> None:
        print(message, flush=True)


def _available_commands(names: tuple[str, ...] = COMMAND_NAMES) -> dict[str, ModuleType]:
    modules = {}
    for name in names:
        try:
            modules[name] = importlib.import_module(f"ti_fusion.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"ti_fusion.cli.{name}":
                raise
    return modules


def _add_common(parser: argparse.ArgumentParser, module: ModuleType, help_texts: bool = True) -> None:
    g = parser.add_argument_group("common options")
    positional = getattr(module, "OUT_FROM_POSITIONAL", None)
    if positional is None:
        g.add_argument("--out", metavar="DIR",
                       help="output folder, new or empty (default: logs/<command>-<YYYYmmdd-HHMMSS-mmm>/)")
    g.add_argument("--overwrite", action="store_true",
                   help=f"replace the earlier run in {positional.upper() if positional else '--out'} "
                        "(its files are removed first)")
    g.add_argument("--quiet", action="store_true", help="no progress bar and no informational lines")
    g.add_argument("--config", metavar="FILE", help="config file (.toml, .yaml or .json); every key with its "
                   "default and unit: docs/CONFIG.md")
    g.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override one config value, e.g. --set icp.dist_threshold=0.05 (repeatable)")
    if getattr(module, "USES_TAICHI", False):
        g.add_argument("--arch", choices=ARCH_CHOICES, default="cpu",
                       help="Taichi backend; auto tries cuda, then vulkan, then cpu (default: cpu)")
    if getattr(module, "USES_DATASET", False):
        d = parser.add_argument_group("dataset options")
        d.add_argument("data", nargs="?", default="", metavar="DATA",
                       help="dataset folder (TUM, ICL-NUIM, 7-Scenes, or a plain folder with --format folder) or "
                            "ROS bag (a ROS 1 .bag, e.g. a RealSense recording; a rosbag2 folder or an .mcap file); "
                            "omitted: the embedded synthetic sequence")
        d.add_argument("--frames", type=int, default=None, metavar="N", help="number of frames (from --start)")
        add_flags(d, module.__name__.rsplit(".", 1)[-1], help_texts)


def build_parser(only: str | None = None, help_texts: bool = True) -> tuple[argparse.ArgumentParser,
                                                                            dict[str, ModuleType]]:
    """The command line's parser and the commands' modules; with ``only`` (a command's name), that command's
    alone: the other commands' modules import Taichi and the kernels, which ``batch``'s driver never needs.
    Without ``help_texts``, the dataset options have no help text (``add_flags``): for a command line that asks
    for no help (``_asks_for_help``)."""
    parser = argparse.ArgumentParser(
        prog="ti-fusion",
        description="Dense RGB-D SLAM with point-to-plane ICP and surfel fusion on Taichi kernels.",
    )
    parser.add_argument("--version", action="version", version=f"ti-fusion {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = _available_commands((only,) if only in COMMAND_NAMES else COMMAND_NAMES)
    for name, module in modules.items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        _add_common(p, module, help_texts)
    return parser, modules


def _apply_dataset_args(args: argparse.Namespace, config: Config) -> None:
    """DATA, the dataset options (``ti_fusion/cli/options.py``) and --frames set on the config. Frame options
    are counts and positions, never Python's from-the-end indices."""
    if getattr(args, "data", ""):
        config.dataset.path = args.data
    if args.frames is not None and args.frames < 1:
        raise InputError(None, f"--frames {args.frames}: must be at least 1")
    apply_flags(args, config)
    if args.start is not None and args.stop is not None and args.stop <= args.start:
        raise InputError(None, f"--stop {args.stop} must be greater than --start {args.start}")
    if args.frames is not None and args.stop is not None:
        raise InputError(None, "give --frames or --stop, not both")
    ds = config.dataset
    if args.frames is not None:
        ds.stop = ds.start + args.frames * ds.stride
        config.synth.frames = max(config.synth.frames, ds.stop) if ds.path == "" else config.synth.frames


def _check_out_holds_no_input(out: str | None, inputs: list[str], option: str) -> None:
    """The output folder must not be an input or hold one (the dataset, the log to inspect): replacing an
    earlier run there would delete it."""
    if not out:
        return
    out_path = Path(out).resolve()
    for given in filter(None, inputs):
        path = Path(given).resolve()
        if path == out_path or out_path in path.parents:
            raise InputError(None, f"{option} {out} holds the input {given}: choose another {option}")


class _TerminalHandler(logging.Handler):
    """Shows the package's log records: warnings on stderr always, information on stdout unless --quiet
    (except a record marked ``essential``: the format line, what was understood of the input)."""

    def __init__(self, command: str, quiet: bool):
        super().__init__(logging.INFO)
        self.command, self.quiet = command, quiet

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.levelno >= logging.WARNING:
            print(f"ti-fusion {self.command}: warning: {message}", file=sys.stderr, flush=True)
        elif not self.quiet or getattr(record, "essential", False):
            print(message, flush=True)


@contextmanager
def _terminal_logging(command: str, quiet: bool):
    logger = logging.getLogger("ti_fusion")
    handler = _TerminalHandler(command, quiet)
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


@contextmanager
def _stop_signals_raise():
    """SIGTERM and SIGHUP raise ``Stopped`` in the main thread, Ctrl-C ``KeyboardInterrupt``; later SIGTERMs
    and SIGHUPs are ignored while the run writes what it has (SIGKILL still ends it at once). A stop that
    arrives during a write that must not be cut in two (``ti_fusion.interrupts.critical``: the log's) is
    raised when the write ends. The first Ctrl-C during the loop over an endless stream (a live camera's)
    ends that loop instead, and the run finishes normally (``ti_fusion.interrupts.end_stream``). Handlers
    are restored afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    outer = sys._getframe(2)  # the ``with`` statement's (below contextlib's __enter__): imports from here on count

    def stop(signum, frame):
        if after_import(signum, frame, outer):
            return
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        interrupt(Stopped(signum))

    def ctrl_c(signum, frame):
        if after_import(signum, frame, outer):
            return
        if end_stream():  # a live camera's: the run ends as at a recording's end, with its map
            _say_from_handler(FINISHING)
            return
        interrupt(KeyboardInterrupt())

    previous = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not when Ctrl-C is ignored
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, ctrl_c)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _say_from_handler(line: str) -> None:
    """One line on stderr from a signal handler: to the file descriptor itself, since the handler may run
    inside a write to ``sys.stderr`` (the progress bar's), which the buffered stream refuses to re-enter."""
    try:
        text = ("\r\x1b[K" if sys.stderr.isatty() else "") + line + "\n"  # \r\x1b[K: over the progress bar
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # stderr captured in-process
        print(line, file=sys.stderr)
        return
    try:
        os.write(fd, text.encode())
    except OSError:  # nobody reads stderr any more: the run still finishes
        pass


def _announce_compiling(quiet: bool) -> None:
    """Say on the terminal that kernels are being compiled: at once when Taichi's kernel cache is empty (a
    first run), else when the first kernel that was not in it has compiled."""
    from ti_fusion.frontend import CLOCK, offline_cache_files

    CLOCK.__init__()  # this run's kernels (an earlier run in this process, e.g. a test's, compiled its own)
    cache = offline_cache_files()
    if cache is not None and cache[1] == 0:
        if not quiet:
            print(f"compiling kernels: the kernel cache ({cache[0]}) is empty, so this first run compiles each kernel "
                  "as it is first used (up to a minute on 2 cores); later runs load them from the cache", flush=True)
        CLOCK.notice = None
    elif not quiet:
        CLOCK.notice = lambda seconds: print(f"compiling kernels that are not in the kernel cache (the first run "
                                             f"after ti-fusion or Taichi changed; {seconds:.1f} s for the first)",
                                             flush=True)


def _silence_clock() -> None:
    if "ti_fusion.frontend" in sys.modules:
        sys.modules["ti_fusion.frontend"].CLOCK.notice = None


def _kernel_times(quiet: bool) -> dict:
    """The summary's kernel compile figures, said on the terminal when kernels were compiled."""
    from ti_fusion.frontend import CLOCK

    CLOCK.notice = None
    here = CLOCK.compile_s - CLOCK.elsewhere_s
    if CLOCK.compiled and not quiet:
        beside = f", {CLOCK.elsewhere_s:.1f} s of it in the frame reader process" if CLOCK.elsewhere_s else ""
        print(f"kernels: {CLOCK.compiled} compiled in {CLOCK.compile_s:.1f} s{beside} (and "
              f"{CLOCK.instances - CLOCK.compiled} loaded from the cache or compiled quickly, "
              f"{CLOCK.seconds - here:.1f} s)", flush=True)
    return {"kernel_instances": CLOCK.instances, "kernels_compiled": CLOCK.compiled,
            "kernel_first_launch_s": round(CLOCK.seconds, 2), "kernel_compile_s": round(CLOCK.compile_s, 2),
            "kernel_compile_elsewhere_s": round(CLOCK.elsewhere_s, 2),
            "kernels_compiled_s": {k: round(v, 2) for k, v in sorted(CLOCK.by_kernel.items(), key=lambda kv: -kv[1])}}


def _os_error_line(exc: OSError) -> str:
    reason = exc.strerror or str(exc)
    return f"{exc.filename}: {reason}" if exc.filename else reason


def _first_cause(exc: BaseException) -> BaseException:
    """The first of a chain of write failures: a full disk fails every later write too (the trajectory and
    the log's footer written on the way out), and the first one says where it began."""
    if not isinstance(exc, (OutputError, OSError)):
        return exc
    first, e, seen = exc, exc, set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OutputError):
            first = e
        e = e.__cause__ or e.__context__
    return first


# A value that starts with a minus sign and a digit ("-525,525,319.5,239.5"): argparse takes it for an option
# unless it is one plain negative number, so "--intrinsics -525,..." would fail with "expected one argument".
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


def _value_options(parser: argparse.ArgumentParser) -> set[str]:
    """The long options of the parser and its sub-commands that take one value."""
    found = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= _value_options(sub)
        elif action.nargs is None and action.option_strings:
            found |= {o for o in action.option_strings if o.startswith("--")}
    return found


def _join_negative_values(argv: list[str], options: set[str]) -> list[str]:
    """``--option -1,2`` as ``--option=-1,2`` for ``options`` that take a value, so that the option's own
    check says what is wrong with it."""
    out, i = [], 0
    while i < len(argv):
        token = argv[i]
        if token in options and i + 1 < len(argv) and _NEGATIVE_VALUE.match(argv[i + 1]):
            out.append(f"{token}={argv[i + 1]}")
            i += 2
        else:
            out.append(token)
            i += 1
    return out


def _asks_for_help(argv: list[str]) -> bool:
    """Whether ``argv`` may ask argparse for a help text: any --h... token (argparse takes abbreviations of --help)
    or short-flag token with an h in it (-h, or -h among other short flags), whatever it turns out to be."""
    return any(token.startswith("--h") or (token[:1] == "-" and token[1:2] != "-" and "h" in token)
               for token in argv)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, modules = build_parser(argv[0] if argv else None, _asks_for_help(argv))
    args = parser.parse_args(_join_negative_values(argv, _value_options(parser)))
    if not args.command:
        parser.print_help()
        return 0
    with _stop_signals_raise(), _terminal_logging(args.command, args.quiet):
        return _run(args, modules[args.command])


def command() -> None:
    """The ``ti-fusion`` command and ``python -m ti_fusion``: ``main()``, then ``end_process`` with its code."""
    gc.freeze()  # what the imports made so far lives to the process's end: the run's full collections skip it
    end_process(main())


def end_process(code: int) -> None:
    """End the process with exit status ``code`` as ``sys.exit`` would, less the interpreter's teardown of every
    module and object (docs/PERFORMANCE.md, "The warm run's fixed cost"): the atexit handlers run, Taichi is reset
    (which writes the kernels this process compiled into the offline cache, as its teardown would) and stdout and
    stderr are flushed, then ``os._exit``. Where the interpreter would still wait for another thread, where a
    profiler, tracer or debugger watches the process or ``python -i`` asked for a prompt (each acts after the
    command returns: ``python -m cProfile -o FILE -m ti_fusion`` writes FILE then), or where a flush fails (a
    reader that went away), ``sys.exit`` ends it the usual way. For the command line only: a caller's own
    process (a notebook, a test) is not to be ended."""
    if any(t is not threading.main_thread() and not t.daemon and t.is_alive() for t in threading.enumerate()) or \
            sys.getprofile() is not None or sys.gettrace() is not None or sys.flags.inspect:
        sys.exit(code)
    import atexit

    atexit._run_exitfuncs()  # (what the interpreter runs first at its exit; it clears them: none runs twice)
    taichi = sys.modules.get("taichi")
    if taichi is not None and taichi.lang.impl.get_runtime().prog is not None:
        taichi.reset()
    try:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
    except (OSError, ValueError):
        sys.exit(code)
    os._exit(code if isinstance(code, int) else 1)


def _write_partial_summary(command: str, out: RunDir | None, exc: TiFusionError) -> None:
    """summary.json of the frames a run did before ``exc`` (which carries them as ``partial_summary``), with
    the error's line; nothing when the run did no frame or the summary cannot be written."""
    partial = dict(getattr(exc, "partial_summary", None) or {})
    if out is None or out.adding or not partial:
        return
    summary = base_summary(command, partial.pop("frames", 0), partial.pop("wall_s", 0.0),
                           partial.pop("ms_per_stage", {}))
    summary.update(partial)
    summary["error"] = str(_first_cause(exc))
    try:
        out.write_summary(summary)
    except (TiFusionError, OSError):  # the first error is the one to report
        pass


def _run(args: argparse.Namespace, module: ModuleType) -> int:
    command = args.command
    out: RunDir | None = None
    try:
        try:
            config = load_config(args.config, args.set)
            if getattr(module, "USES_DATASET", False):
                _apply_dataset_args(args, config)
            if args.quiet:
                config.log.progress = False
            positional = getattr(module, "OUT_FROM_POSITIONAL", None)  # a command whose positional names its output
            out_arg = getattr(args, positional) if positional else args.out
            inputs = [config.dataset.path if getattr(module, "USES_DATASET", False) else "", getattr(args, "log", ""),
                      getattr(args, "map", ""), getattr(args, "manifest", "")]
            _check_out_holds_no_input(out_arg, inputs, positional.upper() if positional else "--out")
            # A command that writes files only when asked (inspect) makes no folder otherwise; one that derives
            # files from a run (mesh RUN_DIR) writes them beside the run's own unless --out says otherwise.
            writes = getattr(module, "writes_files", lambda a: True)(args)
            adds_to = getattr(module, "adds_to_run", lambda a: None)(args)
            out = RunDir(command, adds_to or out_arg, overwrite=args.overwrite,
                         resume=getattr(module, "RESUMES_OUT", False), add_to=bool(adds_to)) if writes else None
            backend = init_backend(args.arch) if getattr(module, "USES_TAICHI", False) else None
            if backend is not None and not args.quiet:
                print(f"backend: {backend.arch} ({backend.reason})", flush=True)
            if backend is not None:
                _announce_compiling(args.quiet)
            ctx = RunContext(command, args, config, out, backend, args.quiet)
            watch = Stopwatch()
            result = module.run(ctx) or {}
            code = result.pop("exit_code", 0)
            wall = watch.ms / 1e3
            summary = base_summary(command, result.pop("frames", 0), result.pop("wall_s", wall),
                                   result.pop("ms_per_stage", {}))
            if backend is not None:
                summary["backend"] = backend.arch
                summary.update(_kernel_times(args.quiet))
            summary.update(result)
            if out is not None and out.adding:  # the run's own summary.json stays the run's
                print(f"outputs written to {out.path}/ beside the run's", flush=True)
            elif out is not None:
                path = out.write_summary(summary)
                print(f"outputs written to {out.path}/ (summary: {path})", flush=True)
            return code
        except TiFusionError as exc:  # a late error: the frames done so far still get their summary.json
            _write_partial_summary(command, out, exc)
            raise
        finally:
            if out is not None:
                out.release()
            _silence_clock()  # a run that failed does not leave its notice to the process's later kernels
    except BrokenPipeError:
        # Whoever read our output stopped reading (| head): say nothing more, and let the interpreter's
        # final flush of stdout go nowhere instead of failing again.
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError):  # stdout is not a file (captured in-process)
            pass
        return 128 + 13  # as a process killed by SIGPIPE (13)
    except TiFusionError as exc:
        print(f"ti-fusion {command}: error: {_first_cause(exc)}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:
        cause = _first_cause(exc)
        line = _os_error_line(cause) if isinstance(cause, OSError) else str(cause)
        print(f"ti-fusion {command}: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        how = f"stopped by {signal.Signals(exc.signum).name}" if isinstance(exc, Stopped) else "interrupted"
        kept = (f"; what was written is in {out.path}/" if out is not None and out.path.is_dir()
                else "; nothing was written")
        print(f"ti-fusion {command}: {how}{kept}", file=sys.stderr, flush=True)
        return 128 + exc.signum if isinstance(exc, Stopped) else 130


if __name__ == "__main__":
    command()
