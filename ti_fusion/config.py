"""Typed configuration: one dataclass per stage, documented defaults, TOML/YAML files, CLI overrides.

A config file holds one table per section, e.g.::

    [icp]
    iterations = [10, 5, 4]      # coarse to fine
    dist_threshold = 0.10

    [maps]
    depth_smooth_radius = 6

    [fusion]
    capacity = 4_000_000

and any field can be overridden from the command line with ``--set icp.dist_threshold=0.05``. Every
field says what it allows (a type, and a range or a set of choices, in its annotation); a value from a
file or ``--set`` that breaks its rule is refused with one line naming the key, the value and what is
allowed; so is a file that is not UTF-8, not parseable, not a table at its top level, or that gives a value
where a section goes. Relative paths in a config file (``dataset.path``, ``dataset.intrinsics``, ...,
``Text(path=True)``) are relative to the file's folder; those of ``--set`` to the working directory.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import io
import json
import math
import numbers
import tokenize
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Callable, Iterable

from ti_fusion.errors import InputError
from ti_fusion.io.formats import LOADERS

# --------------------------------------------------------------------------------------------------
# What a field allows, written beside it: ``name: Annotated[type, rule, ...] = default``. A bool is true
# or false and needs no rule; a number has a ``Range``, text a ``OneOf`` or ``Text``, a list its items'
# ``Range`` and a ``Length``. ``check_value`` applies them to every value a file or ``--set`` gives, so
# a wrong value stops the run at once with one line instead of running with it (or crashing later).


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


@dataclass(frozen=True)
class Range:
    """A number, or every item of a list of numbers, within bounds: ``Range(gt=0)``, ``Range(ge=0, le=1)``."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def allows(self, x: float) -> bool:
        return ((self.ge is None or x >= self.ge) and (self.gt is None or x > self.gt)
                and (self.le is None or x <= self.le) and (self.lt is None or x < self.lt))

    def __str__(self) -> str:
        low = f"[{_num(self.ge)}" if self.ge is not None else f"({_num(self.gt)}" if self.gt is not None else None
        high = f"{_num(self.le)}]" if self.le is not None else f"{_num(self.lt)})" if self.lt is not None else None
        if low and high:
            return f"in {low}, {high}"
        if low:
            return (">= " if low[0] == "[" else "> ") + low[1:]
        if high:
            return ("<= " if high[-1] == "]" else "< ") + high[:-1]
        return ""


class OneOf:
    """Text from a set of choices: ``OneOf("none", "huber")``, or ``OneOf(source=f)`` to ask ``f()`` for
    them when checking (choices that live with their code, such as the dataset formats)."""

    def __init__(self, *choices: str, source: Callable[[], Iterable[str]] | None = None):
        self._choices, self.source = tuple(choices), source

    @property
    def choices(self) -> tuple[str, ...]:
        return tuple(self.source()) if self.source is not None else self._choices

    def __str__(self) -> str:
        return "one of " + ", ".join(self.choices)


@dataclass(frozen=True)
class Text:
    """Free text: a path, a topic name (``what`` says which, in the error line). ``path``: a file or folder,
    which a config file gives relative to its own folder."""

    what: str = "text"
    path: bool = False


@dataclass(frozen=True)
class Length:
    """A list of at least ``ge`` items."""

    ge: int = 1


@dataclass(frozen=True)
class Flag:
    """The field is also an option of the commands that read frames (slam, vo, fuse, icp): ``--name`` (the
    field's name, hyphens for underscores), its value checked by the field's rule and its help the field's
    comment (``field_docs``); ``metavar`` names the value in --help, ``range`` narrows what the option takes
    where the key's rule allows a value that only means "unset" (0 = the format's own). So an option is
    declared once, here."""

    metavar: str | None = None
    range: Range | None = None
    commands: tuple[str, ...] | None = None  # only these commands have the option (None: every one that reads frames)


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "text"}
_PLURAL = {int: "integers", float: "numbers"}
_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


@dataclass(frozen=True)
class Rule:
    """A field's type and constraints, read from its annotation (see ``rules``)."""

    kind: type                      # bool, int, float, str or list
    item: type | None = None        # a list's item type
    optional: bool = False          # None is allowed too
    range: Range | None = None
    choices: OneOf | None = None
    text: Text | None = None
    length: Length | None = None
    flag: Flag | None = None        # also a command-line option (``Flag``)

    def describe(self) -> str:
        """What the field allows, as the error line says it: "a number > 0", "one of none, huber, tukey"."""
        if self.kind is list:
            what = f"a list of {_PLURAL[self.item]}" + (f" {self.range}" if self.range and str(self.range) else "")
            what += f" (at least {self.length.ge})" if self.length else ""
        elif self.choices is not None:
            what = str(self.choices)
        elif self.text is not None:
            what = self.text.what
        else:
            what = _KINDS[self.kind] + (f" {self.range}" if self.range and str(self.range) else "")
        return what + (", or None" if self.optional else "")

    def check(self, value: Any) -> Any:
        """``value`` as the field's type (an integral 3.0 as 3, "yes" as True, a tuple as a list), or
        ValueError when the rule refuses it."""
        if value is None and self.optional:
            return None
        if self.kind is list:
            if not isinstance(value, (list, tuple)) or (self.length and len(value) < self.length.ge):
                raise ValueError
            return [self._scalar(self.item, v) for v in value]
        return self._scalar(self.kind, value)

    def _scalar(self, kind: type, value: Any) -> Any:
        value = _as_kind(kind, value)
        if self.range is not None and not self.range.allows(value):
            raise ValueError
        if self.choices is not None and value not in self.choices.choices:
            raise ValueError
        return value


def _as_kind(kind: type, value: Any) -> Any:
    if kind is bool:
        if isinstance(value, (bool, numbers.Integral)) and value in (0, 1):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
            return value.strip().lower() in _TRUE
        raise ValueError
    if kind is str:
        if isinstance(value, str):
            return value
        raise ValueError
    if isinstance(value, str):  # YAML reads 1e-4 as text; a number written as text is still that number
        try:
            value = int(value)
        except ValueError:
            try:
                value = float(value)
            except ValueError:
                raise ValueError from None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError
    if kind is int:
        if value != int(value):
            raise ValueError
        return int(value)
    return float(value)


