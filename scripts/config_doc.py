"""Write docs/CONFIG.md, the list of every config key, from ti_fusion/config.py itself.

    python scripts/config_doc.py          # rewrite docs/CONFIG.md
    python scripts/config_doc.py --check  # exit 1 when docs/CONFIG.md is not what config.py gives

Each key's default and what it allows come from its dataclass field and annotation, its meaning from the
comment beside it in config.py (``ti_fusion.config.field_docs``, which the command-line options' help reads
too), so the page cannot drift from the code (tests/test_config.py runs the check). The main settings come first, then the tuning knobs (``ti_fusion.config.ADVANCED``) apart, then
the settings that were removed (``ti_fusion.config.REMOVED``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from ti_fusion.cli.options import option
from ti_fusion.config import ADVANCED, REMOVED, RENAMED_SECTIONS, Config, field_docs, rules

DOC = Path(__file__).resolve().parent.parent / "docs" / "CONFIG.md"

# One line per section: what it configures.
SECTIONS = {
    "dataset": "The input: which frames, their depth units, intrinsics, topics and colour camera",
    "synth": "The embedded synthetic sequence (used when `dataset.path` is empty): scene, size, sensor noise",
    "pyramid": "The frame's pyramid that tracking aligns and fusion merges (depth smoothing, depth, vertex and "
               "normal maps per level)",
    "icp": "Dense tracking: projective point-to-plane ICP, with the optional photometric term",
    "fusion": "The surfel map: its size, the level it is built at, merging and removal",
    "slam": "The tracking loop around ICP: motion model, failure checks, re-localisation, loop closure on/off",
    "vo": "Feature odometry (`ti-fusion vo`, the ICP initialiser and the re-localiser): ORB, matching, PnP",
    "loop": "Loop closure (with `slam.loop_closure`): keyframes, place recognition, verification, pose graph",
    "mesh": "The triangle mesh (`ti-fusion mesh`, `slam --mesh`)",
    "map": "The saved map a slam run leaves for a later one (docs/MAPS.md)",
    "log": "The MCAP log and the terminal",
}

HEAD = """# Configuration

Every setting of `ti-fusion`, generated from `ti_fusion/config.py` by `python scripts/config_doc.py`
(do not edit by hand: `tests/test_config.py` fails when this page and the code differ).

Set them in a config file given with `--config FILE` (TOML, YAML or JSON; one table per section) or one at
a time with `--set SECTION.KEY=VALUE` (repeatable), e.g.

```toml
[dataset]
downsample = 2

[icp]
iterations = [10, 5, 4]   # coarse to fine
dist_threshold = 0.10
```

```
ti-fusion slam DATA --config my.toml --set icp.dist_threshold=0.05
```

Keys shown with an option (`dataset.depth_scale` (`--depth-scale`)) are also options of the commands that
read frames (`slam`, `vo`, `fuse`, `icp`), with the meaning below as their `--help`.

Defaults, then the file, then `--set`, then those options. Every value is checked against what its key
allows (the column below): a value that breaks it, an unknown key or a removed one stops the run with one
line naming the key. Relative paths in a config file are relative to the file's folder. Lengths are in
metres, angles in degrees unless a key says otherwise. From Python: `ti_fusion.config.load_config(path, ["icp.dist_threshold=0.05"])`.

The **main settings** are the ones a run is usually given. The **advanced settings** are tuning knobs:
their defaults are what the benchmarks settled on ([BENCHMARKS.md](BENCHMARKS.md)), and most runs should
leave them alone.
"""


def _default(value) -> str:
    if value is None:
        return "None"
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, float):
        return f"`{value:g}`"
    if isinstance(value, int):
        return f"`{value:,}`".replace(",", "_") if value >= 100_000 else f"`{value}`"
    return f"`{value}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _table(section: str, keys: list[str], comments: dict) -> list[str]:
    values = getattr(Config(), section)
    section_type = type(values)
    section_rules = rules(section_type)
    rows = ["| key | default | allowed | meaning |", "| --- | --- | --- | --- |"]
    for key in keys:
        meaning = comments.get((section_type.__name__, key), "")
        flag = f" (`{option(key)}`)" if section_rules[key].flag is not None else ""
        rows.append(f"| `{section}.{key}`{flag} | {_default(getattr(values, key))} | "
                    f"{_cell(section_rules[key].describe())} | {_cell(meaning)} |")
    return rows


def render() -> str:
    comments = field_docs()
    sections = [f.name for f in dataclasses.fields(Config)]
    keys = {s: [f.name for f in dataclasses.fields(type(getattr(Config(), s)))] for s in sections}
    main = {s: [k for k in keys[s] if k not in ADVANCED.get(s, ())] for s in sections}
    advanced = {s: [k for k in keys[s] if k in ADVANCED.get(s, ())] for s in sections}
    n_main, n_advanced = sum(map(len, main.values())), sum(map(len, advanced.values()))
    out = [HEAD, f"{n_main + n_advanced} keys: {n_main} main, {n_advanced} advanced.", "", "## Main settings", ""]
    for s in sections:
        if main[s]:
            out += [f"### [{s}]", "", SECTIONS[s] + ".", ""] + _table(s, main[s], comments) + [""]
    out += ["## Advanced settings (tuning knobs)", "",
            "The same sections as above (`--set icp.min_inliers=200`, `[icp]` in a file); listed apart because "
            "their defaults are settled.", ""]
    for s in sections:
        if advanced[s]:
            out += [f"### [{s}], advanced", ""] + _table(s, advanced[s], comments) + [""]
    out += ["## Removed settings", "",
            "Setting one of these stops the run with one line saying it was removed and why; what the settled "
            "ones measured is in [BENCHMARKS.md](BENCHMARKS.md#settled-and-removed-settings).", "",
            "| key | why |", "| --- | --- |"]
    out += [f"| `{s}.{k}` | {_cell(why)} |" for (s, k), why in sorted(REMOVED.items())]
    out += [f"| `[{s}]` | renamed: {_cell(why)} |" for s, why in sorted(RENAMED_SECTIONS.items())]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/CONFIG.md is out of date")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        if not DOC.is_file() or DOC.read_text(encoding="utf-8") != text:
            print(f"{DOC} is out of date: run python scripts/config_doc.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
