"""Dataset loaders: one per format, one interface (``Dataset``), and format auto-detection."""

from __future__ import annotations

from pathlib import Path

from ..config import DatasetConfig, SynthConfig
from ..errors import InputError
from .base import Dataset, Frame

__all__ = ["Dataset", "Frame", "open_dataset", "FORMATS"]

FORMATS = ("tum", "iclnuim", "7scenes", "synthetic")


def _loader_classes() -> dict:
    from .iclnuim import ICLNUIMDataset
    from .sevenscenes import SevenScenesDataset
    from .synthetic import SyntheticDataset
    from .tum import TUMDataset

    # Order matters for detection: ICL-NUIM's TUM layout is checked before plain TUM.
    return {
        "iclnuim": ICLNUIMDataset,
        "tum": TUMDataset,
        "7scenes": SevenScenesDataset,
        "synthetic": SyntheticDataset,
    }


def detect_format(root: Path) -> str:
    if not root.exists():
        raise InputError(root, "dataset folder does not exist")
    if not root.is_dir():
        raise InputError(root, "not a folder (give the dataset's folder)")
    for name, cls in _loader_classes().items():
        if cls.detect(root):
            return name
    raise InputError(
        root,
        "unrecognised dataset layout: expected TUM (rgb.txt, depth.txt), ICL-NUIM (rgb/, depth/, *.gt.freiburg) "
        "or 7-Scenes (frame-XXXXXX.depth.png); or pass --format",
    )


def open_dataset(cfg: DatasetConfig, synth: SynthConfig | None = None) -> Dataset:
    """The dataset ``cfg`` names; with an empty path, the embedded synthetic sequence."""
    classes = _loader_classes()
    common = dict(downsample=cfg.downsample, start=cfg.start, stop=cfg.stop, stride=cfg.stride)
    if not cfg.path or cfg.format == "synthetic" and not cfg.path:
        return classes["synthetic"].from_config(synth or SynthConfig(), **common)
    root = Path(cfg.path)
    fmt = cfg.format
    if fmt == "auto":
        fmt = detect_format(root)
    elif not root.is_dir():
        raise InputError(root, "dataset folder does not exist")
    if fmt not in classes:
        raise InputError(None, f"unknown dataset format {fmt!r}: choose one of auto, {', '.join(FORMATS)}")
    return classes[fmt](root, config=cfg, **common)