@functools.cache
def rules(section: type) -> dict[str, Rule]:
    """The ``Rule`` of every field of a config section; TypeError names the fields that have none."""
    hints = typing.get_type_hints(section, include_extras=True)
    out, missing = {}, []
    for f in dataclasses.fields(section):
        rule = _rule_of(hints[f.name])
        if rule is None:
            missing.append(f.name)
        else:
            out[f.name] = rule
    if missing:
        raise TypeError(f"{section.__name__}: no rule for {', '.join(missing)} (see ti_fusion/config.py: Range, "
                        "OneOf, Text, Length)")
    return out


def _rule_of(hint: Any) -> Rule | None:
    meta: tuple = ()
    if typing.get_origin(hint) is Annotated:
        hint, *meta = typing.get_args(hint)
    optional = False
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional, hint = len(args) < len(typing.get_args(hint)), args[0] if len(args) == 1 else hint
    item = None
    if typing.get_origin(hint) is list:
        (item,) = typing.get_args(hint)
        hint = list
    if hint not in (bool, int, float, str, list) or (item is not None and item not in (int, float)):
        return None
    found = {type(m): m for m in meta}
    rule = Rule(hint, item, optional, found.get(Range), found.get(OneOf), found.get(Text), found.get(Length),
                found.get(Flag))
    numeric = hint in (int, float) or item is not None
    if (numeric and rule.range is None) or (hint is str and rule.choices is None and rule.text is None) \
            or (hint is list and rule.length is None):
        return None
    return rule


def _dataset_formats() -> tuple[str, ...]:
    return ("auto", *LOADERS)


def field_comments(source: str) -> dict[tuple[str, str], str]:
    """(class name, field name) → the comment text beside the field in ``source``: the comments on the
    field's own lines and on the comment-only lines that follow it, joined."""
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = source.splitlines()
    out = {}
    for node in ast.parse(source).body:
        if not isinstance(node, ast.ClassDef):
            continue
        for stmt in node.body:
            if not isinstance(stmt, ast.AnnAssign) or not isinstance(stmt.target, ast.Name):
                continue
            parts = [comments[n] for n in range(stmt.lineno, stmt.end_lineno + 1) if n in comments]
            n = stmt.end_lineno + 1
            while n <= len(lines) and lines[n - 1].strip().startswith("#"):
                parts.append(comments[n])
                n += 1
            out[node.name, stmt.target.id] = " ".join(p for p in parts if p)
    return out


@functools.cache
def field_docs() -> dict[tuple[str, str], str]:
    """The meaning of every config field, from its comment in this file: docs/CONFIG.md's meaning column
    (scripts/config_doc.py) and the help of the command-line options (``Flag``)."""
    return field_comments(Path(__file__).read_text(encoding="utf-8"))



# The rules most fields have.
Positive = Annotated[float, Range(gt=0)]
NonNegative = Annotated[float, Range(ge=0)]
Fraction = Annotated[float, Range(ge=0, le=1)]
Degrees = Annotated[float, Range(gt=0, le=180)]
Count = Annotated[int, Range(ge=1)]
NonNegativeInt = Annotated[int, Range(ge=0)]
FilePath = Annotated[str, Text("a file path", path=True)]
Topic = Annotated[str, Text("a topic name")]


MAP_WIDTH = 320  # fusion.level = -1: the map is built at the finest pyramid level at most this wide


@dataclass
class DatasetConfig:
    path: Annotated[str, Text("a folder or file path", path=True)] = ""
                                    # the dataset (DATA on the command line); "" = the embedded synthetic sequence
    format: Annotated[str, OneOf(source=_dataset_formats), Flag()] = "auto"
                                    # the dataset's format; auto = detected from the files that identify it
                                    # (docs/DATA.md)
    downsample: Annotated[Count, Flag("N")] = 1  # integer subsampling factor (2 → 320×240 from 640×480)
    start: Annotated[NonNegativeInt, Flag("N")] = 0  # first frame (its index in the sequence, 0 = the first)
    stop: Annotated[int | None, Range(ge=1), Flag("N")] = None  # one past the last frame; None = to the end
    stride: Annotated[Count, Flag("N")] = 1  # take every stride-th frame
    depth_max: NonNegative = 4.0    # depth beyond this (metres) is treated as invalid; 0 = keep every range
    intrinsics_file: FilePath = ""  # a file with "fx fy cx cy" (or a 3x3 K) overriding the format's intrinsics
    max_time_difference: NonNegative = 0.02  # seconds: TUM rgb↔depth association and ground-truth lookup tolerance
    depth_scale: Annotated[NonNegative, Flag("UNITS_PER_METRE", Range(gt=0))] = 0.0
                                    # raw depth units per metre: 1000 for millimetres (RealSense, Azure Kinect),
                                    # 5000 for TUM's; required by --format folder; 0 = the format's own (bags:
                                    # REP 118, 16UC1 in mm, 32FC1 in metres)
    intrinsics: Annotated[str, Text("fx,fy,cx,cy or a file path", path=True), Flag("fx,fy,cx,cy|FILE")] = ""
                                    # camera intrinsics: "fx,fy,cx,cy" or a calibration file (fx fy cx cy, a 3x3 K,
                                    # a camera_info or OpenCV YAML), in place of the format's; a folder needs it
                                    # or camera.yaml/intrinsics.txt
    ground_truth: Annotated[FilePath, Flag("FILE")] = ""
                                    # a TUM trajectory file of the camera's ground-truth poses (folder, bag)
    depth_topic: Annotated[Topic, Flag("TOPIC")] = ""
                                    # bags: the depth image topic; "" = the only one
    color_topic: Annotated[Topic, Flag("TOPIC")] = ""
                                    # bags: the colour image topic; "" = the only one, "none" = depth only
    camera_info_topic: Annotated[Topic, Flag("TOPIC")] = ""
                                    # bags: the CameraInfo topic of the depth images; "" = the depth topic's
                                    # camera_info, or the only one
    gt_topic: Annotated[Topic, Flag("TOPIC")] = ""
                                    # bags: a PoseStamped or Odometry topic of ground-truth poses; "" = none
    color_extrinsics: Annotated[str, Text("a file path or a bag topic"), Flag("FILE|TOPIC")] = ""
                                    # the colour camera's T_color_depth (p_color = T p_depth, metres): a file (4x4
                                    # or 3x4 matrix, or tx ty tz qx qy qz qw) or a bag's Transform,
                                    # TransformStamped or TFMessage topic; colour is then registered to depth
                                    # (RealSense recordings: the recorded one)
    color_intrinsics: Annotated[str, Text("fx,fy,cx,cy or a file path", path=True), Flag("fx,fy,cx,cy|FILE")] = ""
                                    # the colour camera's intrinsics at the colour images' size, for registration
                                    # with color_extrinsics (folder, 7-Scenes; a bag's colour camera_info otherwise)
    camera: Annotated[str, Text("realsense[:SERIAL] or realsense:FILE.bag"), Flag("realsense[:SERIAL]")] = ""
                                    # frames from a live camera instead of a dataset (pip install
                                    # 'ti-fusion[realsense]'); Ctrl-C or --frames N ends the run;
                                    # realsense:FILE.bag plays a recording back through the SDK
    color_registered: bool = False  # folder, bag and log: the colour images are registered to depth (pixel for
                                    # pixel), so photometric tracking may use them; TUM, ICL-NUIM and synthetic
                                    # are, 7-Scenes is not (its own word); a bag with one frame_id for both is
    read_workers: NonNegativeInt = 0  # processes that read frames ahead of the loop where frames are image files
                                      # (folder, TUM, 7-Scenes, ICL-NUIM; bags, logs and the synthetic sequence
                                      # on the CPU backend: one); 0 = a quarter of the usable CPUs, 1 to 4
                                      # (docs/PERFORMANCE.md, reading in processes)


