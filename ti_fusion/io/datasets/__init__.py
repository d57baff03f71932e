"""Dataset loaders: one per format, one interface (``Dataset``), and format detection.

A format is detected only from files that identify it: TUM RGB-D from ``depth.txt``, ICL-NUIM from its
``*.gt.freiburg`` ground truth, 7-Scenes from its ``frame-XXXXXX.depth.png`` names, a ROS 2 bag from its
``metadata.yaml`` or ``.mcap`` file (profile ``ros2``), a ti-fusion run log from its ``log.mcap``. A folder
with none of them, or with the files of two formats, is refused with a line naming the ``--format`` to
pass: the format fixes the depth scale and the intrinsics, and a wrong guess gives wrong depths without
any error. A plain folder of numbered depth PNGs (``--format folder``) is never detected: its units and
camera are the user's to state.

Frames from one's own code need no format: ``rgbd_frame`` makes a ``Frame`` from arrays and
``FrameList`` holds frames as a ``Dataset`` (``ti_fusion.io.datasets.arrays``).
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.errors import InputError
from ti_fusion.io.datasets.base import Dataset, Frame
from ti_fusion.io.formats import FORMATS, LOADERS

__all__ = ["Dataset", "Frame", "open_dataset", "detect_format", "loader_class", "FORMATS", "rgbd_frame",
           "FrameList"]

log = logging.getLogger(__name__)


def loader_class(fmt: str) -> type[Dataset]:
    """The Dataset subclass registered for format ``fmt`` (``ti_fusion/io/formats.py``), imported on first use."""
    if fmt not in LOADERS:
        raise InputError(None, f"unknown dataset format {fmt!r}: choose one of auto, {', '.join(LOADERS)}")
    module, name = LOADERS[fmt].split(":")
    return getattr(importlib.import_module(module), name)


def detect(root: Path) -> tuple[str, str]:
    """(format, the file that identifies it) of a dataset folder or bag file; InputError when none or
    several match."""
    root = Path(root)
    if not root.exists():
        raise InputError(root, "dataset folder does not exist")
    found = {}
    for fmt in LOADERS:
        loader = loader_class(fmt)
        evidence = loader.detect(root) if root.is_dir() or loader.single_file else None
        if evidence:
            found[fmt] = evidence
    if len(found) == 1:
        return next(iter(found.items()))
    if found:
        which = ", ".join(f"{fmt} ({evidence})" for fmt, evidence in found.items())
        raise InputError(root, f"holds the files of more than one format: {which}; pass "
                               + " or ".join(f"--format {fmt}" for fmt in found))
    if not root.is_dir():
        raise InputError(root, "not a folder, nor a ROS bag file (.bag, .mcap or .db3) or a ti-fusion run log: give "
                               "the dataset's folder")
    from ti_fusion.io.datasets.iclnuim import numbered_pngs

    if numbered_pngs(root / "depth") or (root / "depth").is_dir():
        raise InputError(root, "depth/ holds depth images, but no file says which dataset they come from, so "
                               "their depth scale and intrinsics are unknown: pass --format folder --depth-scale "
                               "UNITS_PER_METRE --intrinsics fx,fy,cx,cy (or FILE); if it is ICL-NUIM (5000 "
                               "units per metre, its published intrinsics), pass --format iclnuim")
    known = [what for what in (loader_class(fmt).identified_by for fmt in LOADERS) if what]
    raise InputError(root, f"unrecognised dataset layout: expected {', '.join(known[:-1])} or {known[-1]}; or pass "
                           "--format")


def detect_format(root: Path) -> str:
    """The format of a dataset folder (see ``detect``)."""
    return detect(root)[0]


def open_dataset(cfg: DatasetConfig, synth: SynthConfig | None = None) -> Dataset:
    """The dataset ``cfg`` names; with an empty path, the embedded synthetic sequence.

    Refuses (``InputError``) a selection of no frame and a downsampling that leaves frames too small;
    logs the format line (``Dataset.describe_format``) for the CLI to print.
    """
    common = dict(downsample=cfg.downsample, start=cfg.start, stop=cfg.stop, stride=cfg.stride)
    if cfg.camera:  # a live camera (or the SDK's playback of its recording): ti_fusion/io/datasets/realsense_live.py
        if cfg.path:
            raise InputError(None, f"--camera {cfg.camera} and the dataset {cfg.path}: give one source of frames")
        from ti_fusion.io.datasets.realsense_live import RealSenseCamera

        dataset = RealSenseCamera(cfg.camera, cfg, **common)
        dataset.format_from = "--camera"
        dataset.check_selection()
        log.info(dataset.describe_format(), extra={"essential": True})  # shown with --quiet too
        return dataset
    if not cfg.path:
        if cfg.format not in ("auto", "synthetic"):
            raise InputError(None, f"format {cfg.format} needs a dataset folder (DATA)")
        if cfg.intrinsics or cfg.depth_scale:
            raise InputError(None, "--intrinsics and --depth-scale are for data read from files: the synthetic "
                                   "sequence's camera is set by synth.fx, synth.width and synth.height")
        check_options_apply("synthetic", cfg)
        dataset = loader_class("synthetic").from_config(synth or SynthConfig(), **common)
        dataset.check_selection()
        return dataset
    root = Path(cfg.path)
    fmt = cfg.format
    if fmt == "synthetic":
        raise InputError(root, "format synthetic is the embedded sequence: give no DATA folder with it")
    if cfg.intrinsics and cfg.intrinsics_file:
        raise InputError(None, "dataset.intrinsics and dataset.intrinsics_file both give the intrinsics: keep one")
    if fmt == "auto":
        fmt, evidence = detect(root)
        how = f"detected from {evidence}"
    else:
        loader = loader_class(fmt)  # an unknown name fails here, before the folder is read
        if not root.exists():
            raise InputError(root, "dataset folder does not exist")
        if not root.is_dir() and not loader.single_file:
            raise InputError(root, "not a folder (give the dataset's folder)")
        how = "given by --format or dataset.format"
    check_options_apply(fmt, cfg)
    dataset = loader_class(fmt)(root, config=cfg, **common)
    dataset.format_from = how
    if dataset.replaceable_calibration:
        if cfg.intrinsics:
            _replace_intrinsics(dataset, cfg.intrinsics)
        if cfg.depth_scale:
            dataset.depth_scale = float(cfg.depth_scale)  # read by ImageFileDataset for every frame
    if (cfg.color_extrinsics or cfg.color_intrinsics) and not dataset.reads_color_camera:
        _color_camera(dataset, cfg)
    dataset.check_selection()
    log.info(dataset.describe_format(), extra={"essential": True})  # shown with --quiet too
    return dataset


# Dataset settings that only some formats read (each loader's ``reads`` names those it does), with why the others
# have none: given for a format that does not read it, a setting would be ignored without a word.
_READ_BY_SOME = {
    "ground_truth": "a benchmark folder's ground truth is its own file, a run log's is in the log",
    **{key: "topics are a bag's" for key in ("depth_topic", "color_topic", "camera_info_topic", "gt_topic")},
    "intrinsics": "a run's log holds its calibration",
    "depth_scale": "a run's log holds metres",
}


def check_options_apply(fmt: str, cfg: DatasetConfig) -> None:
    """InputError (one line) for a dataset setting given that format ``fmt`` does not read."""
    for key, why in _READ_BY_SOME.items():
        if getattr(cfg, key, None) and key not in loader_class(fmt).reads:
            formats = [name for name in LOADERS if key in loader_class(name).reads]
            what = "the synthetic sequence" if fmt == "synthetic" else f"a {fmt} dataset"
            raise InputError(None, f"--{key.replace('_', '-')} (dataset.{key}) does not apply to {what}: it is read "
                                   f"only for {' and '.join(formats) if len(formats) < 3 else ', '.join(formats)} "
                                   f"data ({why}); leave it out")


def _color_camera(dataset: Dataset, cfg: DatasetConfig) -> None:
    """A folder's or a benchmark's colour camera (``--color-intrinsics``, ``--color-extrinsics`` FILE), so
    that its colour is registered to depth in the run loop (``ti_fusion/io/registration.py``)."""
    from ti_fusion.io.datasets.extrinsics import read_extrinsics_file
    from ti_fusion.io.datasets.imageio import parse_intrinsics, read_color

    if not (cfg.color_extrinsics and cfg.color_intrinsics):
        given, missing = ("--color-extrinsics", "--color-intrinsics fx,fy,cx,cy|FILE") if cfg.color_extrinsics \
            else ("--color-intrinsics", "--color-extrinsics FILE")
        raise InputError(None, f"{given} registers colour to depth together with {missing} (the colour camera's "
                               "pose from the depth camera and its intrinsics)")
    if not Path(cfg.color_extrinsics).is_file():
        raise InputError(cfg.color_extrinsics, "--color-extrinsics: no such file (a transform topic is for bags)")
    first = next((c for c in getattr(dataset, "_color_files", []) if c is not None), None)
    if first is None:
        raise InputError(dataset.root, "--color-extrinsics: the dataset has no colour images to register")
    h, w = read_color(first).shape[:2]
    K = parse_intrinsics(cfg.color_intrinsics, w, h, option="--color-intrinsics")
    T = read_extrinsics_file(cfg.color_extrinsics)
    dataset.color_camera = (K, T)
    dataset.color_registered = False  # registered by the kernel in the run loop, from the stated calibration
    dataset.notes = [n for n in dataset.notes if "only colours the map" not in n]
    t = T[:3, 3]
    log.info(f"colour camera fx {K.fx:g} fy {K.fy:g} cx {K.cx:g} cy {K.cy:g} at {w}x{h} ({cfg.color_intrinsics}), "
             f"depth-to-colour translation ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m ({cfg.color_extrinsics}): colour is "
             "registered to depth")


def _replace_intrinsics(dataset: Dataset, spec) -> None:
    """``dataset.intrinsics`` in place of a benchmark format's own (its calibration, or the file beside
    its frames), for the images' size that the loader read."""
    from ti_fusion.io.datasets.imageio import parse_intrinsics

    K = dataset.raw_intrinsics
    dataset._intrinsics = parse_intrinsics(spec, K.width, K.height)
    text = ",".join(str(v) for v in spec) if isinstance(spec, (list, tuple)) else spec
    dataset.intrinsics_source = f"{text} (--intrinsics / dataset.intrinsics)"


def __getattr__(name: str):
    # The in-memory dataset and frame maker: imported on first use, like the loaders.
    if name in ("rgbd_frame", "FrameList"):
        from ti_fusion.io.datasets import arrays

        return getattr(arrays, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
