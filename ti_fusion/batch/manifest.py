"""The batch manifest: which ``ti-fusion slam`` runs a batch makes, every one checked before any starts.

A manifest is TOML, YAML or JSON::

    [defaults]                       # options every job gets (any key an input takes); optional
    downsample = 2
    frames = 30

    [[inputs]]                       # one or more
    name = "room"                    # the job's name (default: the data folder's name, or synthetic-<scene>)
    scene = "room"                   # no data: a synthetic scene

    [[inputs]]
    data = "../shared/data/redkitchen-7scenes"    # relative paths are relative to the manifest's folder

    [[variants]]                     # optional: every input runs once per variant
    name = "default"

    [[variants]]
    name = "depth-only"
    set = ["icp.color_weight=0"]

An option key is a ``ti-fusion slam`` option with ``_`` for ``-`` (``depth_scale``, ``no_relocalise = true``,
``set`` a list of ``SECTION.KEY=VALUE``, ``config``, ``arch``), ``data`` for DATA, and two of the batch's
own: ``threads`` (the CPUs the job asks Ray for, and its Taichi's CPU threads: locally up to twice as many,
``runner.taichi_threads``) and ``gpus`` (the GPUs it asks Ray for; default 1 with ``arch`` cuda or vulkan).
Options merge defaults < input < variant, and ``set`` lists are joined in that order (the last value of a
key wins, as on the command line). The keys are read from ``ti-fusion slam``'s own parser, so a new slam
option is a manifest key with no change here.

``read_manifest`` checks what the slam run itself would check first (the option's type and choices, the
config file and every ``--set`` against the typed config, the frame options, DATA and files that exist)
and raises ``InputError(manifest, "<where>: <problem>")``: one line before any job starts.
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ti_fusion.errors import InputError

# Options a batch job cannot take: the batch owns the run folder and the terminal, and a job has no camera.
NOT_IN_MANIFEST = {"help", "out", "overwrite", "quiet", "live", "camera"}
BATCH_KEYS = {"threads", "gpus"}          # the batch's own keys, not slam options
PATH_KEYS = ("data", "config", "trajectory", "ground_truth")                # always files or folders
MAYBE_PATH_KEYS = ("intrinsics", "color_intrinsics", "color_extrinsics")  # a file, or numbers / a topic
GPU_ARCHES = ("cuda", "vulkan")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")


@dataclass(frozen=True)
class Job:
    """One ``ti-fusion slam`` run of the batch."""

    name: str                   # unique in the batch: its run folder runs/<name>/ and its record jobs/<name>.json
    input: str
    variant: str                # "" when the manifest has no variants
    args: tuple[str, ...]       # ti-fusion slam's arguments, without --out (the batch adds it)
    threads: int                # the CPUs the job asks Ray for (Taichi's threads: runner.taichi_threads)
    gpus: float                 # the GPUs the job asks Ray for


@dataclass(frozen=True)
class Manifest:
    path: Path
    jobs: tuple[Job, ...]
    inputs: tuple[str, ...]
    variants: tuple[str, ...]


def slam_options() -> dict[str, argparse.Action]:
    """``ti-fusion slam``'s options by destination (``data`` for DATA), from the CLI's own parser."""
    return {a.dest: a for a in _slam_parser()._actions if a.dest not in NOT_IN_MANIFEST}


def _slam_parser() -> argparse.ArgumentParser:
    from ti_fusion.cli.main import build_parser

    parser, _ = build_parser("slam")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices["slam"]
    raise RuntimeError("ti-fusion has no slam command")


def read_manifest(path: str | Path, default_threads: int = 1) -> Manifest:
    """The manifest's jobs (inputs × variants, input-major), each checked; InputError names the problem."""
    path = Path(path)
    data = _read(path)
    unknown = set(data) - {"defaults", "inputs", "variants"}
    if unknown:
        raise InputError(path, f"unknown key {_first(unknown)!r} at the top level (known: defaults, inputs, variants)")
    options = slam_options()
    base = path.resolve().parent
    defaults = _section(path, data.get("defaults", {}), "defaults", options, base, named=False)
    inputs = data.get("inputs")
    if not isinstance(inputs, list) or not inputs:
        raise InputError(path, "no inputs: add at least one [[inputs]] entry (data = \"FOLDER\", or scene = \"room\")")
    inputs = [_section(path, entry, f"inputs[{k}]", options, base) for k, entry in enumerate(inputs)]
    raw_variants = data.get("variants")
    if raw_variants is not None and (not isinstance(raw_variants, list) or not raw_variants):
        raise InputError(path, "variants: expected a list of [[variants]] entries (or none at all)")
    variants = [_section(path, entry, f"variants[{k}]", options, base, variant=True)
                for k, entry in enumerate(raw_variants or [])]
    _name_all(path, inputs, "inputs", _input_name)
    _name_all(path, variants, "variants", lambda v, k: f"v{k + 1}")
    parser = _quiet_parser(_slam_parser())
    for v in variants:  # a variant's --set alone, so that its error names the variant
        _check_config(path, v["_where"], v.get("config"), v.get("set", []))
    jobs = []
    for inp in inputs:
        for var in variants or [None]:
            jobs.append(_job(path, parser, options, defaults, inp, var, default_threads))
    names = [j.name for j in jobs]
    twice = next((n for n in names if names.count(n) > 1), None)
    if twice is not None:  # "a--b" x "c" and "a" x "b--c": one run folder for two jobs
        raise InputError(path, f"two jobs are named {twice!r}: rename an input or a variant")
    return Manifest(path, tuple(jobs), tuple(i["_name"] for i in inputs), tuple(v["_name"] for v in variants))