@dataclass
class SynthConfig:
    scene: Annotated[str, OneOf("room", "loop", "twins", "wall", "corridor", "jerky", "cabinet", "slats"),
                     Flag()] = "room"
                                    # the scene and its own camera path (docs/DATA.md): room (furnished room),
                                    # loop (corridor loop around a block, for loop closure), twins (the loop with
                                    # two identical sections, for false loops), wall (flat wall and floor),
                                    # corridor (plain walls, posters): geometry-poor, for photometric tracking,
                                    # jerky (the room at random gaps of 0.1-0.7 s) and cabinet (a plain box
                                    # circled in a plain room, a frame every 0.67 s), slats (a chair back of
                                    # slats with 3 cm slots, for the mesh's openings)
    trajectory: Annotated[FilePath, Flag("FILE.tum")] = ""
                                    # a TUM file of camera-to-world poses to render instead of the scene's path:
                                    # one frame per pose at the file's timestamps; "" = the scene's own path
    frames: NonNegativeInt = 0      # frames in the embedded synthetic sequence; 0 = the scene's own length
                                    # (room 120, ~4 s at 30 Hz; a trajectory file: all its poses)
    width: Count = 640              # pixels: image width
    height: Count = 480             # pixels: image height
    fx: Positive = 525.0            # fx = fy; principal point at the image centre
    noise: bool = True              # Kinect-like depth noise (axial Gaussian, quantisation, dropouts)
    seed: NonNegativeInt = 0        # same seed → same frames
    min_range: NonNegative = 0.4    # metres: nearer depth is dropped (noise on)
    max_range: Positive = 4.0       # metres: farther depth is dropped (noise on)
    grazing_deg: Annotated[float, Range(gt=0, le=90)] = 80.0  # depth dropped where the ray is more than this
                                                              # from the surface normal (noise on)
    baseline: Positive = 0.075      # metres: projector–camera baseline of the disparity quantisation
    subpixel: Positive = 8.0        # disparity quantised to 1/subpixel pixel ...
    sensor_width: Count = 640       # ... of a sensor this wide with the same field of view (fx · sensor_width / width)
    color_noise: NonNegative = 2.0  # grey levels: Gaussian noise per colour channel (noise on)
    depth_noise_scale: NonNegative = 1.0  # the axial depth noise is this × the sensor's σ(z) (ti_fusion/sensor.py;
                                    # dimensionless, noise on): more noise, more drift (docs/DATA.md)
    edge_shadow: bool = False       # Kinect v1 edges (noise on; default off, docs/TRACKING.md): no depth where the
                                    # projector, synth.baseline to the camera's left, cannot light (beside near edges)
    edge_holes: NonNegative = 0.0   # pixels (full resolution): depth dropped within this of a depth edge; 0 = none
    flying_pixels: Annotated[float, Range(ge=0, le=1)] = 0.0  # share of the dropped edge pixels given a depth
                                    # between the edge's two sides instead (flying pixels)
    exposure: NonNegative = 0.0     # σ of a frame's log brightness gain (auto-exposure; noise on): 0.1 ≈ ±10 %
    jpeg_quality: Annotated[int, Range(ge=0, le=100)] = 0  # colour through JPEG at this quality (noise on), as
                                    # TUM's re-encoded frames; 0 = none
    color_offset_ms: Annotated[float, Range(ge=-100, le=100)] = 0.0  # ms: colour captured this long after depth
                                    # (before, if negative; noise on), its pose moved along the step to the next
                                    # (previous) frame's; 0 = together


