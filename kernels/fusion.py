"""Point-based fusion (Keller et al. 2013): the kernels of one fusion step and the work images they own.

One step for a frame with camera-to-world pose T = [R | t] (``ti_fusion.kernels.surfel_map.SurfelMap``
runs the kernels, ``ti_fusion.mapping.mapper.SurfelMapper`` strings the stages together):

1. project    every surfel into the frame; per pixel, the surfel nearest in depth (``index_map``);
2. filter 1   the per-surfel mask "projects inside the image with positive depth" (``proj_pixel >= 0``,
              from the same projection);
3. filter 2   in Keller's order, in the same projection: every surfel of pass 1 is tested against its
              pixel's measurement (the frame's vertex within a distance and its normal within an angle of
              the surfel's) and the index map keeps the nearest that passed (``project_compatible_loop``; the
              ``assoc`` image), so a compatible surfel behind an incompatible one still merges. A pixel
              merges into at most one surfel and a surfel takes at most one pixel;
4. merge      associated surfels average in the measurement (weight 1, or Keller's radial confidence,
              optionally times the depth noise's inverse variance);
5. add        every valid pixel without an association becomes a new surfel, unless the disc of a surfel
              merged at a neighbouring pixel already holds its point (``count_segments``);
6. remove     unstable surfels (low weight, not updated for a while) and, optionally, surfels the frame
              sees through (free-space violations); the arrays are compacted in place.

Merge and add also write the frame's anchor (a keyframe id) into the surfels they touch; after a loop
closure, ``apply_corrections`` moves every surfel with its anchor's rigid pose correction.

Determinism: new surfels are appended in row-major pixel order (counts per row segment, a serial scan
over the segments, then per-segment writes), and removal fills the k-th hole below the new count with the
k-th surviving surfel above it (per-block lists and scans), so a run gives the same map on every run and
thread count, not just the same set. The loops over every surfel are branch-free and run over blocks of
BLOCK surfels (see docs/KERNELS.md for why and what that is worth).
"""

import math

import numpy as np
import taichi as ti

from ti_fusion.backend import on_cpu
from ti_fusion.kernels.common import (BLOCK, INT_MAX, LANES, Mat3, Rigid, Vec3, bits_depth, data_oriented, depth_bits,
                                      depth_noise_scale, is_valid, rigid)
from ti_fusion.kernels.index_map import IndexMap, build_loops, list_if, project_one, project_pack
from ti_fusion.kernels.surfels import copy_surfel

# Each image row is counted and appended in this many segments, so that the loops over segments have
# enough iterations to run on several threads.
SEGMENTS = 8
SQRT2 = math.sqrt(2.0)
MIN_COS_VIEW = 0.2  # radius = √2 z / (f |n_z|): |n_z| is clamped here so grazing surfels stay bounded
# Measurement weights (``measurement_weight``'s ``confidence`` bits): Keller's radial confidence, and the
# inverse variance of the depth noise relative to 1 m (as the ICP's ``depth_weighting``), capped.
RADIAL, DEPTH = 1, 2
DEPTH_WEIGHT_MAX = 4.0
FAR = 1e10  # world vertex of an invalid pixel (its world normal is zero, which is what project_compatible_loop tests)
COVERED = -2  # ``assoc`` of a pixel that a neighbour's merged surfel already covers: neither merged nor added

# What a step did, one int32 each in a ``counts`` field of N_COUNTS (read back in one copy): pixels that
# become new surfels, pixels merged, covered pixels, new surfels that found no room (``append_new``),
# surfels removed; the surfel count after the add (the removal's n) and after the removal (its m). The
# stages after the add take their loop bounds from TOTAL and KEPT on the device, so that a step needs no
# count from the host between its kernels.
C_NEW, C_MERGED, C_COVERED, C_LOST, C_REMOVED, C_TOTAL, C_KEPT, N_COUNTS = range(8)


