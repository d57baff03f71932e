"""Typed configuration: one dataclass per stage, documented defaults, TOML/YAML files, CLI overrides.

A config file holds one table per section, e.g.::

    [icp]
    iterations = [10, 5, 4]      # coarse to fine
    dist_threshold = 0.10

    [maps]
    depth_smooth_radius = 6

    [fusion]
    capacity = 4_000_000

and any field can be overridden from the command line with ``--set icp.dist_threshold=0.05``.
"""

from __future__ import annotations

import ast
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ti_fusion.errors import InputError


MAP_WIDTH = 320  # fusion.level = -1: the map is built at the finest pyramid level at most this wide


@dataclass
class DatasetConfig:
    path: str = ""             # dataset folder; "" = the embedded synthetic sequence
    format: str = "auto"       # auto | tum | iclnuim | 7scenes | synthetic
    downsample: int = 1        # integer subsampling factor (2 → 320×240 from 640×480)
    start: int = 0             # first frame (index into the sequence)
    stop: int | None = None    # one past the last frame; None = to the end
    stride: int = 1            # take every stride-th frame
    depth_max: float = 4.0     # depth beyond this (metres) is treated as invalid; 0 = keep every range
    intrinsics_file: str = ""  # a file with "fx fy cx cy" (or a 3x3 K) overriding the format's intrinsics
    max_time_difference: float = 0.02  # seconds: TUM rgb↔depth association and ground-truth lookup tolerance


@dataclass
class SynthConfig:
    frames: int = 120          # frames in the embedded synthetic sequence (~4 s at 30 Hz)
    width: int = 640
    height: int = 480
    fx: float = 525.0          # fx = fy; principal point at the image centre
    noise: bool = True         # Kinect-like depth noise (axial Gaussian, quantisation, dropouts)
    seed: int = 0              # same seed → same frames
    min_range: float = 0.4     # metres: nearer depth is dropped (noise on)
    max_range: float = 4.0     # metres: farther depth is dropped (noise on)
    grazing_deg: float = 80.0  # depth dropped where the ray is more than this from the surface normal (noise on)
    baseline: float = 0.075    # metres: projector–camera baseline of the disparity quantisation
    subpixel: float = 8.0      # disparity quantised to 1/subpixel pixel ...
    sensor_width: int = 640    # ... of a sensor this wide with the same field of view (fx · sensor_width / width)
    color_noise: float = 2.0   # grey levels: Gaussian noise per colour channel (noise on)


@dataclass
class ICPConfig:
    iterations: list[int] = field(default_factory=lambda: [10, 5, 4])  # per pyramid level, coarse → fine
    dist_threshold: float = 0.10     # metres: max ‖p′ − q‖ for a correspondence (finest level)
    normal_threshold_deg: float = 30.0  # max angle between the source and target normals
    solver: str = "cholesky"         # cholesky | lu | qr (QR solves the stacked n×6 system)
    robust: str = "huber"            # none | huber | tukey: weights on the point-to-plane residual
    robust_scale: float = 0.01       # metres: Huber's k or Tukey's c (at 1 m depth with depth_weighting)
    depth_weighting: bool = True     # weight residuals by Kinect's depth noise σ(z) at the target point:
                                     # residual / σ(z) into the robust weight, times 1/σ(z)² (both relative
                                     # to 1 m); redkitchen 500 frames: ATE 6.9 → 4.7 cm
    min_inliers: int = 100           # fewer correspondences → degenerate, reported as a failure
    max_condition: float = 1e7       # cond(AᵀA) above this → degenerate
    stop_update: float = 1e-4        # stop a level when ‖δξ‖ (rad, m) falls below this: 0.1 mm, below the
                                     # noise (redkitchen 500 frames: 1e-5 → 1e-4 gave the same ATE with 13.3 →
                                     # 10.1 iterations per frame)
    level_dist_scale: float = 2.0    # d_thr at pyramid level l is dist_threshold · level_dist_scale**l (coarse levels gate wider)
    converged_update: float = 1e-4   # result.converged: the last ‖δξ‖ (rad, m) fell below this