@dataclass
class ICPConfig:
    iterations: Annotated[list[int], Range(ge=0), Length(ge=1)] = field(default_factory=lambda: [10, 5, 4])
                                     # per pyramid level, coarse → fine
    dist_threshold: Positive = 0.10  # metres: max ‖p′ − q‖ for a correspondence (finest level)
    normal_threshold_deg: Degrees = 30.0  # max angle between the source and target normals
    robust: Annotated[str, OneOf("none", "huber", "tukey")] = "huber"  # weights on the point-to-plane residual
    robust_scale: Positive = 0.01    # metres: Huber's k or Tukey's c (at 1 m depth with depth_weighting)
    depth_weighting: bool = True     # weight residuals by Kinect's depth noise σ(z) at the target point:
                                     # residual / σ(z) into the robust weight, times 1/σ(z)² (both relative
                                     # to 1 m); off doubled redkitchen's ATE (docs/BENCHMARKS.md, Ablations)
    min_inliers: Annotated[int, Range(ge=6)] = 100  # fewer correspondences → degenerate, reported as a failure
                                     # (the 6×6 system needs six at the very least)
    max_condition: Annotated[float, Range(ge=1)] = 1e7  # cond(AᵀA) above this → degenerate (cond is >= 1)
    stop_update: NonNegative = 1e-4  # stop the finest level when ‖δξ‖ (rad, m) falls below this: 0.1 mm, below
                                     # the noise; doubled per coarser level; also what ICPResult.converged tests
    level_dist_scale: Positive = 2.0  # d_thr at pyramid level l is dist_threshold · level_dist_scale**l (coarse
                                      # levels gate wider)
    color_weight: NonNegative = 0.01  # weight of the photometric term's normal equations beside ICP's (intensity
                                     # in [0, 1] against metres); 0 = depth only. Off where colour is not
                                     # registered to depth (7-Scenes). 0.01 measured best on every synthetic scene
                                     # (docs/BENCHMARKS.md, colour by default: wall 147 → 0.09 cm)
    color_robust_scale: Positive = 0.05  # intensity in [0, 1]: Huber's k on the photometric residual
    color_finest_scale: Annotated[float, Range(ge=0, le=1)] = 0.4  # on JPEG-compressed colour (the live frame's
                                     # blockiness) the finest pyramid level's colour weight is color_weight ×
                                     # this: there real colour (TUM cabinet) pulled pairs off the truth, the
                                     # coarser levels held them; clean colour keeps the whole weight
                                     # (docs/PHOTOMETRIC.md, real colour)
    weak_ratio: Annotated[float, Range(gt=0, lt=1)] = 1e-3  # a direction of the geometric AᵀA whose eigenvalue
                                     # is below this fraction of the largest is reported weak (degeneracy)


