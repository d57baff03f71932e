"""The surfel map on the Taichi side: storage (``surfels``) with the stages of a fusion step (``fusion``) and
the prediction (``prediction``) as methods.

This is the Python edge of the kernels: each method converts poses and thresholds into kernel arguments,
runs a stage's kernels in order, and keeps what must survive between stages (the surfel count, which
surfels the per-surfel projection scratch is current for). Stage methods take the frame's fields at the
map's level (``FramePyramid.vertex[l]`` etc.) and 4×4 camera-to-world poses (float64 NumPy).
"""

import math
from typing import NamedTuple

import numpy as np
import taichi as ti

from ti_fusion.errors import MapCapacityError
from ti_fusion.kernels import fusion, prediction
from ti_fusion.kernels.common import PoseArgs
from ti_fusion.kernels.fusion import FusionImages
from ti_fusion.kernels.prediction import PredictionImages
from ti_fusion.kernels.surfels import Pool, SurfelStore, ThisStart


class AddCounts(NamedTuple):
    """What ``SurfelMap.add`` did, in pixels."""

    new: int  # pixels that became surfels
    merged: int  # pixels merged into a surfel (by the ``merge`` before)
    covered: int  # unassociated pixels not added: a neighbour's merged surfel covers them


class SurfelMap(SurfelStore):
    """A growable surfel map with the stages of one fusion step and the renderer.

    ``count`` surfels are live, at indices [0, count).
    """

    counts = ThisStart()
    _pose = ThisStart()

    def __init__(self, capacity: int = 4_000_000, grow: bool = True):
        super().__init__(capacity, grow)
        # per-call results (fusion.C_*; one field serves every map)
        self.counts = Pool.field("step_counts", lambda: ti.field(ti.i32, shape=fusion.N_COUNTS))
        self._count_on_device = False  # a deferred add or removal changed the count: ``step_counts`` reads it
        self._pose = Pool.field("pose_args", PoseArgs)  # (to world, to camera) of the last pose, on the device

    @property
    def count(self) -> int:
        """Live surfels: after a deferred add or removal, read from the device (``step_counts``)."""
        if getattr(self, "_count_on_device", False):
            self.step_counts()
        return self._count

    @count.setter
    def count(self, value: int) -> None:
        self._count = int(value)
        self._count_on_device = False  # set from the host: the host's count holds

    def fusion_images(self, height: int, width: int) -> FusionImages:
        """The fusion step's work images at this resolution: shared by all maps, overwritten by the next
        step at this resolution."""
        return Pool.image_set(FusionImages, height, width)

    def prediction_images(self, height: int, width: int) -> PredictionImages:
        """The renderer's images at this resolution: shared by all maps, overwritten by the next render."""
        return Pool.image_set(PredictionImages, height, width)

    # -- 1-3: project, filter pass 1, filter pass 2 ------------------------------------------------------
    def associate_compatible(self, pose: np.ndarray, intrinsics, vertex, normal, dist_threshold: float,
                             normal_threshold_deg: float) -> FusionImages:
        """Keller's order: filter passes 1 and 2 for every surfel in one projection, then per pixel the
        nearest surfel that passed: ``img.assoc`` holds it or -1."""
        H, W = vertex.shape
        img = self.fusion_images(H, W)
        cos_threshold = math.cos(math.radians(normal_threshold_deg))
        to_world, to_camera = self._pose(pose)
        fusion.associate(self.arrays, self.count, img, vertex, normal, to_world, to_camera, *intrinsics.as_tuple(),
                         dist_threshold, cos_threshold)
        self._projected = self.count
        return img

    # -- 4-5: merge and add --------------------------------------------------------------------------------
    def merge(self, img: FusionImages, vertex, normal, pose, intrinsics, frame_index: int,
              confidence: bool, sigma: float, has_color: bool, depth_weighted: bool = False,
              anchor: int = 0, color=None) -> None:
        """Average the frame into the surfels ``img.assoc`` chose; they take ``anchor``. With ``has_color``
        the colour is read from ``color``, the frame's colour packed at this resolution (a Taichi field,
        e.g. ``FramePyramid.packed_color``), or from ``img.color`` (``FusionImages.set_color``) when None."""
        if self._projected > 0:
            if confidence:
                img.radial_confidence(intrinsics.cx, intrinsics.cy, sigma)
            fusion.merge_listed(self.arrays, img, vertex, normal, self._pose(pose)[0], intrinsics.fx,
                                fusion.weight_bits(confidence, depth_weighted),
                                img.color if color is None else color, int(has_color), frame_index, int(anchor))

    def add(self, img: FusionImages, vertex, normal, pose, intrinsics, frame_index: int, confidence: bool,
            sigma: float, has_color: bool, depth_weighted: bool = False,
            cover: tuple[float, float] | None = None, anchor: int = 0, defer: bool = False,
            color=None) -> AddCounts | None:
        """Append the valid unassociated pixels as surfels (with ``anchor``; their colour as ``merge``
        reads it, from ``color`` or ``img.color``). With ``cover`` = (dist_threshold,
        normal_threshold_deg), unassociated pixels on the disc of a neighbour's merged surfel are marked
        (``img.assoc`` = COVERED) in the same pass, and not added.

        With ``defer``, nothing is read back: the map is grown for the worst case (every pixel new) unless
        it already has room for it, the count stays on the device, and None is returned; ``step_counts``
        reads what the step did, once, after ``remove(..., defer=True)``."""
        dist, angle = cover if cover is not None else (0.0, 0.0)
        to_world = self._pose(pose)[0]
        H, W = img.assoc.shape
        weights = fusion.weight_bits(confidence, depth_weighted)
        color = img.color if color is None else color
        if confidence:
            img.radial_confidence(intrinsics.cx, intrinsics.cy, sigma)
        if defer and self.count + H * W <= self.capacity:  # room for every pixel: one launch, nothing read
            fusion.add_step(self.arrays, self.count, img, vertex, normal, to_world, dist, math.cos(math.radians(angle)),
                            cover is not None, intrinsics.fx, weights, color, int(has_color), frame_index,
                            int(anchor), self.counts)
            self._count_on_device = True
            return None
        fusion.count_segments(img, vertex, normal, to_world, dist, math.cos(math.radians(angle)), cover is not None)
        fusion.scan_segments(img, self.counts, self.count)
        c = self._read_counts()  # the exact count, to grow the map for it
        counts = AddCounts(int(c[fusion.C_NEW]), int(c[fusion.C_MERGED]), int(c[fusion.C_COVERED]))
        self.ensure_capacity(self.count + counts.new)  # before any write: grow or raise
        if counts.new == 0:
            return None if defer else counts
        fusion.append_new(self.arrays, self.count, img, vertex, normal, to_world, intrinsics.fx, weights, color,
                          int(has_color), frame_index, int(anchor), self.counts)
        if defer:
            self._count_on_device = True
            return None
        self._check_lost(int(self.counts[fusion.C_LOST]))
        self.count += counts.new
        return counts

    def _read_counts(self) -> np.ndarray:
        """``counts`` as NumPy (``fusion.read_counts``)."""
        out = np.empty(fusion.N_COUNTS, np.int32)
        fusion.read_counts(self.counts, out)
        return out

    def _check_lost(self, lost: int) -> None:
        if lost:  # cannot happen after ensure_capacity; never let it pass silently
            raise MapCapacityError(f"{lost} new surfels did not fit (capacity {self.capacity}): "
                                   f"raise fusion.capacity")

    # -- 6: remove ------------------------------------------------------------------------------------------
    def remove(self, frame_index: int, unstable: bool, unstable_weight: float, unstable_age: int,
               free_space: bool = False, free_space_margin: float = 0.05, depth=None,
               defer: bool = False) -> int | None:
        """Drop unstable / free-space-violating surfels and compact in place; returns how many went. With
        ``defer`` (after ``add(..., defer=True)``), every kernel runs with the counts on the device, even
        when nothing goes (they then do nothing), and None is returned (``step_counts``)."""
        if not (unstable or free_space):
            return None if defer else 0
        if free_space and depth is None:
            raise ValueError("free-space removal needs the frame's depth field")
        if not self._count_on_device:
            if self.count == 0:
                return None if defer else 0
            self.counts[fusion.C_TOTAL] = self.count  # the removal's n
        if depth is None:
            depth = Pool.field("no_depth", lambda: ti.field(ti.f32, shape=(1, 1)))  # never read
        args = (self.arrays, self.counts, self._projected, frame_index, int(unstable), unstable_weight, unstable_age,
                bool(free_space), free_space_margin, depth)
        if defer:
            fusion.remove_step(*args)
            self._count_on_device = True
            return None
        fusion.mark_removal(*args)
        fusion.sum_removals(self.arrays, self.counts)
        removed = int(self.counts[fusion.C_REMOVED])
        if removed > 0:
            fusion.fill_holes(self.arrays, self.counts)
            self.count -= removed
            self._projected = 0  # indices moved: the projection scratch is stale
        return removed

    def step_counts(self) -> dict[str, int]:
        """What the last step did (new, merged, covered, removed, surfels): one read of the counts, which
        also brings the host's ``count`` up to date after a deferred add and removal."""
        c = self._read_counts()
        if self._count_on_device:
            self._count_on_device = False
            self._check_lost(int(c[fusion.C_LOST]))
            self.count = int(c[fusion.C_KEPT])
            if c[fusion.C_REMOVED] > 0:
                self._projected = 0  # indices moved: the projection scratch is stale
        return {"new": int(c[fusion.C_NEW]), "merged": int(c[fusion.C_MERGED]), "covered": int(c[fusion.C_COVERED]),
                "removed": int(c[fusion.C_REMOVED]), "surfels": self.count}

    # -- loop closure ---------------------------------------------------------------------------------------
    def apply_corrections(self, corrections: np.ndarray) -> int:
        """Move every surfel with the rigid correction of its anchor: ``corrections`` is (K, 4, 4), anchor k
        < K gets p ← R_k p + t_k and n ← R_k n (float32 on the map); surfels with other anchors, and those
        whose anchor's correction is exactly the identity, are left as they are (bit for bit). Returns how
        many anchors moved."""
        T = np.asarray(corrections, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"corrections must be (K, 4, 4) rigid transforms, not of shape {T.shape}")
        if not np.all(np.isfinite(T)):
            raise ValueError("corrections must be finite")
        K = len(T)
        flat = np.zeros((max(K, 1), 12), np.float32)  # a zero-length ndarray argument is not allowed
        moved = np.zeros(max(K, 1), np.int32)
        if K:
            flat[:K] = np.concatenate([T[:, :3, :3].reshape(K, 9), T[:, :3, 3]], axis=1)
            identity = np.concatenate([np.eye(3).ravel(), np.zeros(3)]).astype(np.float32)
            moved[:K] = np.any(flat[:K] != identity, axis=1)
        n_moved = int(moved.sum())
        if self.count > 0 and n_moved:
            fusion.apply_corrections(self.arrays, self.count, flat, moved)
            self._projected = 0  # positions changed: the fusion projection is stale
        return n_moved

    def reactivate(self, frame_index: int, min_weight: float) -> None:
        """Loop closure: every live surfel of weight ≥ ``min_weight`` counts as updated at ``frame_index``,
        so the active window (``render(min_time=...)``) includes it again; weaker surfels keep their last
        update, and with it their turn in the removal of unstable surfels."""
        if self.count > 0:
            fusion.reactivate(self.arrays, self.count, int(frame_index), float(min_weight))

    # -- prediction -----------------------------------------------------------------------------------------
    def render(self, pose: np.ndarray, intrinsics, out_vertex=None, out_normal=None, out_depth=None,
               min_weight: float = 0.0, max_half: int = 1, fill_half: int = 0,
               min_time: int = -2**31, holes_apart: bool = False, out_filled=None) -> PredictionImages:
        """Predicted vertex / normal / depth maps in the camera frame of ``pose`` (zero = no surfel).

        Outputs are Taichi fields of shape (intrinsics.height, intrinsics.width), e.g. a FramePyramid' level
        0; left out, they are the returned images' ``vertex``, ``normal``, ``depth`` fields (valid until
        the next render at this resolution). Surfels with weight ≥ ``min_weight`` that face the camera
        are splatted as discs reaching at most ``max_half`` pixels from their centre pixel; the vertex lies
        on the pixel's ray, at the depth where the ray meets the disc. A pixel that no surfel projects to
        (a hole) takes the nearest disc its ray meets within max(``max_half``, ``fill_half``) pixels.
        Surfels last updated before frame ``min_time`` (inactive: ElasticFusion's time window) are left out.

        With ``holes_apart`` (``max_half`` 0 and ``fill_half`` 1 only), the outputs keep the holes (what
        ``clear_holes`` leaves) and ``out_filled`` (default: the returned images' ``filled_depth``) the filled
        depth, in the same launch and for less than the fill alone costs (``prediction.splat_apart_loop``).
        """
        if holes_apart and (max_half, fill_half) != (0, 1):
            raise ValueError(f"holes_apart renders max_half 0 and fill_half 1, not {max_half} and {fill_half}")
        img = self.prediction_images(intrinsics.height, intrinsics.width)
        to_camera = self._pose(pose)[1]
        fx, fy, cx, cy = intrinsics.as_tuple()
        prediction.render(self.arrays, self.count, img, to_camera, fx, fy, cx, cy, float(min_weight), int(min_time),
                          int(max_half), int(fill_half), img.vertex if out_vertex is None else out_vertex,
                          img.normal if out_normal is None else out_normal,
                          img.depth if out_depth is None else out_depth, bool(holes_apart),
                          img.filled_depth if out_filled is None else out_filled)
        self._projected = 0  # the projection scratch now holds the render's projection, not the fusion step's
        return img

    def clear_holes(self, intrinsics, out_vertex, out_normal, out_depth) -> None:
        """After ``render`` with ``max_half`` = 0 into these outputs: zero the pixels that only the hole fill
        reached (no surfel projects to them), leaving each surfel's own pixel."""
        img = self.prediction_images(intrinsics.height, intrinsics.width)
        prediction.clear_holes(img, out_vertex, out_normal, out_depth)

    def render_image(self, pose: np.ndarray, intrinsics, by_normal: bool = False, min_weight: float = 0.0,
                     max_half: int = 3, background=(0.12, 0.12, 0.12)) -> np.ndarray:
        """uint8 RGB view of the map from ``pose``: surfel colours, or world normals as (n + 1) / 2."""
        return self.render_images(pose, intrinsics, (by_normal,), min_weight, max_half, background)[0]

    def render_images(self, pose: np.ndarray, intrinsics, by_normal=(False, True), min_weight: float = 0.0,
                      max_half: int = 3, background=(0.12, 0.12, 0.12)) -> list[np.ndarray]:
        """``render_image`` for each of ``by_normal``, from one render (the shading reads only its index map)."""
        img = self.render(pose, intrinsics, min_weight=min_weight, max_half=max_half)
        out = []
        for normal in by_normal:
            prediction.shade(self.arrays, img, int(normal), np.asarray(background, dtype=np.float32))
            out.append((np.clip(img.image.to_numpy(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
        return out