@ti.kernel
def read_counts(counts: ti.template(), out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """out = ``counts`` (the N_COUNTS of a step) on the calling thread: a field's ``to_numpy`` copies in a
    parallel loop, a wake-up and join of the worker threads for eight numbers."""
    ti.loop_config(serialize=True)
    for k in range(N_COUNTS):
        out[k] = counts[k]


def weight_bits(radial: bool, depth: bool) -> int:
    """``measurement_weight``'s ``confidence`` argument."""
    return (RADIAL if radial else 0) | (DEPTH if depth else 0)


@data_oriented
class FusionImages:
    """The per-pixel work images of the fusion step at one resolution."""

    def __init__(self, height: int, width: int):
        self.height, self.width = height, width
        shape = (height, width)
        self.index_map = IndexMap(height, width)
        self.assoc = ti.field(ti.i32, shape=shape)  # the pixel's associated surfel; -1 none; COVERED
        self.color = ti.field(ti.i32, shape=shape)  # the frame's colour packed r | g << 8 | b << 16
        # the frame's measurements in the world frame (``world_measurements_loop``, for ``project_compatible_loop``)
        self.world_vertex = ti.Vector.field(3, ti.f32, shape=shape)  # FAR where the pixel is invalid
        self.world_normal = ti.Vector.field(3, ti.f32, shape=shape)  # zero where the pixel is invalid
        # the surfel merged at each associated pixel, as ``merge`` left it (world frame), for the coverage
        # test of ``count_segments``
        self.merged_position = ti.Vector.field(3, ti.f32, shape=shape)
        self.merged_normal = ti.Vector.field(3, ti.f32, shape=shape)
        self.merged_radius = ti.field(ti.f32, shape=shape)
        self.radial = ti.field(ti.f32, shape=shape)  # Keller's radial confidence per pixel (``fill_radial``)
        self.radial_for = None  # the (cx, cy, sigma) it was filled for
        segments = (height, SEGMENTS)  # per row segment (``count_segments``): counts and output offsets
        self.seg_new = ti.field(ti.i32, shape=segments)
        self.seg_merged = ti.field(ti.i32, shape=segments)
        self.seg_covered = ti.field(ti.i32, shape=segments)
        self.seg_offset = ti.field(ti.i32, shape=segments)

    @property
    def index(self):
        """The index map's surfel per pixel (INT_MAX = none)."""
        return self.index_map.index

    def set_color(self, rgb: np.ndarray, step: int = 1) -> None:
        """``color`` from a uint8 H×W×3 RGB image taken at every ``step``-th row and column (``pack_color``)."""
        rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
        shape = tuple(-(-n // step) for n in rgb.shape[:2])
        if rgb.ndim != 3 or rgb.shape[2] != 3 or shape != (self.height, self.width):
            raise ValueError(f"colour of shape {rgb.shape} at every {step}th pixel for images of shape "
                             f"{(self.height, self.width)}")
        pack_color(self.color, rgb, int(step))

    def radial_confidence(self, cx: float, cy: float, sigma: float) -> None:
        """Fill ``radial`` for these intrinsics and σ, unless it already holds them."""
        key = (float(cx), float(cy), float(sigma))
        if self.radial_for != key:
            fill_radial(self, *key)
            self.radial_for = key


# -- measurements ----------------------------------------------------------------------------------------


@ti.kernel
def fill_radial(img: ti.template(), cx: ti.f32, cy: ti.f32, sigma: ti.f32):
    """img.radial = Keller's radial confidence exp(−γ²/2σ²) of every pixel, γ its distance from the image
    centre over the largest such distance. It depends on the pixel only, so it is computed when the image
    centre or σ changes (``FusionImages.radial_confidence``) rather than once per merged or added surfel."""
    for v, u in img.radial:
        gamma2 = ((u - cx) ** 2 + (v - cy) ** 2) / (cx * cx + cy * cy)
        img.radial[v, u] = ti.exp(-gamma2 / (2.0 * sigma * sigma))


@ti.func
def measurement_weight(img: ti.template(), v, u, z, confidence: ti.template()):
    """1, or Keller's radial confidence of pixel (v, u) (``confidence`` bit RADIAL, ``img.radial``); times
    (σ(1 m) / σ(z))², capped at DEPTH_WEIGHT_MAX, with σ the sensor's depth noise (bit DEPTH)."""
    w = 1.0
    if ti.static(confidence & RADIAL):
        w = img.radial[v, u]
    if ti.static(confidence & DEPTH):
        s = depth_noise_scale(z, ti.f32)
        w *= ti.min(s * s, DEPTH_WEIGHT_MAX)
    return w


@ti.func
def measurement_radius(z, nz, f):
    """Keller's surfel radius: the pixel's footprint at depth z, √2 z / f, widened by the slant 1/|n_z|."""
    return SQRT2 * z / (f * ti.max(ti.abs(nz), MIN_COS_VIEW))


@ti.func
def unpack_color(c):
    return Vec3(c & 255, (c >> 8) & 255, (c >> 16) & 255)


# -- 1-3 in Keller's order (compatible surfels only) -----------------------------------------------------


@ti.kernel
def associate(s: ti.template(), n: ti.i32, img: ti.template(), vertex: ti.template(), normal: ti.template(),
              to_world: Rigid, to_camera: Rigid, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
              dist_threshold: ti.f32, cos_threshold: ti.f32):
    """Steps 1-3 in one launch, their loops one after the other: ``world_measurements_loop``,
    ``project_compatible_loop`` over the first ``n`` surfels, the index map of the compatible ones
    (``index_map.build_loops``: cleared, then filled) and ``assoc_from_index_loop``. With n = 0 every pixel
    is unassociated."""
    world_measurements_loop(img, vertex, normal, to_world)
    project_compatible_loop(s, n, img, to_camera, fx, fy, cx, cy, dist_threshold, cos_threshold)
    build_loops(s, n, img.index_map, True, None)
    assoc_from_index_loop(img)


@ti.func
def world_measurements_loop(img: ti.template(), vertex: ti.template(), normal: ti.template(), pose: ti.template()):
    """img.world_vertex, world_normal = the frame's vertex and normal maps in the world frame ((R, t) maps
    camera to world); where the pixel has no vertex or no normal, FAR and zero."""
    for v, u in img.world_vertex:  # (the frame's maps may be levels of a stacked field: no struct-for)
        R, t = rigid(pose)
        q = vertex[v, u]
        nq = normal[v, u]
        valid = is_valid(q, nq)
        img.world_vertex[v, u] = ti.select(valid, R @ q + t, Vec3(FAR, FAR, FAR))
        img.world_normal[v, u] = ti.select(valid, R @ nq, Vec3(0.0, 0.0, 0.0))


@ti.func
def project_compatible_loop(s: ti.template(), n, img: ti.template(), pose: ti.template(), fx, fy, cx, cy,
                            dist_threshold, cos_threshold):
    """Keller's association order in one pass over the surfels: filter pass 1 (``proj_pixel``, as in
    ``index_map.project_surfels``), then filter pass 2 against the measurement at that pixel
    (``world_measurements_loop``, so the test is ‖p − q_w‖ and n·n_w in the world frame, as the NumPy
    reference); the surfels that pass (the compatible ones, a few percent of the map) are listed per
    block, and the index map's passes then take the nearest per pixel among them. (R, t) maps world to
    camera. A pixel still merges into at most one surfel: the nearest compatible one rather than the
    nearest one.

    This loop over every surfel is the step's largest cost, hence its shape: each block is two loops, the
    first projects (no reads of the frame; on the CPU eight surfels at a time, ``index_map.project_pack``), the second reads the measurement at the projected pixel and
    tests; no branches (every surfel reads a pixel, (0, 0) when outside, and is written into the list,
    which keeps it only when it passes); the pose is read per surfel; no atomics (on Vulkan, atomics inside
    the serial loop of a parallel one are unreliable in Taichi 1.7, so they live in the flat loops over
    the gathered list). docs/KERNELS.md has what each of these is worth.
    """
    H, W = img.assoc.shape
    for b in range((n + BLOCK - 1) // BLOCK):  # parallel over blocks, serial inside one
        m = ti.min(BLOCK, n - b * BLOCK)  # a trip count rather than a break at n
        packs = 0
        if ti.static(on_cpu()):  # eight surfels at a time as 8-vectors
            packs = m // LANES
        for g in range(packs):
            project_pack(s, b * BLOCK + g * LANES, pose, fx, fy, cx, cy, H, W)
        for j in range(packs * LANES, m):
            project_one(s, b * BLOCK + j, pose, fx, fy, cx, cy, H, W, False, 0.0, 0)
        found = 0
        for j in range(m):
            i = b * BLOCK + j
            pix = s.proj_pixel[i]
            at = ti.max(pix, 0)  # pixel (0, 0) when outside: read, and masked
            v, u = at // W, at % W
            d = s.position[i] - img.world_vertex[v, u]
            nw = img.world_normal[v, u]
            ok = (pix >= 0) & (nw.norm_sqr() > 0) & (d.norm_sqr() <= dist_threshold * dist_threshold) \
                & (s.normal[i].dot(nw) >= cos_threshold)
            found = list_if(s, b, found, i, ok)
        s.block_listed[b] = found


@ti.kernel
def pack_color(color: ti.template(), rgb: ti.types.ndarray(dtype=ti.u8, ndim=3), step: ti.i32):
    """``pack_color_loop`` in one launch: the input image crosses as it is, with no copy on the host."""
    pack_color_loop(color, rgb, step)


@ti.func
def pack_color_loop(color: ti.template(), rgb: ti.template(), step):
    """color[v, u] = the uint8 RGB image ``rgb`` at row v·``step``, column u·``step``, packed
    r | g << 8 | b << 16 (``unpack_color`` reads it)."""
    for v, u in color:
        pack_color_pixel(color, rgb, step, v, u)


@ti.func
def pack_color_pixel(color: ti.template(), rgb: ti.template(), step, v, u):
    """Pixel (v, u) of ``pack_color_loop``."""
    y, x = v * step, u * step
    color[v, u] = (ti.cast(rgb[y, x, 0], ti.i32) | (ti.cast(rgb[y, x, 1], ti.i32) << 8)
                   | (ti.cast(rgb[y, x, 2], ti.i32) << 16))


@ti.func
def assoc_from_index_loop(img: ti.template()):
    """assoc = the index map (built from compatible surfels only), with -1 for none."""
    for v, u in img.assoc:
        i = img.index_map.index[v, u]
        img.assoc[v, u] = ti.select(i == INT_MAX, -1, i)


# -- 4. merge --------------------------------------------------------------------------------------------


@ti.func
def merge_one(s: ti.template(), i, img: ti.template(), vertex: ti.template(), normal: ti.template(), v, u,
              R, t, f, confidence: ti.template(), color: ti.template(), has_color, frame_index, anchor):
    """p ← (w p + α (R q + t)) / (w + α), n likewise then normalised, colour likewise (from the packed
    ``color`` image), w ← w + α; the surfel takes the frame's anchor."""
    q = vertex[v, u]
    nq = normal[v, u]
    a = measurement_weight(img, v, u, q.z, confidence)
    w = s.weight[i]
    s.position[i] = (w * s.position[i] + a * (R @ q + t)) / (w + a)
    n_sum = w * s.normal[i] + a * (R @ nq)
    length = n_sum.norm()
    if length > 0:
        s.normal[i] = n_sum / length
    if has_color:
        s.color[i] = (w * s.color[i] + a * unpack_color(color[v, u])) / (w + a)
    s.weight[i] = w + a
    s.radius[i] = ti.min(s.radius[i], measurement_radius(q.z, nq.z, f))
    s.t_updated[i] = frame_index
    s.anchor[i] = anchor
    img.merged_position[v, u] = s.position[i]
    img.merged_normal[v, u] = s.normal[i]
    img.merged_radius[v, u] = s.radius[i]


@ti.kernel
def merge_listed(s: ti.template(), img: ti.template(), vertex: ti.template(), normal: ti.template(),
                 pose: Rigid, f: ti.f32, confidence: ti.template(), color: ti.template(), has_color: ti.i32,
                 frame_index: ti.i32, anchor: ti.i32):
    """Every surfel that a pixel's association chose averages in that pixel's measurement (and, with
    ``has_color``, the colour of the packed image ``color`` there: ``FusionImages.color`` or the frame's
    own, ``FramePyramid.packed_color``).

    Only the surfels the projection listed (in the image; with Keller's order, compatible too) can have
    been chosen, so only they are visited, in index order: each reads its pixel from ``proj_pixel`` and
    merges when ``assoc`` there names it. Surfel attributes are thus read and written in index order, not
    in the random order a loop over the pixels would reach them in (a cache miss per attribute per merged
    surfel)."""
    W = img.assoc.shape[1]
    for k in range(s.n_listed[None]):
        R, t = rigid(pose)
        i = s.listed[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        if img.assoc[v, u] == i:
            merge_one(s, i, img, vertex, normal, v, u, R, t, f, confidence, color, has_color, frame_index, anchor)


# -- 5. add (stream compaction in row-major pixel order) -------------------------------------------------


@ti.func
def covered_by_neighbour(img: ti.template(), v, u, qw, nw, dist_threshold, cos_threshold):
    """Whether the point qw (normal nw), both world frame, of pixel (v, u) lies on the disc of a surfel
    merged at one of the pixel's 8 neighbours: within the disc's radius in its tangent plane,
    ``dist_threshold`` along its normal, normals within the angle. The merged surfels are read as
    ``merge`` left them at their pixels (``merged_*``): image reads instead of random reads of the surfel
    arrays."""
    H, W = img.assoc.shape
    covered = False
    for dv in ti.static(range(-1, 2)):
        for du in ti.static(range(-1, 2)):
            if ti.static(dv != 0 or du != 0):
                y = v + dv
                x = u + du
                if 0 <= y < H and 0 <= x < W:
                    if img.assoc[y, x] >= 0 and not covered:
                        d = qw - img.merged_position[y, x]
                        n = img.merged_normal[y, x]
                        along = n.dot(d)
                        r = img.merged_radius[y, x]
                        if ti.abs(along) <= dist_threshold and d.norm_sqr() - along * along <= r * r \
                                and n.dot(nw) >= cos_threshold:
                            covered = True
    return covered


@ti.func
def segment_range(g, W):
    """Pixels [begin, end) of segment g of a row of W pixels."""
    width = (W + SEGMENTS - 1) // SEGMENTS
    return ti.min(g * width, W), ti.min((g + 1) * width, W)


@ti.func
def count_segments_loops(img: ti.template(), vertex: ti.template(), normal: ti.template(), pose: ti.template(),
                         dist_threshold, cos_threshold, cover: ti.template()):
    """Per row segment: pixels merged, valid pixels without an association (the new surfels), and covered
    pixels. With ``cover``, each valid unassociated pixel is first tested against the discs of the surfels
    merged at its 8 neighbours (``covered_by_neighbour``) and marked COVERED if one holds its point.
    ``pose`` (R, t) maps camera to world.

    Why: surfels project to pixel centres only approximately, so a map as dense as the image still leaves
    some pixels without a surfel of their own (two surfels round to one pixel, its neighbour gets none),
    and adding a surfel at every such pixel made the map grow by several percent of the frame at each
    frame, however often the surface had been seen. Keller et al. search a neighbourhood of a
    super-sampled index map for the same reason. Pixels only change from -1 to COVERED and only assoc ≥ 0
    is read, so the result does not depend on the order the pixels run in."""
    H, W = img.assoc.shape
    for v, g in ti.ndrange(H, SEGMENTS):
        R, t = rigid(pose)
        begin, end = segment_range(g, W)
        new = 0
        merged = 0
        covered = 0
        for u in range(begin, end):
            a = img.assoc[v, u]
            if a >= 0:
                merged += 1
            elif a == -1:
                q = vertex[v, u]
                nq = normal[v, u]
                if is_valid(q, nq):
                    is_covered = False
                    if ti.static(cover):
                        is_covered = covered_by_neighbour(img, v, u, R @ q + t, R @ nq, dist_threshold,
                                                          cos_threshold)
                    if is_covered:
                        img.assoc[v, u] = COVERED
                        covered += 1
                    else:
                        new += 1
            elif a == COVERED:
                covered += 1
        img.seg_new[v, g] = new
        img.seg_merged[v, g] = merged
        img.seg_covered[v, g] = covered


@ti.kernel
def count_segments(img: ti.template(), vertex: ti.template(), normal: ti.template(), pose: Rigid,
                   dist_threshold: ti.f32, cos_threshold: ti.f32, cover: ti.template()):
    """``count_segments_loops`` in one launch."""
    count_segments_loops(img, vertex, normal, pose, dist_threshold, cos_threshold, cover)



@ti.func
def scan_segments_loops(img: ti.template(), counts: ti.template(), n):
    """Exclusive prefix sum of the new-surfel counts in row-major order, and the step's new, merged and
    covered totals; with ``n`` surfels before the add, the count after it (TOTAL, and KEPT until a
    removal says otherwise), no losses and no removals yet."""
    new = 0
    merged = 0
    covered = 0
    H = img.seg_new.shape[0]
    ti.loop_config(serialize=True)  # (a struct-for would not be serialised)
    for v, g in ti.ndrange(H, SEGMENTS):
        img.seg_offset[v, g] = new
        new += img.seg_new[v, g]
        merged += img.seg_merged[v, g]
        covered += img.seg_covered[v, g]
    counts[C_NEW] = new
    counts[C_MERGED] = merged
    counts[C_COVERED] = covered
    counts[C_LOST] = 0
    counts[C_REMOVED] = 0
    counts[C_TOTAL] = n + new
    counts[C_KEPT] = n + new


@ti.kernel
def scan_segments(img: ti.template(), counts: ti.template(), n: ti.i32):
    """``scan_segments_loops`` in one launch."""
    scan_segments_loops(img, counts, n)



@ti.func
def append_new_loops(s: ti.template(), n, img: ti.template(), vertex: ti.template(), normal: ti.template(),
                     pose: ti.template(), f, confidence: ti.template(), color: ti.template(), has_color,
                     frame_index, anchor, counts: ti.template()):
    """Write the new surfels at n + seg_offset[v, g] + (rank within the segment), so in row-major pixel
    order; count any that do not fit (``counts[C_LOST]``).

    The caller has grown the map first, so ``lost`` stays 0: it is the guard against an out-of-bounds
    write, not the capacity check.
    """
    H, W = img.assoc.shape
    for v, g in ti.ndrange(H, SEGMENTS):
        R, t = rigid(pose)
        begin, end = segment_range(g, W)
        k = n + img.seg_offset[v, g]
        lost = 0
        for u in range(begin, end):
            q = vertex[v, u]
            nq = normal[v, u]
            if img.assoc[v, u] == -1 and is_valid(q, nq):
                if k < s.capacity:
                    s.position[k] = R @ q + t
                    s.normal[k] = R @ nq
                    c = Vec3(128.0, 128.0, 128.0)
                    if has_color:
                        c = unpack_color(color[v, u])
                    s.color[k] = c
                    s.weight[k] = measurement_weight(img, v, u, q.z, confidence)
                    s.radius[k] = measurement_radius(q.z, nq.z, f)
                    s.t_created[k] = frame_index
                    s.t_updated[k] = frame_index
                    s.anchor[k] = anchor
                else:
                    lost += 1
                k += 1
        if lost > 0:
            ti.atomic_add(counts[C_LOST], lost)


@ti.kernel
def append_new(s: ti.template(), n: ti.i32, img: ti.template(), vertex: ti.template(), normal: ti.template(),
               pose: Rigid, f: ti.f32, confidence: ti.template(), color: ti.template(), has_color: ti.i32,
               frame_index: ti.i32, anchor: ti.i32, counts: ti.template()):
    """``append_new_loops`` in one launch."""
    append_new_loops(s, n, img, vertex, normal, pose, f, confidence, color, has_color, frame_index, anchor, counts)



# -- 6. remove (in-place compaction that keeps the order of the survivors below the new count) -----------


@ti.func
def mark_removal_loops(s: ti.template(), counts: ti.template(), n_projected, frame_index, unstable, unstable_weight,
                       unstable_age, free_space: ti.template(), margin, depth: ti.template()):
    """The surfels to drop: ``block_removals[b]`` of them in block b, listed in index order at
    ``removals_by_block[b·BLOCK:]``. No per-surfel flags are written: the lists are all the later passes
    read.

    Unstable: weight < unstable_weight and not updated for unstable_age frames. Free space: the frame
    measures a depth more than ``margin`` behind the surfel along its ray, so the camera sees through
    it (only surfels that existed at projection time, i < n_projected, and were not merged now). The
    surfels are the first n = ``counts[C_TOTAL]``.
    """
    W = depth.shape[1]
    n = counts[C_TOTAL]
    for b in range((n + BLOCK - 1) // BLOCK):
        removed = 0
        for j in range(ti.min(BLOCK, n - b * BLOCK)):  # a trip count, as in project_compatible_loop
            i = b * BLOCK + j
            # branch-free: whether a surfel is weak and stale follows no pattern the branch predictor
            # can learn
            rm = ti.select((unstable != 0) & (s.weight[i] < unstable_weight)
                           & (frame_index - s.t_updated[i] >= unstable_age), 1, 0)
            if ti.static(free_space):
                if i < n_projected and s.proj_pixel[i] >= 0:
                    if s.t_updated[i] != frame_index:
                        pix = s.proj_pixel[i]
                        d = depth[pix // W, pix % W]
                        if d > 0 and d > bits_depth(s.proj_depth[i]) + margin:
                            rm = 1
            if rm:  # rare (a few surfels a frame): a branch that predicts, and no store for the others
                s.removals_by_block[b * BLOCK + removed] = i
            removed += rm
        s.block_removals[b] = removed


@ti.kernel
def mark_removal(s: ti.template(), counts: ti.template(), n_projected: ti.i32, frame_index: ti.i32,
                 unstable: ti.i32, unstable_weight: ti.f32, unstable_age: ti.i32,
                 free_space: ti.template(), margin: ti.f32, depth: ti.template()):
    """``mark_removal_loops`` in one launch."""
    mark_removal_loops(s, counts, n_projected, frame_index, unstable, unstable_weight, unstable_age, free_space,
                       margin, depth)



@ti.func
def sum_removals_loops(s: ti.template(), counts: ti.template()):
    """The removals of the n = ``counts[C_TOTAL]`` surfels (REMOVED) and the count m they leave (KEPT);
    then, per block, holes (removed, index < m: ``block_holes``) and movers (kept, index ≥ m), and where
    each block's go (``hole_offset``, ``mover_offset``). There are as many of each (``n_holes``). Blocks
    wholly below or above m take their counts from ``block_removals``; only the block that straddles m is
    re-counted. Both serial, on one thread, in one launch.
    """
    n = counts[C_TOTAL]
    total = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        total += s.block_removals[b]
    counts[C_REMOVED] = total
    m = n - total
    counts[C_KEPT] = m
    holes = 0
    movers = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        lo = b * BLOCK
        hi = ti.min(lo + BLOCK, n)
        h = 0
        k = 0
        if hi <= m:
            h = s.block_removals[b]
        elif lo >= m:
            k = (hi - lo) - s.block_removals[b]
        else:  # the block's removals below m, then its survivors at or above m
            for r in range(s.block_removals[b]):
                if s.removals_by_block[lo + r] < m:
                    h += 1
            k = (hi - m) - (s.block_removals[b] - h)
        s.block_holes[b] = h
        s.hole_offset[b] = holes
        s.mover_offset[b] = movers
        holes += h
        movers += k
    s.n_holes[None] = holes


@ti.kernel
def sum_removals(s: ti.template(), counts: ti.template()):
    """``sum_removals_loops`` in one launch."""
    sum_removals_loops(s, counts)



@ti.func
def fill_holes_loops(s: ti.template(), counts: ti.template()):
    """After ``sum_removals``, with n = TOTAL and m = KEPT: the k-th surviving surfel at or above m moves
    into the k-th hole below m (no overlap), in three loops of one launch. First the holes are listed
    (``holes[k]`` = the k-th hole below m, in index order: the first ``block_holes[b]`` entries of each
    block's list of removals, in index order, so those below m come first); then the movers
    (``movers``), so that the copies run in parallel over the surfels: the tail [m, n) spans too few
    blocks for a loop over blocks to use more than one thread. With no removals every loop is empty."""
    n = counts[C_TOTAL]
    m = counts[C_KEPT]
    # On the CPU the two listing loops run on the calling thread: removals are a few hundred surfels a frame,
    # so they take microseconds, less than handing a loop to the worker threads and waiting for it.
    if ti.static(on_cpu()):
        ti.loop_config(serialize=True)
    for b in range((m + BLOCK - 1) // BLOCK):
        k = s.hole_offset[b]
        for j in range(s.block_holes[b]):
            s.holes[k + j] = s.removals_by_block[b * BLOCK + j]
    if ti.static(on_cpu()):
        ti.loop_config(serialize=True)
    for b in range(ti.select(m < n, m // BLOCK, 0), ti.select(m < n, (n + BLOCK - 1) // BLOCK, 0)):
        k = s.mover_offset[b]
        lo = b * BLOCK
        removals = s.block_removals[b]
        r = 0  # the next entry of the block's list of removals (in index order) not below m
        while r < removals and s.removals_by_block[lo + r] < m:
            r += 1
        for i in range(ti.max(lo, m), ti.min(lo + BLOCK, n)):
            if r < removals and s.removals_by_block[lo + r] == i:
                r += 1
            else:
                s.movers[k] = i
                k += 1
    for k in range(s.n_holes[None]):
        copy_surfel(s, s.movers[k], s, s.holes[k])


@ti.kernel
def fill_holes(s: ti.template(), counts: ti.template()):
    """``fill_holes_loops`` in one launch."""
    fill_holes_loops(s, counts)



@ti.kernel
def add_step(s: ti.template(), n: ti.i32, img: ti.template(), vertex: ti.template(), normal: ti.template(),
             pose: Rigid, dist_threshold: ti.f32, cos_threshold: ti.f32, cover: ti.template(), f: ti.f32,
             confidence: ti.template(), color: ti.template(), has_color: ti.i32, frame_index: ti.i32,
             anchor: ti.i32, counts: ti.template()):
    """The add of a step in one launch, when the map has room for every pixel: ``count_segments``,
    ``scan_segments`` and ``append_new``, one after the other (each reads what the one before wrote)."""
    count_segments_loops(img, vertex, normal, pose, dist_threshold, cos_threshold, cover)
    scan_segments_loops(img, counts, n)
    append_new_loops(s, n, img, vertex, normal, pose, f, confidence, color, has_color, frame_index, anchor, counts)


@ti.kernel
def remove_step(s: ti.template(), counts: ti.template(), n_projected: ti.i32, frame_index: ti.i32,
                unstable: ti.i32, unstable_weight: ti.f32, unstable_age: ti.i32, free_space: ti.template(),
                margin: ti.f32, depth: ti.template()):
    """The removal of a step in one launch, with its counts on the device: ``mark_removal``,
    ``sum_removals`` and ``fill_holes`` one after the other (with no removals the last one's loops are
    empty)."""
    mark_removal_loops(s, counts, n_projected, frame_index, unstable, unstable_weight, unstable_age, free_space,
                       margin, depth)
    sum_removals_loops(s, counts)
    fill_holes_loops(s, counts)


# -- loop closure: per-anchor rigid corrections ----------------------------------------------------------


@ti.kernel
def reactivate(s: ti.template(), n: ti.i32, frame_index: ti.i32, min_weight: ti.f32):
    """Loop closure: surfels i < n with weight ≥ ``min_weight`` count as updated at ``frame_index`` (the
    active model again); weaker ones keep their ``t_updated``, so that the removal of unstable surfels,
    which tests it, still drops them. Each surfel writes only itself."""
    for i in range(n):
        if s.weight[i] >= min_weight:
            s.t_updated[i] = frame_index


@ti.kernel
def apply_corrections(s: ti.template(), n: ti.i32, corrections: ti.types.ndarray(dtype=ti.f32, ndim=2),
                      moved: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """Every surfel i < n whose anchor k has ``moved[k]`` ≠ 0 (0 ≤ k < K) goes with anchor k's correction
    (R, t) = ``corrections[k]`` (a ``Rigid``: R row-major, then t): p ← R p + t, n ← R n. Other surfels
    (anchors outside [0, K), or anchors whose correction is the identity and so not ``moved``) are not
    written, which keeps them bit-identical. Each surfel writes only itself: no atomics."""
    K = corrections.shape[0]
    for i in range(n):
        k = s.anchor[i]
        if 0 <= k < K:
            if moved[k] != 0:
                R = Mat3([[corrections[k, 3 * r + c] for c in ti.static(range(3))]
                          for r in ti.static(range(3))])
                t = Vec3(corrections[k, 9], corrections[k, 10], corrections[k, 11])
                s.position[i] = R @ s.position[i] + t
                s.normal[i] = R @ s.normal[i]