# -- reading --------------------------------------------------------------------------------------------
def _read(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "manifest not found")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the manifest: {exc}") from None
    try:
        if path.suffix == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            data = tomllib.loads(text)
        elif path.suffix in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text) or {}
        elif path.suffix == ".json":
            data = json.loads(text)
        else:
            raise InputError(path, "a manifest is .toml, .yaml/.yml or .json")
    except InputError:
        raise
    except Exception as exc:  # each reader's own parse error, in one line
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) if mark is not None else None
        raise InputError(path, f"cannot parse the manifest: {where}{problem or ' '.join(str(exc).split())}") from None
    if not isinstance(data, dict):
        raise InputError(path, "the manifest's top level must be a table (defaults, inputs, variants)")
    return data


def _first(keys) -> str:
    return sorted(map(str, keys))[0]


def _section(path: Path, entry: Any, where: str, options: dict, base: Path, named: bool = True,
             variant: bool = False) -> dict:
    """One table of options, its keys checked and normalised (``-`` → ``_``), paths resolved against ``base``."""
    if not isinstance(entry, dict):
        raise InputError(path, f"{where}: expected a table of options, got {type(entry).__name__}")
    known = set(options) | BATCH_KEYS | ({"name"} if named else set())
    if variant:
        known.discard("data")  # the input is the input's; a variant changes how it runs
    out: dict[str, Any] = {"_where": where}
    for raw_key, value in entry.items():
        key = str(raw_key).replace("-", "_")
        if key not in known:
            hint = " (a variant changes how an input runs; put data in [[inputs]])" if variant and key == "data" else ""
            raise InputError(path, f"{where}: unknown key {raw_key!r}{hint} (known: {', '.join(sorted(known))})")
        out[key] = _value(path, where, key, value, options.get(key))
    for key in PATH_KEYS + MAYBE_PATH_KEYS:
        if isinstance(out.get(key), str) and out[key]:
            resolved = base / Path(out[key]).expanduser()
            if key in PATH_KEYS or resolved.exists():
                out[key] = str(resolved.resolve())
    if "name" in out:
        out["_where"] = f"{where} ({out['name']})"
    return out


