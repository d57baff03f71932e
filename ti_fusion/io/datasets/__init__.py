"""Dataset loaders: one per format, one interface (``Dataset``), and format detection.

A format is detected only from files that identify it: TUM RGB-D from ``depth.txt``, ICL-NUIM from its
``*.gt.freiburg`` ground truth, 7-Scenes from its ``frame-XXXXXX.depth.png`` names. A folder with none of
them, or with the files of two formats, is refused with a line naming the ``--format`` to pass: the
format fixes the depth scale and the intrinsics, and a wrong guess gives wrong depths without any error.
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame

__all__ = ["Dataset", "Frame", "open_dataset", "detect_format", "loader_class", "FORMATS"]

FORMATS = ("tum", "iclnuim", "7scenes", "synthetic")

log = logging.getLogger(__name__)

# format → (module, class). Modules are imported on demand, so one format's import problem cannot break
# the others.
_LOADERS = {
    "tum": (".tum", "TUMDataset"),
    "iclnuim": (".iclnuim", "ICLNUIMDataset"),
    "7scenes": (".sevenscenes", "SevenScenesDataset"),
    "synthetic": (".synthetic", "SyntheticDataset"),
}


def loader_class(fmt: str) -> type:
    """The Dataset subclass of format ``fmt``."""
    if fmt not in _LOADERS:
        raise InputError(None, f"unknown dataset format {fmt!r}: choose one of auto, {', '.join(FORMATS)}")
    module, name = _LOADERS[fmt]
    return getattr(importlib.import_module(module, __name__), name)


def detect(root: Path) -> tuple[str, str]:
    """(format, the file that identifies it) of a dataset folder; InputError when none or several match."""
    root = Path(root)
    if not root.exists():
        raise InputError(root, "dataset folder does not exist")
    if not root.is_dir():
        raise InputError(root, "not a folder (give the dataset's folder)")
    found = {}
    for fmt in _LOADERS:
        evidence = loader_class(fmt).detect(root)
        if evidence:
            found[fmt] = evidence
    if len(found) == 1:
        return next(iter(found.items()))
    if found:
        which = ", ".join(f"{fmt} ({evidence})" for fmt, evidence in found.items())
        raise InputError(root, f"holds the files of more than one format: {which}; pass "
                               + " or ".join(f"--format {fmt}" for fmt in found))
    from ti_fusion.io.datasets.iclnuim import numbered_pngs

    if numbered_pngs(root / "depth"):
        raise InputError(root, "depth/ holds numbered PNGs, but no file says which dataset they come from, so "
                               "their depth scale and intrinsics are unknown: if it is ICL-NUIM (5000 units per "
                               "metre, its published intrinsics), pass --format iclnuim")
    raise InputError(root, "unrecognised dataset layout: expected TUM (depth.txt), ICL-NUIM (*.gt.freiburg) "
                           "or 7-Scenes (frame-XXXXXX.depth.png); or pass --format")


def detect_format(root: Path) -> str:
    """The format of a dataset folder (see ``detect``)."""
    return detect(root)[0]


def open_dataset(cfg: DatasetConfig, synth: SynthConfig | None = None) -> Dataset:
    """The dataset ``cfg`` names; with an empty path, the embedded synthetic sequence.

    Refuses (``InputError``) a selection of no frame and a downsampling that leaves frames too small;
    logs the format line (``Dataset.describe_format``) for the CLI to print.
    """
    common = dict(downsample=cfg.downsample, start=cfg.start, stop=cfg.stop, stride=cfg.stride)
    if not cfg.path:
        if cfg.format not in ("auto", "synthetic"):
            raise InputError(None, f"format {cfg.format} needs a dataset folder (DATA)")
        dataset = loader_class("synthetic").from_config(synth or SynthConfig(), **common)
        dataset.check_selection()
        return dataset
    root = Path(cfg.path)
    fmt = cfg.format
    if fmt == "synthetic":
        raise InputError(root, "format synthetic is the embedded sequence: give no DATA folder with it")
    if fmt == "auto":
        fmt, evidence = detect(root)
        how = f"detected from {evidence}"
    else:
        if not root.is_dir():
            raise InputError(root, "not a folder (give the dataset's folder)" if root.exists()
                             else "dataset folder does not exist")
        loader_class(fmt)  # an unknown name fails here, before the folder is read
        how = "given by --format or dataset.format"
    dataset = loader_class(fmt)(root, config=cfg, **common)
    dataset.format_from = how
    dataset.check_selection()
    log.info(dataset.describe_format())
    return dataset
