"""Point-based fusion: a surfel map that frames with known poses are integrated into.

    mapper = SurfelMapper(config.fusion)
    stats = mapper.integrate(frame_pyramid, frame.color, pose, frame_index)   # merged, added, removed, surfels
    mapper.render_pyramid(frame_pyramid, pose, intrinsics)   # the prediction that ICP tracks against
    mapper.export_ply("map.ply")

    mapper.anchor = keyframe_id       # written into every surfel the next integrate calls create or update
    mapper.apply_corrections(T)       # loop closure: (K, 4, 4), surfels of anchor k move by T[k]

The map and its stages live in ``ti_fusion.kernels.surfel_map`` (kernels in ``ti_fusion.kernels.fusion`` and
``ti_fusion.kernels.prediction``); this layer holds the configuration, uploads the frame's colour, times the
stages and reports what changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics
from ti_fusion.config import FusionConfig
from ti_fusion.kernels.surfel_map import SurfelMap
from ti_fusion.timing import StageTimer, timed_stage

STAGES = ("project", "merge", "add", "remove")
# The prediction for tracking shows each surfel at its own pixel (a disc reaching a pixel further dilated occluding
# edges and cost ATE), and builds its coarse levels from a render whose holes take the nearest disc within this
# many pixels (without it they empty out walking forward; docs/BENCHMARKS.md, "Settled and removed settings"). 1, or
# 0 for no fill: the render's ``holes_apart`` takes 1 only.
FILL_HALF = 1


@dataclass
class FusionStats:
    """What one ``integrate`` call did."""

    merged: int  # pixels averaged into an existing surfel
    added: int  # new surfels
    removed: int  # surfels dropped (unstable or free-space violations)
    surfels: int  # live surfels afterwards
    valid_pixels: int  # pixels with a valid vertex and normal (the naive map would add them all)
    covered: int = 0  # unassociated pixels not added: a neighbour's merged surfel covers them
    ms: dict[str, float] = field(default_factory=dict)  # per stage (only with a timer)


class SurfelMapper:
    """Integrates RGB-D frames with known camera-to-world poses into a surfel map (Keller et al. 2013)."""

    def __init__(self, config: FusionConfig | None = None):
        self.config = config or FusionConfig()
        self.map = SurfelMap(self.config.capacity, self.config.grow)
        # the anchor (keyframe id) that ``integrate`` writes into the surfels it creates or updates, so that
        # ``apply_corrections`` can move them with that keyframe's pose correction after a loop closure
        self.anchor: int = 0

    @property
    def count(self) -> int:
        return self.map.count

    def frame_level(self, frame_pyramid) -> int:
        """The map's level (``fusion.level``, counted from the input) counted in ``frame_pyramid``'s levels:
        the maps ``integrate`` fuses, and where a frame's colour is packed for it; ValueError if the pyramid
        does not have it."""
        input_width = frame_pyramid.input_shape[1]
        map_level = self.config.map_level(input_width)
        level = map_level - frame_pyramid.input_level
        if not 0 <= level < frame_pyramid.levels:
            raise ValueError(f"fusion.level {map_level} (for {input_width} px wide frames) needs frame maps "
                             f"with level {map_level} of the input; these have levels {frame_pyramid.input_level}"
                             f"..{frame_pyramid.input_level + frame_pyramid.levels - 1}")
        return level

    def integrate(self, frame_pyramid, color: np.ndarray | None, pose: np.ndarray, frame_index: int,
                  timer: StageTimer | None = None) -> FusionStats:
        """Fuse one frame: project, filter (pass 1 and 2), merge, add, remove.

        frame_pyramid: a computed ``FramePyramid`` (the map's level is used); color: uint8 H×W×3 RGB or None
        (packed here, unless the pyramid's ``compute`` packed this image at the map's level already:
        ``FramePyramid.packed_color``, which saves a wait for the device per frame off the CPU);
        pose: 4×4 camera-to-world; frame_index: the time stamp stored in the surfels (frames since start).
        With a ``timer``, every stage is synchronised and timed (ms in the stats and in the timer).
        """
        cfg = self.config
        level = self.frame_level(frame_pyramid)
        map_level = level + frame_pyramid.input_level  # counted from the input resolution
        vertex, normal, depth = frame_pyramid.vertex[level], frame_pyramid.normal[level], frame_pyramid.depth[level]
        K: Intrinsics = frame_pyramid.intrinsics[level]
        H, W = frame_pyramid.shapes[level]
        pose = np.asarray(pose, dtype=np.float64)
        ms: dict[str, float] = {}
        stage = partial(timed_stage, timer, sync=ti.sync, into=ms)

        with stage("project"):  # Keller's order: each pixel's nearest surfel among those that pass the filters
            img = self.map.associate_compatible(pose, K, vertex, normal, cfg.dist_threshold, cfg.normal_threshold_deg)
            has_color = color is not None
            packed = frame_pyramid.packed_color(level, color) if has_color else None
            if has_color and packed is None:  # the map level's pixels of the input's colour, packed on the device
                img.set_color(color, 2**map_level)
        with stage("merge"):
            self.map.merge(img, vertex, normal, pose, K, frame_index, cfg.confidence_weighting,
                           cfg.confidence_sigma, has_color, cfg.depth_weighting, self.anchor, packed)
        # add and remove pass their counts on the device (defer): the step's counts cross once, at its end
        with stage("add"):  # with skip_covered, covered pixels are marked in the same pass and not added
            cover = (cfg.dist_threshold, cfg.normal_threshold_deg) if cfg.skip_covered else None
            self.map.add(img, vertex, normal, pose, K, frame_index, cfg.confidence_weighting, cfg.confidence_sigma,
                         has_color, cfg.depth_weighting, cover, self.anchor, defer=True, color=packed)
        with stage("remove"):
            self.map.remove(frame_index, cfg.remove_unstable, cfg.unstable_weight, cfg.unstable_age,
                            cfg.remove_free_space, cfg.free_space_margin, depth, defer=True)
        c = self.map.step_counts()
        return FusionStats(c["merged"], c["new"], c["removed"], c["surfels"], c["merged"] + c["new"] + c["covered"],
                           c["covered"], ms)

    def apply_corrections(self, corrections: np.ndarray, reactivate_at: int | None = None) -> int:
        """Loop closure: move the map with the corrected poses. ``corrections`` (K, 4, 4): the rigid
        transform T_k = T_k,new · T_k,old⁻¹ (world frame) of anchor k; every surfel of anchor k < K gets
        p ← R_k p + t_k, n ← R_k n; surfels of anchors ≥ K, and of anchors whose T_k is the identity,
        are untouched. Returns how many anchors moved.

        With ``reactivate_at`` (a frame count), every surfel of weight ≥ ``fusion.unstable_weight`` counts
        as updated then: the corrected old surfels agree with the current pose again, so they are active
        (tracked against) again, as ElasticFusion reactivates the model after a loop; only confirmed ones,
        or loops every few frames would keep unstable surfels from removal."""
        moved = self.map.apply_corrections(corrections)
        if reactivate_at is not None:
            self.map.reactivate(reactivate_at, self.config.unstable_weight)
        return moved

    def anchors(self) -> np.ndarray:
        """The anchor of every live surfel (int32, in map order)."""
        return self.map.to_numpy(("anchor",))["anchor"]

    # -- rendering -----------------------------------------------------------------------------------------
    def render_pyramid(self, frame_pyramid, pose: np.ndarray, intrinsics: Intrinsics,
                       min_weight: float | None = None, min_time: int = -2**31, intensity: bool = False) -> None:
        """Fill a ``FramePyramid`` with the prediction: every pyramid level from the rendered depth (with the
        maps' own settings), and level 0's vertex and normal maps straight from the
        surfels (averaged normals, smoother than normals from depth differences). Surfels below
        ``min_weight`` (default ``fusion.render_min_weight``) or last updated before frame ``min_time``
        (inactive: ElasticFusion's time window, ``slam.active_window``) are left out. With ``intensity``,
        the pyramid's intensity too: at each pixel the grey level of the surfel seen there (the model's side of
        the photometric term).

        The pyramid is built from a render whose holes (pixels no surfel projects to) take a neighbour's
        disc (``FILL_HALF``), while level 0 keeps the surfels' own pixels: the render writes both, the filled
        depth apart (``holes_apart``, into the pyramid's ``spare_depth``), and level 1 is averaged down from that.
        Why: surfels fused from afar
        lie up to two pixels apart once the camera comes nearer (fusion adds none where a neighbour's disc
        covers the pixel), and a coarse pixel exists only where its centre fine pixel has depth, so the coarse
        levels emptied (tracking lost on the synthetic corridor loop); filled at level 0 too, the synthetic
        room's ATE doubled (docs/KERNELS.md)."""
        if min_weight is None:
            min_weight = self.config.render_min_weight
        level0 = frame_pyramid.vertex[0], frame_pyramid.normal[0], frame_pyramid.depth[0]
        apart = FILL_HALF > 0
        img = self.map.render(pose, intrinsics, *level0, min_weight, 0, FILL_HALF, min_time, holes_apart=apart,
                              out_filled=frame_pyramid.spare_depth)
        frame_pyramid.compute_from_field(intrinsics, level0_maps=False,
                                         level1_from=frame_pyramid.spare_depth if apart else None)
        if intensity:
            frame_pyramid.intensity_from_surfels(img.view_index, self.map.arrays.color)  # the render's view

    def render_image(self, pose: np.ndarray, intrinsics: Intrinsics, by_normal: bool = False) -> np.ndarray:
        """uint8 RGB view of the map from ``pose`` (surfel colour, or world normal as (n + 1) / 2)."""
        return self.map.render_image(pose, intrinsics, by_normal)

    def render_images(self, pose: np.ndarray, intrinsics: Intrinsics, by_normal=(False, True)) -> list[np.ndarray]:
        """``render_image`` for each of ``by_normal``, from one render of the map."""
        return self.map.render_images(pose, intrinsics, by_normal)

    # -- export --------------------------------------------------------------------------------------------
    def to_numpy(self) -> dict[str, np.ndarray]:
        return self.map.to_numpy()

    def sample_points(self, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """(positions, uint8 RGB colours) of at most ``max_points`` surfels: every k-th, for log snapshots."""
        stride = max(1, -(-self.count // max(1, int(max_points))))
        data = self.map.to_numpy(("position", "color"), stride)
        # surfel colours are floats in [0, 255]; log_points reads float colours as [0, 1]
        return data["position"], np.clip(np.rint(data["color"]), 0, 255).astype(np.uint8)

    def export_ply(self, path: str | Path) -> Path:
        return self.ply_writer(path)()

    def ply_writer(self, path: str | Path):
        """A function that writes the map as it is now as a PLY file at ``path`` (and returns the path): the map
        is read here, the file written when it is called, with no Taichi (so on any thread)."""
        from ti_fusion.io.ply import write_ply

        data = self.map.to_numpy()
        # confidence and radius: what ``ti-fusion mesh map.ply`` needs to keep only confirmed surfels
        return lambda: write_ply(path, data["position"], data["normal"], data["color"],
                                 {"confidence": data["weight"], "radius": data["radius"]})