@dataclass
class MapsConfig:
    """The per-frame maps (``kernels/maps.py`` FrameMaps) that ICP aligns and fusion merges: depth
    smoothing, pyramid, vertex and normal maps. How far the input is averaged down first is
    ``Config.frame_input_level`` (``fusion.level`` and ``slam.track_at_map_level``)."""

    normal_max_depth_jump: float = 0.05  # metres: neighbours further apart in depth give no normal
                                         # (× 2**l at pyramid level l)
    pyramid_depth_sigma: float = 0.03    # metres: the pyramid's and the smoothing's depth means count only
                                         # neighbours within 3σ of the centre depth (no mixing across edges)
    depth_smooth_radius: int = -1    # edge-preserving (2r+1)² depth mean before the maps; 0 = raw; -1 = auto,
                                     # width // 50 (12 px at 640, 6 at 320). Redkitchen 500 frames, 640×480 with
                                     # the map at 320×240: r = 2 → 3.95 cm, 6 → 2.98, 12 → 2.67, 24 → 2.69

    def smooth_radius(self, width: int) -> int:
        """``depth_smooth_radius`` for maps ``width`` pixels wide (resolves -1 = auto)."""
        return max(1, width // 50) if self.depth_smooth_radius < 0 else self.depth_smooth_radius


@dataclass
class FusionConfig:
    capacity: int = 4_000_000        # surfels preallocated
    level: int = -1                  # pyramid level the map is fused from and rendered at for tracking: 0 = the
                                     # input resolution, 1 = half (range-checked 3×3 mean, ¼ the surfels); -1 =
                                     # auto, the finest level at most 320 px wide. Redkitchen 500 frames at
                                     # 640×480: level 0 → 4.6 cm at 3.0 fps, level 1 → 4.0 cm at 9.4 fps
    grow: bool = True                # when full: reallocate ×2 (True) or stop with an error (False)
    dist_threshold: float = 0.03     # metres: stricter than ICP association
    normal_threshold_deg: float = 20.0
    confidence_weighting: bool = True  # weight measurements by radial distance from the image centre
    remove_unstable: bool = True     # drop surfels with low confidence not seen for `unstable_age` frames
    unstable_weight: float = 3.0
    unstable_age: int = 20
    remove_free_space: bool = False  # drop surfels observed clearly in front of the measured surface
    free_space_margin: float = 0.05  # metres
    depth_weighting: bool = False    # measurement weight also × (σ(1 m)/σ(z))², capped at 4 (Kinect depth noise)
    confidence_sigma: float = 0.6    # Keller's σ: measurement weight exp(−γ²/2σ²), γ = radial distance / max
    association: str = "compatible"     # a pixel merges into: nearest = its nearest surfel if that one passes
                                     # filter 2 | compatible = the nearest of its surfels that pass (Keller)
    skip_covered: bool = True        # a pixel on the disc of a surfel merged at a neighbouring pixel adds no
                                     # surfel (keeps the map from growing at every frame)
    render_min_weight: float = 0.0   # rendering for tracking: only surfels at least this confident (Keller's
                                     # stable points; from frame unstable_age on, before that all surfels).
                                     # Redkitchen 500 frames: 1 / 2 / 4 → ATE 2.77 / 2.81 / 2.80 cm vs 2.73 at 0
    render_max_half: int = 0         # rendering for tracking: a surfel's disc reaches at most this many pixels
                                     # from its centre. 0: each pixel shows its own front surfel; 1 dilated
                                     # occluding edges by a pixel and cost ATE (redkitchen 320×240: 4.5 → 3.4 cm)
    view_back: float = 1.0           # PNG views: metres the first camera is pulled back along its axis

    def map_level(self, width: int) -> int:
        """``level`` for frames ``width`` pixels wide (resolves -1 = auto)."""
        if self.level >= 0:
            return self.level
        level = 0
        while width > MAP_WIDTH:
            width, level = (width + 1) // 2, level + 1
        return level


@dataclass
class SLAMConfig:
    tracking: str = "model"          # model: align to the map rendered at the last pose | frame: previous frame
    motion_model: bool = True        # constant-velocity initialisation
    min_inlier_ratio: float = 0.15   # below → tracking failure (frame not fused)
    max_residual: float = 0.02       # metres RMS: above → tracking failure
    max_update_deg: float = 20.0     # pose change against the motion model above this → failure
    max_update_m: float = 0.3
    relocalise: str = "features"     # features | none: after a failure, re-initialise with ORB+PnP
    anchor_to_ground_truth: bool = True  # start at the first frame's GT pose (same frame as GT in viewers)
    track_at_map_level: bool = True  # with fusion.level > 0, average the frame down to the map's resolution
                                     # before smoothing and tracking (False: smooth and track at the input
                                     # resolution, each model point aligned to a finer frame). Redkitchen 500
                                     # frames at 640×480: ATE 2.73 vs 2.67 cm, maps 8 vs 33 ms per frame


@dataclass
class VOConfig:
    n_features: int = 1000           # ORB keypoints per frame at most (cv2.ORB_create(n_features))
    match: str = "min_distance"      # min_distance: d < max(4·d_min, floor) | ratio: Lowe's ratio test
    min_distance_factor: float = 4.0  # min_distance mode: good = Hamming distance < factor · d_min ...
    min_distance_floor: float = 30.0  # ... or below this floor (so near-identical frames keep matches)
    ratio: float = 0.8               # ratio mode: best distance < ratio · second best (knnMatch k=2)
    min_good_match: int = 10         # fewer good matches → frame rejected
    min_inliers: int = 5             # fewer RANSAC inliers → frame rejected
    min_inliers_init: int = 20       # ICP initialiser / re-localisation (no motion-size check): fewer → no estimate
    max_norm: float = 0.3            # ‖Δt‖ + min(2π − ‖r‖, ‖r‖) above this → frame rejected
    ransac_reprojection_px: float = 3.0  # RANSAC inlier threshold on the reprojection error (pixels)
    ransac_iterations: int = 300     # RANSAC hypotheses at most (fewer once 0.99 confidence is reached)
    voxel_size: float = 0.02         # metres: downsampling of the joined cloud
    cloud_stride: int = 4            # joined cloud: back-project every N-th pixel in u and v of each frame


@dataclass
class LogConfig:
    map_every: int = 30              # frames between /map/points messages (and one at the end)
    map_max_points: int = 200_000    # /map/points is downsampled to at most this many points
    depth_every: int = 10            # frames between /camera/depth images
    progress: bool = True            # progress bar on the terminal


@dataclass
class Config:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    synth: SynthConfig = field(default_factory=SynthConfig)
    maps: MapsConfig = field(default_factory=MapsConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    slam: SLAMConfig = field(default_factory=SLAMConfig)
    vo: VOConfig = field(default_factory=VOConfig)
    log: LogConfig = field(default_factory=LogConfig)

    def frame_input_level(self, width: int) -> int:
        """How many pyramid steps a frame ``width`` px wide is averaged down on input: to the map's level
        (``fusion.level``) unless ``slam.track_at_map_level`` is off."""
        return self.fusion.map_level(width) if self.slam.track_at_map_level else 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _read_file(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "config file not found")
    text = path.read_text()
    try:
        if path.suffix == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            return tomllib.loads(text)
        if path.suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ModuleNotFoundError:
                raise InputError(path, "reading YAML needs PyYAML (pip install pyyaml); or use TOML") from None
            return yaml.safe_load(text) or {}
        if path.suffix == ".json":
            return json.loads(text)
    except InputError:
        raise
    except Exception as exc:  # parse errors from any of the three readers
        raise InputError(path, f"cannot parse config: {exc}") from None
    raise InputError(path, "config must be .toml, .yaml/.yml or .json")


def _set_field(section_obj: Any, key: str, value: Any, where: str) -> None:
    names = {f.name for f in dataclasses.fields(section_obj)}
    if key not in names:
        raise InputError(None, f"{where}: unknown setting {key!r} (known: {', '.join(sorted(names))})")
    current = getattr(section_obj, key)
    if isinstance(current, bool):
        if isinstance(value, str):
            value = value.lower() in ("1", "true", "yes", "on")
        value = bool(value)
    elif isinstance(current, int) and not isinstance(value, bool) and isinstance(value, (int, float)):
        value = int(value)
    elif isinstance(current, float) and isinstance(value, (int, float)):
        value = float(value)
    setattr(section_obj, key, value)


# Settings that moved to another section: the old name still sets the new one.
MOVED = {("icp", name): ("maps", name)
         for name in ("normal_max_depth_jump", "pyramid_depth_sigma", "depth_smooth_radius")}


def apply_dict(config: Config, data: dict, where: str = "config") -> Config:
    for section, values in data.items():
        if not hasattr(config, section) or not isinstance(values, dict):
            raise InputError(None, f"{where}: unknown section {section!r}")
        for key, value in values.items():
            to_section, to_key = MOVED.get((section, key), (section, key))
            _set_field(getattr(config, to_section), to_key, value, f"{where} [{section}]")
    return config


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"icp.iterations=[10,5,4]"`` → ("icp", "iterations", [10, 5, 4])."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise InputError(None, f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. icp.dist_threshold=0.05")
    lhs, rhs = text.split("=", 1)
    section, key = lhs.strip().split(".", 1)
    try:
        value = ast.literal_eval(rhs.strip())
    except (ValueError, SyntaxError):
        value = rhs.strip()
    return section, key, value


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the file (if any), then ``--set`` overrides."""
    config = Config()
    if path:
        apply_dict(config, _read_file(Path(path)), where=str(path))
    for text in overrides or []:
        section, key, value = parse_override(text)
        apply_dict(config, {section: {key: value}}, where="--set")
    return config