@dataclass
class PyramidConfig:
    """The frame's pyramid (``kernels/pyramid.py`` FramePyramid) that ICP aligns and fusion merges: depth
    smoothing, the depth pyramid and each level's vertex and normal maps. How far the input is averaged down first is
    ``Config.frame_input_level`` (the map's level, ``fusion.level``)."""

    normal_max_depth_jump: Positive = 0.05  # metres: neighbours further apart in depth give no normal
                                            # (× 2**l at pyramid level l)
    depth_sigma: Positive = 0.03            # metres: the pyramid's and the smoothing's depth means count only
                                            # neighbours within 3σ of the centre depth (no mixing across edges)
    depth_smooth_radius: Annotated[int, Range(ge=-1)] = -1
                                     # edge-preserving (2r+1)² depth mean before the maps; 0 = raw; -1 = auto,
                                     # width // 50 (12 px at 640, 6 at 320; docs/BENCHMARKS.md has the sweep)

    def smooth_radius(self, width: int) -> int:
        """``depth_smooth_radius`` for maps ``width`` pixels wide (resolves -1 = auto)."""
        return max(1, width // 50) if self.depth_smooth_radius < 0 else self.depth_smooth_radius


@dataclass
class FusionConfig:
    capacity: Count = 4_000_000      # surfels preallocated
    level: Annotated[int, Range(ge=-1)] = -1
                                     # pyramid level the map is fused from and rendered at for tracking: 0 = the
                                     # input resolution, 1 = half (range-checked 3×3 mean, ¼ the surfels); -1 =
                                     # auto, the finest level at most 320 px wide (on redkitchen more accurate
                                     # and faster than 640×480: docs/BENCHMARKS.md)
    grow: bool = True                # when full: reallocate ×2 (True) or stop with an error (False)
    dist_threshold: Positive = 0.03  # metres: stricter than ICP association
    normal_threshold_deg: Degrees = 20.0  # max angle between a pixel's normal and the surfel's it merges into
    confidence_weighting: bool = True  # weight measurements by radial distance from the image centre
    remove_unstable: bool = True     # drop surfels with low confidence not seen for `unstable_age` frames
    unstable_weight: NonNegative = 3.0  # confidence below which a surfel is unstable (at or above: confirmed)
    unstable_age: NonNegativeInt = 20  # frames an unstable surfel may go unseen before it is removed
    remove_free_space: bool = False  # drop surfels observed clearly in front of the measured surface
    free_space_margin: NonNegative = 0.05  # metres
    depth_weighting: bool = False    # measurement weight also × (σ(1 m)/σ(z))², capped at 4 (Kinect depth noise)
    confidence_sigma: Positive = 0.6  # Keller's σ: measurement weight exp(−γ²/2σ²), γ = radial distance / max
    skip_covered: bool = True        # a pixel on the disc of a surfel merged at a neighbouring pixel adds no
                                     # surfel (keeps the map from growing at every frame)
    render_min_weight: NonNegative = 0.0  # rendering for tracking: only surfels at least this confident (Keller's
                                     # stable points; from frame unstable_age on, before that all surfels).
                                     # Above 0 did not help on redkitchen (docs/BENCHMARKS.md)
    view_back: Annotated[float, Range()] = 1.0  # PNG views: metres the first camera is pulled back along its axis

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
    motion_model: bool = True        # constant-velocity initialisation (per second: scaled by the time between frames)
    motion_damping: Fraction = 0.5   # the velocity is multiplied by this after a step the guess missed by more
                                     # than half (the speed changed)
    hypotheses: Annotated[str, OneOf("doubt", "always", "motion")] = "doubt"
                                     # doubt: ICP again from the last good pose when the motion model's alignment
                                     # fails or is in doubt, then ORB+PnP, a wide-basin re-localisation and the guess
                                     # turned further before a failure | always: every start every frame | motion:
                                     # the guess alone
    doubt_residual_ratio: Positive = 1.5  # an alignment is in doubt when its residual is above this × the median
                                     # residual of the last tracked frames (their own level, not a fixed one)
    relocalise_iterations: Annotated[list[int], Range(ge=0), Length(ge=1)] = field(
        default_factory=lambda: [20, 10, 4])  # dense re-localisation's ICP iterations per level (coarse → fine;
                                     # as many levels as icp.iterations, else icp.iterations)
    relocalise_level_dist_scale: Positive = 3.0  # its d_thr at level l: icp.dist_threshold × this**l
    slide_ratio: Annotated[float, Range(ge=0, lt=1)] = 0.004  # where the weakest eigenvalue of the motion start's
                                     # geometric AᵀA is below this fraction of the largest, ICP starts again
                                     # slide_steps along that direction (0 = never): projective ICP stops in other
                                     # minima along it (real TUM cabinet keyframes 13.0 → 3.3 cm; docs/TRACKING.md)
    slide_color_ratio: Annotated[float, Range(gt=0)] = 0.1  # ... unless colour lifts that direction above this
                                     # fraction of the largest (eᵀ(AᵀA + λ A_cᵀA_c)e / λmax): colour holds it
    slide_steps: Annotated[list[float], Range(gt=0), Length(ge=1)] = field(
        default_factory=lambda: [0.04, 0.08, 0.12])  # metres: those starts, each way along the weak direction
    score_gate: Positive = 0.03      # metres: starts that pass the checks are compared by the fraction of the
                                     # prediction within this of the frame at their pose (and its residual)
    min_inlier_ratio: Fraction = 0.15  # below → tracking failure (frame not fused)
    max_residual: Positive = 0.02    # metres RMS: above → tracking failure
    max_update_deg: Positive = 20.0  # pose change against the motion model above this → failure
    max_update_m: Positive = 0.3     # ... and this (metres) → failure
    relocalise: Annotated[str, OneOf("features", "none")] = "features"
                                     # after a failure, re-initialise with ORB+PnP (features) or not (none)
    start_at_ground_truth: bool = True  # start at the first frame's GT pose (same frame as GT in viewers)
    loop_closure: bool = True        # keyframes, place recognition, loop verification and pose-graph correction
                                     # of the poses and the map ([loop]; docs/LOOP_CLOSURE.md)
    active_window: NonNegativeInt = 200  # frames: tracking renders only surfels updated within this many fused frames
                                     # (ElasticFusion's active model; older ones stay in the map for loop closure);
                                     # 0 = the whole map


@dataclass
class VOConfig:
    n_features: Count = 1000         # ORB keypoints per frame at most (cv2.ORB_create(n_features))
    match: Annotated[str, OneOf("min_distance", "ratio")] = "min_distance"
                                     # min_distance: d < max(4·d_min, floor) | ratio: Lowe's ratio test
    min_distance_factor: Positive = 4.0  # min_distance mode: good = Hamming distance < factor · d_min ...
    min_distance_floor: NonNegative = 30.0  # ... or below this floor (so near-identical frames keep matches)
    ratio: Annotated[float, Range(gt=0, le=1)] = 0.8  # ratio mode: best distance < ratio · second best (knnMatch k=2)
    min_good_match: NonNegativeInt = 10  # fewer good matches → frame rejected
    min_inliers: NonNegativeInt = 5  # fewer RANSAC inliers → frame rejected
    min_inliers_init: NonNegativeInt = 20  # ICP initialiser / re-localisation (no motion-size check): fewer → none
    max_norm: Positive = 0.3         # ‖Δt‖ + min(2π − ‖r‖, ‖r‖) above this → frame rejected
    ransac_reprojection_px: Positive = 3.0  # RANSAC inlier threshold on the reprojection error (pixels)
    ransac_iterations: Count = 300   # RANSAC hypotheses at most (fewer once 0.99 confidence is reached)
    voxel_size: Positive = 0.02      # metres: downsampling of the joined cloud
    cloud_stride: Count = 4          # joined cloud: back-project every N-th pixel in u and v of each frame


@dataclass
class LoopConfig:
    keyframe_translation: Positive = 0.25  # metres moved since the last keyframe → a new keyframe
    keyframe_rotation_deg: Degrees = 20.0  # degrees turned since the last keyframe → a new keyframe
    keyframe_overlap: Fraction = 0.7  # fraction of the last keyframe's depth points still seen below this → a new
                                      # keyframe
    keyframe_min_frames: Count = 5   # frames between two keyframes at least (a keyframe costs ORB and a search)
    n_features: Count = 500          # ORB keypoints per keyframe at most
    max_hamming: Annotated[int, Range(ge=0, le=256)] = 40  # bits: before the vocabulary exists (first keyframes),
                                     # a descriptor's neighbour in another keyframe votes for it when closer than this
    min_score: Fraction = 0.15       # bag-of-words similarity (DBoW2's L1 score, 0 to 1; or the fraction of voting
                                     # descriptors before the vocabulary exists) below this → not a candidate
    candidates: Count = 3            # best-scoring earlier keyframes verified per keyframe at most
    min_frame_gap: Count = 60        # frames between a candidate keyframe and the current one at least, and at least
                                     # slam.active_window (nearer ones are odometry's business: tracking aligns to them)
    min_consistent: Count = 12       # pre-check: matches whose 3D distances to the others agree (within
                                     # consistent_m) at least, else rejected before PnP
    consistent_m: Positive = 0.05    # metres: pre-check tolerance on the distance between two matched 3D points
    min_pnp_inliers: Count = 25      # PnP RANSAC inliers at least
    min_inlier_ratio: Fraction = 0.2  # ICP between the two keyframes: inliers / valid pixels at least (two raw
                                      # frames of one place at 5 cm / 4 deg apart gave 0.30 on the synthetic room)
    max_residual: Positive = 0.015   # metres: ICP's RMS point-to-plane residual at most
    max_icp_change_deg: Degrees = 10.0  # ICP may move PnP's guess by at most this (degrees) ...
    max_icp_change_m: Positive = 0.15  # ... and this (metres), else the two disagree: rejected
    odometry_sigma_m: Positive = 0.01  # pose graph: standard deviation of an odometry edge's translation, metres
    odometry_sigma_deg: Positive = 0.5  # and of its rotation, degrees
    odometry_from_icp: bool = False  # pose graph: shape each odometry edge's covariance by the tracked frames' ICP
                                     # AᵀA (directions ICP could not observe get large variance; docs/LOOP_CLOSURE.md)
    keyframe_pnp: bool = False       # pose graph: also an edge between consecutive keyframes from PnP RANSAC on
                                     # their ORB features (loop sigmas, Huber): their motion observed apart from ICP
    loop_sigma_m: Positive = 0.02    # standard deviation of a loop edge's translation, metres
    loop_sigma_deg: Positive = 1.0   # and of its rotation, degrees
    robust: Annotated[str, OneOf("gnc", "cauchy", "huber", "none")] = "gnc"  # robust kernel on loop edges: gnc =
                                     # Geman–McClure by graduated non-convexity (GTSAM's GncLMOptimizer), which
                                     # also closes loops that start many sigmas away; cauchy / huber: plain LM
    robust_scale: Positive = 1.0     # cauchy / huber: the kernel's k, in standard deviations of the loop edge
    max_loop_error: Positive = 5.0   # after optimisation a loop edge further than this (its standard deviations,
                                     # Mahalanobis over 6 components) from the optimised poses was rejected by the
                                     # kernel: the poses and the map are left as they were
    min_loop_error: NonNegative = 0.5  # a verified loop whose edge is within this (its standard deviations) of the
                                     # current poses is kept in the graph but moves nothing until a larger loop: the
                                     # trajectory already agrees with it within the loop's own accuracy


@dataclass
class MeshConfig:
    voxel_size: Annotated[float, Range(ge=0.001, le=0.5)] = 0.01  # metres: the edge of the grid's cubes (docs/MESH.md)
    method: Annotated[str, OneOf("surfels", "depth")] = "depth"  # slam --mesh: depth = the run's depth frames
                                     # re-integrated at its poses; surfels = a signed distance splatted from the map's
                                     # confirmed surfels (ti-fusion mesh RUN_DIR: always). Room: F@1cm 0.984 vs 0.900
    truncation: Annotated[float, Range(ge=1.0, le=10.0)] = 4.0  # depth: voxels each side of a pixel's depth it writes
    depth_min_weight: NonNegative = 0.0  # depth: voxels with at most this many pixel samples are not meshed
    carve_frames: NonNegativeInt = 2  # depth: a voxel this many frames saw through (and more than saw a surface
                                     # at it) is empty space, so openings stay open; 0 = off (docs/MESH.md)
    carve_sigmas: NonNegative = 3.0  # depth: seen through = the depth beyond the voxel by more than the
                                     # truncation plus this many σ(depth) of the sensor's noise
    min_weight: NonNegative = 3.0    # only surfels at least this confident are meshed (fusion.unstable_weight: the
                                     # confirmed ones, never removed as unstable)
    band: Annotated[float, Range(ge=1.0, le=4.0)] = 2.0  # voxels: how far along its normal a surfel writes its distance
    max_reach: Annotated[float, Range(ge=1.0, le=4.0)] = 2.0  # voxels: a surfel writes across its normal out to its
                                     # radius, at least 1 voxel and at most this (gaps wider than twice it stay open)
    max_voxels: Count = 40_000_000   # the sparse grid's bound (~2 GB with marching cubes' copies): more stops with a message
    max_triangles: NonNegativeInt = 0  # > 0: decimate the mesh to at most this many triangles (vertex clustering)
    log_triangles: NonNegativeInt = 300_000  # /map/mesh in the log: decimated to at most this many triangles; 0 = not logged
    after_run: bool = False          # slam: mesh the map at the end of the run (slam --mesh): mesh.ply, mesh.glb, /map/mesh


@dataclass
class MapConfig:
    save_map: Annotated[str, Text("a folder path", path=True), Flag("DIR", commands=("slam",))] = ""
                                     # where the run's saved map goes (map.json and map.bin, docs/MAPS.md), a new
                                     # folder or one holding a saved map, which it replaces; "" = map/ in the run
                                     # folder
    map: Annotated[str, Text("a run folder or a saved map", path=True), Flag("RUN_OR_MAP_DIR", commands=("slam",))] = ""
                                     # a saved map to start from (a run folder holding map/, or the map's folder): the
                                     # run is a second session in it, not localised until a frame finds itself in the
                                     # map; its trajectory is in the map's frame (docs/MAPS.md)
    localize: Annotated[bool, Flag(commands=("slam",))] = False  # with map: track against the map without changing
                                     # it (no fusion, no keyframes; no saved map written)
    unfound: Annotated[str, OneOf("fail", "map-anyway"), Flag(commands=("slam",))] = "fail"  # with map, a session
                                     # that never finds itself in it: fail = every frame tries, none gets a pose, the
                                     # run exits with status 3 | map-anyway = after find_frames frames it maps on in
                                     # its own frame, the loaded map set aside
    find_frames: Count = 30          # map-anyway: frames a session tries to find itself in the map before it maps on


@dataclass
class LogConfig:
    map_every: NonNegativeInt = 30   # frames between /map/points messages (and one at the end); 0 = at the end only
    map_max_points: Count = 200_000  # /map/points is downsampled to at most this many points
    depth_every: NonNegativeInt = 10  # frames between /camera/depth images; 0 = none
    progress: bool = True            # progress bar on the terminal


@dataclass
class Config:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    synth: SynthConfig = field(default_factory=SynthConfig)
    pyramid: PyramidConfig = field(default_factory=PyramidConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    slam: SLAMConfig = field(default_factory=SLAMConfig)
    vo: VOConfig = field(default_factory=VOConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    map: MapConfig = field(default_factory=MapConfig)
    log: LogConfig = field(default_factory=LogConfig)

    def frame_input_level(self, width: int) -> int:
        """How many pyramid steps a frame ``width`` px wide is averaged down on input: to the map's level
        (``fusion.level``), so the frame is smoothed and tracked at the map's resolution."""
        return self.fusion.map_level(width)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _read_file(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "config file not found")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise InputError(path, f"config is not UTF-8 text (line {line}, byte {exc.object[exc.start:exc.start + 1]!r}): "
                               "save it as UTF-8") from None
    except OSError as exc:
        raise InputError(path, f"cannot read config: {exc.strerror or exc}") from None
    data = _parse_text(path, text)
    if _too_big(data):
        raise InputError(path, f"config holds more than {MAX_CONFIG_VALUES} values (YAML aliases that expand "
                               "into each other?): a config is a few tables of settings")
    if not isinstance(data, dict):
        raise InputError(path, f"config's top level is {_type_name(data)}: expected a table of sections "
                               "(e.g. icp: with its settings)")
    return data


# A config file holds a few hundred values at most; YAML aliases can make a few hundred bytes expand into
# billions (an "alias bomb"), which no check may walk or print in full.
MAX_CONFIG_VALUES = 100_000


def _too_big(data: Any) -> bool:
    """Whether ``data`` expands to more than MAX_CONFIG_VALUES values (stops counting there)."""
    count, stack = 0, [data]
    while stack:
        item = stack.pop()
        count += 1
        if count > MAX_CONFIG_VALUES:
            return True
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
    return False


def _type_name(value: Any) -> str:
    return {list: "a list", str: "text", bool: "true/false", type(None): "empty"}.get(
        type(value), "a number" if isinstance(value, numbers.Number) else type(value).__name__)


def _parse_text(path: Path, text: str) -> Any:
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
    except Exception as exc:  # parse errors from any of the three readers: one line, where the reader says
        raise InputError(path, f"cannot parse config: {_one_line(exc)}") from None
    raise InputError(path, "config must be .toml, .yaml/.yml or .json")


def _one_line(exc: Exception) -> str:
    """A parser's error in one line: YAML's problem and its line and column (its multi-line message quotes the
    text with a caret), TOML's and JSON's message as they give it."""
    mark = getattr(exc, "problem_mark", None)
    if mark is not None:
        problem = getattr(exc, "problem", None) or getattr(exc, "context", None) or "syntax error"
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    return " ".join(str(exc).split())


def _show(value: Any, limit: int = 200) -> str:
    """A value as the user wrote it, near enough: text quoted, None as None; cut after ``limit`` characters."""
    if isinstance(value, (list, dict)) and _too_big(value):
        return f"a {type(value).__name__} of more than {MAX_CONFIG_VALUES} values"
    text = repr(value) if isinstance(value, str) else json.dumps(value) if isinstance(value, list) else str(value)
    return text if len(text) <= limit else text[:limit] + "..."


def check_value(section: str, key: str, value: Any, where: str = "config") -> Any:
    """``value`` for ``section.key`` as its field's type, or InputError: one line naming the key, the value
    and what the field allows (``where``: the file, or --set)."""
    rule = rules(type(getattr(Config(), section)))[key]
    try:
        return rule.check(value)
    except ValueError:
        raise InputError(None, f"{where}: {section}.{key} = {_show(value)}: must be {rule.describe()}") from None


def check_config(config: Config, where: str = "config") -> Config:
    """Every field of ``config`` checked against its rule (for a config built in Python)."""
    for section in dataclasses.fields(config):
        values = getattr(config, section.name)
        for key in rules(type(values)):
            setattr(values, key, check_value(section.name, key, getattr(values, key), where))
    return config


def _set_field(config: Config, section: str, key: str, value: Any, where: str) -> None:
    """Set ``section.key`` to ``value`` checked against its rule."""
    section_obj = getattr(config, section)
    names = {f.name for f in dataclasses.fields(section_obj)}
    if key not in names:
        if (section, key) in REMOVED:
            raise InputError(None, f"{where}: {section}.{key} was removed: {REMOVED[section, key]}")
        raise InputError(None, f"{where} [{section}]: unknown setting {key!r} (known: {', '.join(sorted(names))})")
    setattr(section_obj, key, check_value(section, key, value, where))


# Settings that are gone, with what replaced them, so an old config file is told why in its one error line
# (what each removed ablation measured is in docs/BENCHMARKS.md, "Settled and removed settings").
REMOVED = {
    **{("icp", name): f"moved to pyramid.{name}" for name in ("normal_max_depth_jump", "depth_smooth_radius")},
    ("icp", "pyramid_depth_sigma"): "moved to pyramid.depth_sigma",
    ("icp", "solver"): "the 6×6 step is always solved by Cholesky (LU and QR agreed with it; docs/BENCHMARKS.md)",
    ("icp", "converged_update"): "the result is converged when the last update passed its level's stop test "
                                 "(icp.stop_update at the finest)",
    ("loop", "odometry_info_ratio"): "fixed at 1 (the inverse information; docs/BENCHMARKS.md)",
    ("loop", "odometry_max_scale"): "fixed at 1e6 (docs/BENCHMARKS.md)",
    ("fusion", "association"): "always Keller's: the nearest surfel that passes the filters (docs/BENCHMARKS.md)",
    ("fusion", "render_max_half"): "fixed at 0: each surfel at its own pixel (1 cost ATE; docs/BENCHMARKS.md)",
    ("fusion", "render_fill_half"): "fixed at 1, coarse levels only (0 lost the synthetic loop; BENCHMARKS.md)",
    ("slam", "tracking"): "the frame is always aligned to the map rendered at the last pose (docs/BENCHMARKS.md)",
    ("slam", "track_at_map_level"): "the frame is always tracked at the map's resolution (docs/BENCHMARKS.md)",
    ("loop", "gnc_min_weight"): "fixed at 0.1 (GNC leaves outliers near 0; docs/BENCHMARKS.md)",
    ("slam", "anchor_to_ground_truth"): "renamed slam.start_at_ground_truth ('anchor' is a surfel's keyframe)",
    ("dataset", "read_threads"): "renamed dataset.read_workers: frames are read in worker processes, not threads",
}

# Sections that were renamed, with the new names of their keys.
RENAMED_SECTIONS = {"maps": "it is [pyramid] (pyramid.depth_smooth_radius, pyramid.normal_max_depth_jump, "
                            "pyramid.depth_sigma; 'map' is the surfel map)"}

# The tuning knobs: docs/CONFIG.md lists them apart from the main settings, because their defaults are what the
# benchmarks settled on and most runs leave them alone. They stay in their stage's section, so that a key keeps
# one name in files, --set and the code.
ADVANCED = {
    "dataset": ("read_workers",),
    "synth": ("fx", "min_range", "max_range", "grazing_deg", "baseline", "subpixel", "sensor_width", "color_noise",
              "depth_noise_scale", "edge_shadow", "edge_holes", "flying_pixels",
              "exposure", "jpeg_quality", "color_offset_ms"),
    "pyramid": ("normal_max_depth_jump", "depth_sigma", "depth_smooth_radius"),
    "icp": ("normal_threshold_deg", "robust_scale", "depth_weighting", "min_inliers", "max_condition",
            "stop_update", "level_dist_scale", "color_robust_scale", "color_finest_scale", "weak_ratio"),
    "fusion": ("dist_threshold", "normal_threshold_deg", "confidence_weighting", "remove_unstable", "unstable_weight",
               "unstable_age", "remove_free_space", "free_space_margin", "depth_weighting", "confidence_sigma",
               "skip_covered", "render_min_weight"),
    "slam": ("motion_model", "motion_damping", "hypotheses", "doubt_residual_ratio",
             "relocalise_iterations", "relocalise_level_dist_scale", "score_gate", "min_inlier_ratio", "max_residual",
             "max_update_deg", "max_update_m", "active_window"),
    "vo": ("match", "min_distance_factor", "min_distance_floor", "ratio", "min_good_match", "min_inliers",
           "min_inliers_init", "max_norm", "ransac_reprojection_px", "ransac_iterations", "cloud_stride"),
    "loop": ("keyframe_translation", "keyframe_rotation_deg", "keyframe_overlap", "keyframe_min_frames", "n_features",
             "max_hamming", "min_score", "candidates", "min_frame_gap", "min_consistent", "consistent_m",
             "min_pnp_inliers", "min_inlier_ratio", "max_residual", "max_icp_change_deg", "max_icp_change_m",
             "odometry_sigma_m", "odometry_sigma_deg", "odometry_from_icp", "keyframe_pnp", "loop_sigma_m",
             "loop_sigma_deg", "robust", "robust_scale", "max_loop_error", "min_loop_error"),
    "mesh": ("truncation", "depth_min_weight", "min_weight", "band", "max_reach", "max_voxels"),
}


def apply_dict(config: Config, data: dict, where: str = "config", base: Path | None = None) -> Config:
    """Set every ``section.key`` of ``data``; ``base``: the folder that relative paths in it are relative to
    (a config file's own folder; None for --set, whose paths are the working directory's)."""
    if not isinstance(data, dict):
        raise InputError(None, f"{where}: config is {_type_name(data)}: expected a table of sections")
    sections = [f.name for f in dataclasses.fields(config)]
    for section, values in data.items():
        if section in RENAMED_SECTIONS:
            raise InputError(None, f"{where}: section {section!r} was renamed: {RENAMED_SECTIONS[section]}")
        if section not in sections:
            raise InputError(None, f"{where}: unknown section {section!r} (known: {', '.join(sections)})")
        if not isinstance(values, dict):
            raise InputError(None, f"{where}: section {section!r} must be a table of settings (e.g. [{section}] "
                                   f"in TOML), not {_type_name(values)} ({_show(values)})")
        for key, value in values.items():
            if base is not None:
                value = _relative_to(base, section, key, value)
            _set_field(config, section, key, value, where)
    return config


def _relative_to(base: Path, section: str, key: str, value: Any) -> Any:
    """A path setting's value (``Text(path=True)``) relative to ``base``; any other value as it is."""
    rule = rules(type(getattr(Config(), section))).get(key)  # an unknown key is refused when it is set
    if rule is None or rule.text is None or not rule.text.path or not isinstance(value, str) or not value.strip():
        return value
    if key.endswith("intrinsics") and len(value.replace(",", " ").split()) == 4 and not (base / value).exists():
        return value  # "fx,fy,cx,cy", not a file
    path = Path(value).expanduser()
    return value if path.is_absolute() else str(base / path)


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"icp.iterations=[10,5,4]"`` → ("icp", "iterations", [10, 5, 4]). A text field takes the text as
    written (``dataset.path=2023`` is the folder "2023", not a number)."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise InputError(None, f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. icp.dist_threshold=0.05")
    lhs, rhs = text.split("=", 1)
    section, key = (part.strip() for part in lhs.split(".", 1))
    rhs = rhs.strip()
    try:
        value = ast.literal_eval(rhs)
    except (ValueError, SyntaxError):
        value = rhs
    if not isinstance(value, str) and _kind(section, key) is str:
        value = rhs
    return section, key, value


def _kind(section: str, key: str) -> type | None:
    """The type of field ``section.key`` (None when there is no such field)."""
    section_type = type(getattr(Config(), section, None))
    if not dataclasses.is_dataclass(section_type):
        return None
    rule = rules(section_type).get(key)
    return rule.kind if rule else None


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the file (if any), then ``--set`` overrides; every value checked as it is set."""
    config = Config()
    if path:
        apply_dict(config, _read_file(Path(path)), where=str(path), base=Path(path).parent)
    for text in overrides or []:
        section, key, value = parse_override(text)
        apply_dict(config, {section: {key: value}}, where="--set")
    return config