def _value(path: Path, where: str, key: str, value: Any, action: argparse.Action | None) -> Any:
    def bad(expected: str):
        return InputError(path, f"{where}: {key} = {json.dumps(value, default=str)}: expected {expected}")

    if key == "name":
        if not isinstance(value, str) or not _NAME.match(value):
            raise bad("a name of letters, digits, '.', '_', '+' or '-' (it names the job's run folder)")
        return value
    if key == "threads":
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise bad("a whole number of threads, at least 1")
        return value
    if key == "gpus":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise bad("a number of GPUs, 0 or more")
        return value
    if action is not None and isinstance(action, argparse._AppendAction):
        values = [value] if isinstance(value, str) else value
        if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
            raise bad('a list of texts, e.g. ["icp.color_weight=0"]')
        return list(values)
    if action is not None and action.nargs == 0:  # a flag
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise bad("a text or a number")
    return value


def _input_name(entry: dict, k: int) -> str:
    if entry.get("data"):
        return Path(entry["data"]).name or f"input{k + 1}"
    if entry.get("trajectory"):
        return f"synthetic-{entry.get('scene', 'room')}-{Path(entry['trajectory']).stem}"
    return f"synthetic-{entry.get('scene', 'room')}"


def _name_all(path: Path, entries: list[dict], what: str, default) -> None:
    seen: dict[str, str] = {}
    for k, entry in enumerate(entries):
        name = entry.get("name") or default(entry, k)
        name = re.sub(r"[^A-Za-z0-9._+-]", "_", name)
        if name in seen:
            raise InputError(path, f"{entry['_where']}: two {what} are named {name!r} ({seen[name]} too): "
                                   "give each its own name")
        seen[name] = entry["_where"]
        entry["_name"] = name


# -- one job ----------------------------------------------------------------------------------------------
class _ParseError(Exception):
    pass


def _quiet_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The slam parser raising its complaint instead of printing usage and exiting."""
    def error(message):
        raise _ParseError(message)

    parser.error = error
    return parser


def _argv(options: dict, order: list[str], actions: dict) -> list[str]:
    argv = [options["data"]] if options.get("data") else []
    for key in order:
        if key in ("data", "name") or key in BATCH_KEYS or key not in options:
            continue
        action, value = actions[key], options[key]
        flag = next(o for o in action.option_strings if o.startswith("--"))
        if isinstance(action, argparse._AppendAction):
            argv += [f"{flag}={v}" for v in value]
        elif action.nargs == 0:
            argv += [flag] if value else []
        else:
            argv.append(f"{flag}={value}")
    return argv


def _merge(*sections: dict | None) -> dict:
    out: dict[str, Any] = {}
    for s in sections:
        for key, value in (s or {}).items():
            if key.startswith("_"):
                continue
            out[key] = out.get(key, []) + value if key == "set" else value
    return out


def _job(path: Path, parser, actions: dict, defaults: dict, inp: dict, var: dict | None,
         default_threads: int) -> Job:
    options = _merge(defaults, inp, var)
    name = inp["_name"] + (f"--{var['_name']}" if var is not None else "")
    where = f"job {name}"
    args = _argv(options, list(actions), actions)
    try:
        ns = parser.parse_args(args)
    except _ParseError as exc:
        raise InputError(path, f"{where}: {exc}") from None
    _check_config(path, where, ns.config, ns.set, ns)
    for key in ("data", "trajectory", "ground_truth"):
        value = getattr(ns, key, None)
        if value and not Path(value).exists():
            raise InputError(path, f"{where}: {key} {value}: no such file or folder")
    arch = options.get("arch", actions["arch"].default if "arch" in actions else "cpu")
    gpus = options.get("gpus", 1 if arch in GPU_ARCHES else 0)
    return Job(name, inp["_name"], var["_name"] if var is not None else "", tuple(args),
               int(options.get("threads", default_threads)), float(gpus))


def _check_config(path: Path, where: str, config_file, sets, ns=None) -> None:
    """The config file and every ``--set`` against the typed config, and the dataset options as the run
    applies them (``--frames 0``, ``--scene`` with DATA), as the job's own run would at its start."""
    from ti_fusion.config import load_config

    try:
        config = load_config(config_file, list(sets or []))
        if ns is not None:
            from ti_fusion.cli.main import _apply_dataset_args

            _apply_dataset_args(ns, config)
    except InputError as exc:
        raise InputError(path, f"{where}: {exc}") from None
