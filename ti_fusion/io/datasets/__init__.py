"""Dataset loaders: one per format, one interface (``Dataset``), and format auto-detection."""

from __future__ import annotations

import importlib
from pathlib import Path

from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame

__all__ = ["Dataset", "Frame", "open_dataset", "detect_format", "loader_class", "FORMATS"]

FORMATS = ("tum", "iclnuim", "7scenes", "synthetic")


# format → (module, class). Order matters for detection: ICL-NUIM's TUM-like layout is checked before
# plain TUM. Modules are imported on demand, so one format's import problem cannot break the others.
_LOADERS = {
    "iclnuim": (".iclnuim", "ICLNUIMDataset"),
    "tum": (".tum", "TUMDataset"),
    "7scenes": (".sevenscenes", "SevenScenesDataset"),
    "synthetic": (".synthetic", "SyntheticDataset"),
}


def loader_class(fmt: str) -> type:
    """The Dataset subclass of format ``fmt``."""
    if fmt not in _LOADERS:
        raise InputError(None, f"unknown dataset format {fmt!r}: choose one of auto, {', '.join(FORMATS)}")
    module, name = _LOADERS[fmt]
    return getattr(importlib.import_module(module, __name__), name)


def detect_format(root: Path) -> str:
    if not root.exists():
        raise InputError(root, "dataset folder does not exist")
    if not root.is_dir():
        raise InputError(root, "not a folder (give the dataset's folder)")
    for fmt in _LOADERS:
        if fmt != "synthetic" and loader_class(fmt).detect(root):
            return fmt
    raise InputError(
        root,
        "unrecognised dataset layout: expected TUM (rgb.txt, depth.txt), ICL-NUIM (rgb/, depth/, *.gt.freiburg) "
        "or 7-Scenes (frame-XXXXXX.depth.png); or pass --format",
    )


def open_dataset(cfg: DatasetConfig, synth: SynthConfig | None = None) -> Dataset:
    """The dataset ``cfg`` names; with an empty path, the embedded synthetic sequence."""
    common = dict(downsample=cfg.downsample, start=cfg.start, stop=cfg.stop, stride=cfg.stride)
    if not cfg.path or cfg.format == "synthetic" and not cfg.path:
        return loader_class("synthetic").from_config(synth or SynthConfig(), **common)
    root = Path(cfg.path)
    fmt = cfg.format
    if fmt == "auto":
        fmt = detect_format(root)
    elif not root.is_dir():
        raise InputError(root, "dataset folder does not exist")
    return loader_class(fmt)(root, config=cfg, **common)
