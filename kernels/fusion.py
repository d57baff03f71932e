"""The surfel map and point-based fusion (Keller et al. 2013) as Taichi kernels.

A surfel is a small oriented disc: position, normal, colour, weight (confidence), radius and the frames
it was created and last updated in. The map keeps them as a structure of arrays of a fixed capacity;
``SurfelMap.ensure_capacity`` grows it (reallocate ×2 and copy, on the Taichi side) or raises
``MapCapacityError`` before a write could go past the end.

One fusion step for a frame with camera-to-world pose T = [R | t] (``ti_fusion.mapping.mapper.SurfelMapper``
strings the stages together):

1. project    every surfel into the frame; per pixel, the surfel nearest in depth (the index map);
2. filter 1   the per-surfel mask "projects inside the image with positive depth" (``proj_pixel >= 0``,
              computed by the same kernel as step 1);
3. filter 2   per pixel, the index-map surfel is associated when the frame's vertex is within a distance
              and its normal within an angle of the surfel's (``assoc`` image). Alternatively
              (``fusion.association = "compatible"``, Keller's order) every surfel of pass 1 is tested
              against its pixel's measurement first and the index map keeps the nearest that passed:
              a compatible surfel behind an incompatible one still merges. Either way a pixel merges
              into at most one surfel and a surfel takes at most one pixel;
4. merge      associated surfels average in the measurement (weight 1, or Keller's radial confidence);
5. add        every valid pixel without an association becomes a new surfel;
6. remove     unstable surfels (low weight, not updated for a while) and, optionally, surfels the frame
              sees through (free-space violations); the arrays are compacted in place.

Why the index map needs two passes: Vulkan guarantees only 32-bit atomics, so a 64-bit key
(depth << 32 | index) is out. A packed 32-bit key would leave too few bits for either: 4 M surfels
need 22 bits, leaving 10 bits of depth, 4 mm steps over 4 m, so surfels a few millimetres apart would
tie and be ranked by index rather than depth. So pass 1 takes an atomic min of
the depth's float bits (for positive IEEE-754 floats the bit patterns, read as int32, order exactly like
the values), and pass 2 lets every surfel whose depth bits equal the pixel's minimum take an atomic min
of its index. The winner is the nearest surfel, exact ties broken by the smallest index: deterministic
on every backend. Both passes run over a list, not over the map: the projection (one branch-free pass
over every surfel, the step's largest cost) lists the surfels it keeps per block of BLOCK surfels, and
the list (about half the map for rendering, a few percent with Keller's order) is gathered in index
order for the index map's two passes and for the merge.

Determinism elsewhere: new surfels are appended in row-major pixel order (counts per row segment, a
serial scan over the segments, then per-segment writes), and removal fills the k-th hole below the new count with the k-th
surviving surfel above it (block counts and scans), so a run gives the same map on every run and
thread count, not just the same set.
"""

import math
import weakref

import numpy as np
import taichi as ti
from taichi.lang import impl

from ti_fusion.errors import MapCapacityError
from ti_fusion.geometry import flatten_pose

INT_MAX = 2147483647  # "no surfel" in the index maps and "no depth" in the depth keys
# Surfels per block of the per-block lists and compaction scans. Small enough that the loops over blocks
# run in parallel: Taichi's CPU backend (1.7) hands out 512 iterations of a range-for per task, whatever
# block_dim says, so a loop over fewer than ~1000 blocks ran on one thread (at 1024 surfels per block,
# every map below a million surfels).
BLOCK = 128
# Each image row is counted and appended in this many segments, so that the loops over segments have
# enough iterations to run on several threads (Taichi's CPU range-for splits into tasks of 512 iterations:
# a loop over the 240 rows ran on one).
SEGMENTS = 8
SQRT2 = math.sqrt(2.0)
MIN_COS_VIEW = 0.2  # radius = √2 z / (f |n_z|): |n_z| is clamped here so grazing surfels stay bounded
# Measurement weights (``measurement_weight``'s ``confidence`` bits): Keller's radial confidence, and
# Kinect's depth noise σ(z) = A + B (z − Z0)² (Nguyen et al. 2012) relative to 1 m, capped.
RADIAL, DEPTH = 1, 2
NOISE_A, NOISE_B, NOISE_Z0 = 0.0012, 0.0019, 0.4
NOISE_1M = NOISE_A + NOISE_B * (1.0 - NOISE_Z0) ** 2
DEPTH_WEIGHT_MAX = 4.0
Vec3 = ti.types.vector(3, ti.f32)
Mat3 = ti.types.matrix(3, 3, ti.f32)
# A rigid transform as a kernel argument: R row-major, then t (12 float32). Passed as a small array rather
# than as matrix and vector arguments, whose conversion cost ~65 µs more per launch (measured on the CPU).
Rigid = ti.types.ndarray(dtype=ti.f32, ndim=1)

# Fields of one surfel, in the order of ``SurfelArrays.attributes``.
ATTRIBUTES = ("position", "normal", "colour", "weight", "radius", "t_created", "t_updated")


@ti.data_oriented
class SurfelArrays:
    """The surfel attributes (structure of arrays) and per-surfel scratch, for one capacity.

    Allocated in its own SNode tree so that growing the map can free the old arrays.
    """

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.blocks = self.capacity // BLOCK + 1
        assert self.blocks * BLOCK >= self.capacity  # candidate lists of a block fit in its slice
        fb = ti.FieldsBuilder()
        self.position = ti.Vector.field(3, ti.f32)  # world frame, metres
        self.normal = ti.Vector.field(3, ti.f32)  # world frame, unit
        self.colour = ti.Vector.field(3, ti.f32)  # RGB in [0, 255]
        self.weight = ti.field(ti.f32)  # confidence: sum of measurement weights
        self.radius = ti.field(ti.f32)  # metres
        self.t_created = ti.field(ti.i32)  # frame index
        self.t_updated = ti.field(ti.i32)  # frame index of the last merge
        # Scratch of the current step: pixel (v·W + u, or -1 outside: filter pass 1) and depth bits.
        self.proj_pixel = ti.field(ti.i32)
        self.proj_depth = ti.field(ti.i32)
        # scratch list: from a projection to the merge, the surfels the projection kept (in the image;
        # with Keller's order, compatible too) in index order, n_candidates[0] of them; during removal,
        # the k-th hole's index, then (after the n_candidates[0] = h holes) the k-th mover's
        self.slot = ti.field(ti.i32)
        # the surfels a projection keeps from block b are first listed at candidate[b·BLOCK :]
        # (block_candidates[b] of them), then gathered into ``slot``; during removal, block b's removals
        self.candidate = ti.field(ti.i32)
        for f in (self.position, self.normal, self.colour, self.weight, self.radius, self.t_created,
                  self.t_updated, self.proj_pixel, self.proj_depth, self.slot, self.candidate):
            fb.dense(ti.i, self.capacity).place(f)  # one array per attribute: SoA
        self.block_a = ti.field(ti.i32)
        self.block_b = ti.field(ti.i32)
        self.offset_a = ti.field(ti.i32)
        self.offset_b = ti.field(ti.i32)
        self.block_candidates = ti.field(ti.i32)
        for f in (self.block_a, self.block_b, self.offset_a, self.offset_b, self.block_candidates):
            fb.dense(ti.i, self.blocks).place(f)
        self.n_candidates = ti.field(ti.i32)
        fb.dense(ti.i, 1).place(self.n_candidates)
        self.tree = fb.finalize()

    @property
    def attributes(self):
        return [getattr(self, name) for name in ATTRIBUTES]

    def destroy(self) -> None:
        self.tree.destroy()


@ti.data_oriented
class ImageScratch:
    """Per-pixel work images of one resolution, shared by the fusion step and the renderer."""

    def __init__(self, height: int, width: int):
        self.height, self.width = height, width
        shape = (height, width)
        self.depth_key = ti.field(ti.i32, shape=shape)  # float bits of the nearest depth, INT_MAX = none
        self.index = ti.field(ti.i32, shape=shape)  # nearest surfel; INT_MAX (after pass 2: -1) = none
        self.assoc = ti.field(ti.i32, shape=shape)  # filter pass 2: associated surfel or -1
        self.colour = ti.field(ti.i32, shape=shape)  # frame colour packed r | g << 8 | b << 16
        segments = (height, SEGMENTS)  # per row segment (``count_segments``): counts and output offsets
        self.seg_new = ti.field(ti.i32, shape=segments)
        self.seg_merged = ti.field(ti.i32, shape=segments)
        self.seg_covered = ti.field(ti.i32, shape=segments)
        self.seg_offset = ti.field(ti.i32, shape=segments)
        # Rendering: the front surfel of each pixel in the camera frame, the splat result, and outputs.
        # (During a fusion step pc, nc, rad hold instead the merged surfel of each pixel, world frame.)
        self.pc = ti.Vector.field(3, ti.f32, shape=shape)
        self.nc = ti.Vector.field(3, ti.f32, shape=shape)
        self.rad = ti.field(ti.f32, shape=shape)  # -1 = no surfel
        self.view_index = ti.field(ti.i32, shape=shape)  # surfel seen at the pixel, INT_MAX = none
        self.vertex = ti.Vector.field(3, ti.f32, shape=shape)
        self.normal = ti.Vector.field(3, ti.f32, shape=shape)
        self.depth = ti.field(ti.f32, shape=shape)
        self.image = ti.Vector.field(3, ti.f32, shape=shape)  # rendered RGB in [0, 1]
        self.radial = ti.field(ti.f32, shape=shape)  # Keller's radial confidence per pixel (``fill_radial``)
        # The frame's measurements in the world frame for ``project_compatible`` (``world_measurements``)
        self.world_vertex = ti.Vector.field(3, ti.f32, shape=shape)  # FAR where the pixel is invalid
        self.world_normal = ti.Vector.field(3, ti.f32, shape=shape)
        self.radial_for = None  # the (cx, cy, sigma) it was filled for

    def radial_confidence(self, cx: float, cy: float, sigma: float) -> None:
        """Fill ``radial`` for these intrinsics and σ, unless it already holds them."""
        key = (float(cx), float(cy), float(sigma))
        if self.radial_for != key:
            fill_radial(self, *key)
            self.radial_for = key


# ---------------------------------------------------------------------------------------------------
# Small helpers


@ti.func
def rigid(pose: ti.template()):
    """(R, t) of a ``Rigid`` argument."""
    R = Mat3([[pose[3 * i + j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    t = Vec3(pose[9], pose[10], pose[11])
    return R, t


@ti.func
def depth_bits(z):
    """int32 bit pattern of a positive float32: ordered exactly like the floats themselves."""
    return ti.bit_cast(ti.cast(z, ti.f32), ti.i32)


@ti.func
def bits_depth(k):
    return ti.bit_cast(k, ti.f32)


@ti.func
def is_valid(q, nq):
    return q.z > 0 and nq.norm_sqr() > 0


@ti.kernel
def fill_radial(img: ti.template(), cx: ti.f32, cy: ti.f32, sigma: ti.f32):
    """img.radial = Keller's radial confidence exp(−γ²/2σ²) of every pixel, γ its distance from the image
    centre over the largest such distance. It depends on the pixel only, so it is computed when the image
    centre or σ changes (``ImageScratch.radial_confidence``) rather than once per merged or added surfel
    (an exp each: a quarter of the merge)."""
    for v, u in img.radial:
        gamma2 = ((u - cx) ** 2 + (v - cy) ** 2) / (cx * cx + cy * cy)
        img.radial[v, u] = ti.exp(-gamma2 / (2.0 * sigma * sigma))


@ti.func
def measurement_weight(img: ti.template(), v, u, z, confidence: ti.template()):
    """1, or Keller's radial confidence of pixel (v, u) (``confidence`` bit 1, ``img.radial``); times
    (σ(1 m) / σ(z))², capped at DEPTH_WEIGHT_MAX, with σ Kinect's axial depth noise (bit 2:
    inverse-variance weighting, as the ICP's ``depth_weighting``)."""
    w = 1.0
    if ti.static(confidence & RADIAL):
        w = img.radial[v, u]
    if ti.static(confidence & DEPTH):
        s = NOISE_1M / (NOISE_A + NOISE_B * (z - NOISE_Z0) * (z - NOISE_Z0))
        w *= ti.min(s * s, DEPTH_WEIGHT_MAX)
    return w


@ti.func
def measurement_radius(z, nz, f):
    """Keller's surfel radius: the pixel's footprint at depth z, √2 z / f, widened by the slant 1/|n_z|."""
    return SQRT2 * z / (f * ti.max(ti.abs(nz), MIN_COS_VIEW))


@ti.func
def unpack_colour(c):
    return Vec3(c & 255, (c >> 8) & 255, (c >> 16) & 255)


# ---------------------------------------------------------------------------------------------------
# 1-2. Projection, index map, filter pass 1


@ti.kernel
def clear_index(img: ti.template()):
    for v, u in img.index:
        img.depth_key[v, u] = INT_MAX
        img.index[v, u] = INT_MAX


@ti.func
def project_to_pixel(pc, fx, fy, cx, cy, H, W):
    """(inside, u, v) of a camera-frame point, without branches: inside = z > 0 and the pixel
    u = ⌊fx x/z + cx + ½⌋, v likewise (round to nearest), is in the image; (u, v) = (0, 0) when not."""
    inv_z = 1.0 / pc.z  # inf or negative where z ≤ 0: masked below
    uf = fx * pc.x * inv_z + cx + 0.5
    vf = fy * pc.y * inv_z + cy + 0.5
    inside = (pc.z > 0) & (uf >= 0.0) & (uf < W) & (vf >= 0.0) & (vf < H)  # NaN compares false
    u = ti.min(ti.cast(ti.select(inside, uf, 0.0), ti.i32), W - 1)  # uf ≥ 0: truncation is the floor
    v = ti.min(ti.cast(ti.select(inside, vf, 0.0), ti.i32), H - 1)
    return inside, u, v


@ti.func
def list_if(s: ti.template(), b, found, i, keep):
    """Append surfel i to block b's list when ``keep``: written always, kept by the count (no branch)."""
    s.candidate[b * BLOCK + found] = i
    return found + ti.select(keep, 1, 0)


@ti.kernel
def project_surfels(s: ti.template(), n: ti.i32, img: ti.template(), pose: Rigid,
                    fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32, render: ti.template(), min_weight: ti.f32):
    """Filter pass 1: proj_pixel ≥ 0 for surfels inside the image with z > 0, which are also listed per
    block (``candidate``, ``block_candidates``) for the index map's passes over them
    (``gather_candidates``, ``nearest_candidates``, ``claim_candidates``).

    ``pose`` (R, t) maps world to camera. Pixel u = ⌊fx x/z + cx + ½⌋ (round to nearest): a frame vertex at pixel
    u projects back to u. For rendering, surfels below ``min_weight`` or facing away are left out too.
    Branch-free, as ``project_compatible`` (and for the same reason).
    """
    H, W = img.index.shape
    for b in range((n + BLOCK - 1) // BLOCK):  # parallel over blocks, serial inside one
        found = 0
        for j in range(ti.min(BLOCK, n - b * BLOCK)):  # (a trip count, not a break: see project_compatible)
            i = b * BLOCK + j
            R, t = rigid(pose)  # per surfel: see project_compatible
            pc = R @ s.position[i] + t
            keep, u, v = project_to_pixel(pc, fx, fy, cx, cy, H, W)
            if ti.static(render):
                keep = keep & (s.weight[i] >= min_weight) & ((R @ s.normal[i]).dot(pc) < 0)
            s.proj_pixel[i] = ti.select(keep, v * W + u, -1)
            s.proj_depth[i] = depth_bits(ti.abs(pc.z))
            found = list_if(s, b, found, i, keep)
        s.block_candidates[b] = found


# ---------------------------------------------------------------------------------------------------
# 3. Filter pass 2


@ti.kernel
def associate(s: ti.template(), img: ti.template(), vertex: ti.template(), normal: ti.template(),
              pose: Rigid, dist_threshold: ti.f32, cos_threshold: ti.f32):
    """assoc[v, u] = the index-map surfel if the frame's point is within the thresholds, else -1.

    (R, t) maps camera to world. One pixel merges into at most one surfel (its index-map surfel), and a
    surfel projects to one pixel, so no surfel is merged twice.
    """
    for v, u in img.index:
        R, t = rigid(pose)
        i = img.index[v, u]
        a = -1
        if i == INT_MAX or i < 0:  # < 0: already converted by an earlier call
            img.index[v, u] = -1
        else:
            q = vertex[v, u]
            nq = normal[v, u]
            if is_valid(q, nq):
                qw = R @ q + t
                nw = R @ nq
                if (qw - s.position[i]).norm() <= dist_threshold and nw.dot(s.normal[i]) >= cos_threshold:
                    a = i
        img.assoc[v, u] = a


FAR = 1e10  # world vertex of an invalid pixel (whose world normal is zero, which is what the test checks)


@ti.kernel
def world_measurements(img: ti.template(), vertex: ti.template(), normal: ti.template(), pose: Rigid):
    """img.world_vertex, world_normal = the frame's vertex and normal maps in the world frame ((R, t) maps
    camera to world); where the pixel has no vertex or no normal, FAR and zero."""
    for v, u in vertex:
        R, t = rigid(pose)
        q = vertex[v, u]
        nq = normal[v, u]
        valid = is_valid(q, nq)
        img.world_vertex[v, u] = ti.select(valid, R @ q + t, Vec3(FAR, FAR, FAR))
        img.world_normal[v, u] = ti.select(valid, R @ nq, Vec3(0.0, 0.0, 0.0))


@ti.kernel
def project_compatible(s: ti.template(), n: ti.i32, img: ti.template(), pose: Rigid, fx: ti.f32, fy: ti.f32,
                       cx: ti.f32, cy: ti.f32, dist_threshold: ti.f32, cos_threshold: ti.f32):
    """Keller's association order in one pass over the surfels: filter pass 1 (``proj_pixel``, as in
    ``project_surfels``), then filter pass 2 against the measurement at that pixel (``world_measurements``,
    so the test is ‖p − q_w‖ and n·n_w in the world frame, as the NumPy reference); the surfels that pass
    (the compatible ones, a few percent of the map) are listed per block of BLOCK surfels (``candidate``,
    ``block_candidates``), and ``claim_candidates`` then takes the nearest depth per pixel among them.
    (R, t) maps world to camera. A pixel still merges into at most one surfel: the nearest compatible one
    rather than the nearest one.

    This loop over every surfel is the step's largest cost, hence its shape. Each block is two loops: the
    first projects (no reads of the frame), the second reads the measurement at the projected pixel and
    tests. One loop doing both, with the measurement read depending on the projection just computed, ran
    1.3x slower (1 M surfels at 320×240, one core: 10.1 -> 7.9 ms). No branches: every surfel reads a
    pixel of the frame maps (pixel (0, 0) when it is outside the image) and is written into the list,
    which keeps it only when it passes; with about half the map in view, in an order the branch
    predictor cannot follow, branches made the pass 1.7x slower. The pose is read per surfel: read once
    per block, the projection loop ran 3x slower. No atomics here: on Vulkan (Taichi 1.7), atomics inside
    the serial loop of a parallel one run for only some iterations, so they live in the flat loops over
    the gathered list below.
    """
    H, W = img.index.shape
    for b in range((n + BLOCK - 1) // BLOCK):  # parallel over blocks, serial inside one
        m = ti.min(BLOCK, n - b * BLOCK)  # a trip count rather than a break at n: 1.07x faster on one core
        for j in range(m):
            i = b * BLOCK + j
            R, t = rigid(pose)
            pc = R @ s.position[i] + t
            inside, u, v = project_to_pixel(pc, fx, fy, cx, cy, H, W)
            s.proj_pixel[i] = ti.select(inside, v * W + u, -1)
            s.proj_depth[i] = depth_bits(ti.abs(pc.z))
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
        s.block_candidates[b] = found


@ti.kernel
def gather_candidates(s: ti.template(), n: ti.i32):
    """The per-block lists of the last projection (``project_surfels`` or ``project_compatible``) into
    one list in index order: ``slot[:m]``, m = ``n_candidates[0]`` (a serial scan over the blocks, then
    one parallel copy per block)."""
    total = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        s.offset_a[b] = total
        total += s.block_candidates[b]
    s.n_candidates[0] = total
    for b in range((n + BLOCK - 1) // BLOCK):
        for k in range(s.block_candidates[b]):
            s.slot[s.offset_a[b] + k] = s.candidate[b * BLOCK + k]


@ti.kernel
def nearest_candidates(s: ti.template(), img: ti.template()):
    """First pass of the index map, over the listed surfels: the nearest depth per pixel."""
    W = img.index.shape[1]
    for k in range(s.n_candidates[0]):
        i = s.slot[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        key = s.proj_depth[i]
        if key < img.depth_key[v, u]:  # plain read first: most lose, and skip the atomic
            ti.atomic_min(img.depth_key[v, u], key)


@ti.kernel
def claim_candidates(s: ti.template(), img: ti.template()):
    """Second pass of the index map, over the listed surfels: among those at a pixel's nearest depth, the
    smallest index wins."""
    W = img.index.shape[1]
    for k in range(s.n_candidates[0]):
        i = s.slot[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        if s.proj_depth[i] == img.depth_key[v, u]:
            ti.atomic_min(img.index[v, u], i)


@ti.kernel
def assoc_from_index(img: ti.template()):
    for v, u in img.index:
        i = img.index[v, u]
        if i == INT_MAX or i < 0:
            i = -1
        img.index[v, u] = i
        img.assoc[v, u] = i


# ---------------------------------------------------------------------------------------------------
# 4. Merge


@ti.func
def merge_one(s: ti.template(), i, img: ti.template(), vertex: ti.template(), normal: ti.template(), v, u,
              R, t, f, confidence: ti.template(), has_colour, frame_index):
    """p ← (w p + α (R q + t)) / (w + α), n likewise then normalised, colour likewise, w ← w + α."""
    q = vertex[v, u]
    nq = normal[v, u]
    a = measurement_weight(img, v, u, q.z, confidence)
    w = s.weight[i]
    s.position[i] = (w * s.position[i] + a * (R @ q + t)) / (w + a)
    n_sum = w * s.normal[i] + a * (R @ nq)
    length = n_sum.norm()
    if length > 0:
        s.normal[i] = n_sum / length
    if has_colour:
        s.colour[i] = (w * s.colour[i] + a * unpack_colour(img.colour[v, u])) / (w + a)
    s.weight[i] = w + a
    s.radius[i] = ti.min(s.radius[i], measurement_radius(q.z, nq.z, f))
    s.t_updated[i] = frame_index
    # the merged surfel at its pixel, for the coverage test of ``count_segments`` (the render scratch is
    # free during fusion)
    img.pc[v, u] = s.position[i]
    img.nc[v, u] = s.normal[i]
    img.rad[v, u] = s.radius[i]


@ti.kernel
def merge_candidates(s: ti.template(), img: ti.template(), vertex: ti.template(),
                     normal: ti.template(), pose: Rigid, f: ti.f32, confidence: ti.template(), has_colour: ti.i32,
                     frame_index: ti.i32):
    """Every surfel that a pixel's association chose averages in that pixel's measurement.

    Only the surfels the projection listed (``gather_candidates``: in the image; with Keller's order,
    compatible too) can have been chosen, so only they are visited, in index order: each reads its pixel
    from ``proj_pixel`` and merges when ``assoc`` there names it. Surfel attributes are then read and
    written in index order; looping over the pixels instead reached them in random order, one cache miss
    per attribute per merged surfel, and ran several times slower on maps of a million surfels."""
    W = img.assoc.shape[1]
    for k in range(s.n_candidates[0]):
        R, t = rigid(pose)
        i = s.slot[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        if img.assoc[v, u] == i:
            merge_one(s, i, img, vertex, normal, v, u, R, t, f, confidence, has_colour, frame_index)


# ---------------------------------------------------------------------------------------------------
# 5. Add (stream compaction in row-major pixel order)


COVERED = -2  # ``assoc`` of a pixel that a neighbour's merged surfel already covers: neither merged nor added


@ti.func
def covered_by_neighbour(img: ti.template(), v, u, qw, nw, dist_threshold, cos_threshold):
    """Whether the point qw (normal nw), both world frame, of pixel (v, u) lies on the disc of a surfel
    merged at one of the pixel's 8 neighbours: within the disc's radius in its tangent plane,
    ``dist_threshold`` along its normal, normals within the angle. The merged surfels are read as
    ``merge`` left them at their pixels (``img.pc``, ``nc``, ``rad``): image reads instead of random reads
    of the surfel arrays."""
    H, W = img.assoc.shape
    covered = False
    for dv in ti.static(range(-1, 2)):
        for du in ti.static(range(-1, 2)):
            if ti.static(dv != 0 or du != 0):
                y = v + dv
                x = u + du
                if 0 <= y < H and 0 <= x < W:
                    if img.assoc[y, x] >= 0 and not covered:
                        d = qw - img.pc[y, x]
                        n = img.nc[y, x]
                        along = n.dot(d)
                        r = img.rad[y, x]
                        if ti.abs(along) <= dist_threshold and d.norm_sqr() - along * along <= r * r \
                                and n.dot(nw) >= cos_threshold:
                            covered = True
    return covered


@ti.func
def segment_range(g, W):
    """Pixels [begin, end) of segment g of a row of W pixels."""
    width = (W + SEGMENTS - 1) // SEGMENTS
    return ti.min(g * width, W), ti.min((g + 1) * width, W)


@ti.kernel
def count_segments(img: ti.template(), vertex: ti.template(), normal: ti.template(), pose: Rigid,
                   dist_threshold: ti.f32, cos_threshold: ti.f32, cover: ti.template()):
    """Per row segment: pixels merged, valid pixels without an association (the new surfels), and covered
    pixels. With ``cover``, each valid unassociated pixel is first tested against the discs of the surfels
    merged at its 8 neighbours (``covered_by_neighbour``) and marked COVERED if one holds its point.
    ``pose`` (R, t) maps camera to world.

    Why: surfels project to pixel centres only approximately, so a map as dense as the image still leaves
    some pixels without a surfel of their own (two surfels round to one pixel, its neighbour gets none).
    Adding a surfel at every such pixel made the map grow by several percent of the frame at each frame,
    however often the surface had been seen. Keller et al. search a neighbourhood of a super-sampled index
    map for the same reason. Pixels only change from -1 to COVERED and only assoc ≥ 0 is read, so the
    result does not depend on the order the pixels run in."""
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
def scan_segments(img: ti.template(), totals: ti.template()):
    """Exclusive prefix sum of the new-surfel counts in row-major order; totals = (new, merged, -, -,
    covered)."""
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
    totals[0] = new
    totals[1] = merged
    totals[4] = covered


@ti.kernel
def append_new(s: ti.template(), n: ti.i32, img: ti.template(), vertex: ti.template(), normal: ti.template(),
               pose: Rigid, f: ti.f32, confidence: ti.template(), has_colour: ti.i32, frame_index: ti.i32,
               overflow: ti.template()):
    """Write the new surfels at n + seg_offset[v, g] + (rank within the segment), so in row-major pixel
    order; count any that do not fit.

    The caller has grown the map first, so ``overflow`` stays 0: it is the guard against an
    out-of-bounds write, not the capacity check.
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
                    if has_colour:
                        c = unpack_colour(img.colour[v, u])
                    s.colour[k] = c
                    s.weight[k] = measurement_weight(img, v, u, q.z, confidence)
                    s.radius[k] = measurement_radius(q.z, nq.z, f)
                    s.t_created[k] = frame_index
                    s.t_updated[k] = frame_index
                else:
                    lost += 1
                k += 1
        if lost > 0:
            ti.atomic_add(overflow[2], lost)


# ---------------------------------------------------------------------------------------------------
# 6. Remove (in-place compaction that keeps the order of the survivors below the new count)


@ti.kernel
def mark_removal(s: ti.template(), n: ti.i32, n_projected: ti.i32, frame_index: ti.i32,
                 unstable: ti.i32, unstable_weight: ti.f32, unstable_age: ti.i32,
                 free_space: ti.template(), margin: ti.f32, depth: ti.template()):
    """The surfels to drop: block_a[b] of them in block b, listed in index order at candidate[b·BLOCK :]
    (the projection's lists are spent by now: the merge has run). No per-surfel flags are written: the
    lists are all the later passes read, and a flag per surfel was 4 MB more to write per million.

    Unstable: weight < unstable_weight and not updated for unstable_age frames. Free space: the frame
    measures a depth more than ``margin`` behind the surfel along its ray, so the camera sees through
    it (only surfels that existed at projection time, i < n_projected, and were not merged now).
    """
    W = depth.shape[1]
    for b in range((n + BLOCK - 1) // BLOCK):
        removed = 0
        for j in range(ti.min(BLOCK, n - b * BLOCK)):  # a trip count, as in project_compatible
            i = b * BLOCK + j
            # branch-free: whether a surfel is weak and stale follows no pattern the branch predictor
            # can learn, and nested branches made this pass twice as slow as reading both fields
            rm = ti.select((unstable != 0) & (s.weight[i] < unstable_weight)
                           & (frame_index - s.t_updated[i] >= unstable_age), 1, 0)
            if ti.static(free_space):
                if i < n_projected and s.proj_pixel[i] >= 0:
                    if s.t_updated[i] != frame_index:
                        pix = s.proj_pixel[i]
                        d = depth[pix // W, pix % W]
                        if d > 0 and d > bits_depth(s.proj_depth[i]) + margin:
                            rm = 1
            s.candidate[b * BLOCK + removed] = i
            removed += rm
        s.block_a[b] = removed


@ti.kernel
def sum_blocks(s: ti.template(), n: ti.i32, totals: ti.template()):
    total = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        total += s.block_a[b]
    totals[3] = total


@ti.kernel
def scan_blocks(s: ti.template(), n: ti.i32, m: ti.i32):
    """Per block, holes (removed, index < m: block_b) and movers (kept, index ≥ m), and their exclusive
    prefix sums (offset_a, offset_b). There are as many of each. Blocks wholly below or above m take
    their counts from block_a (the removals per block); only the block that straddles m is re-counted.
    """
    holes = 0
    movers = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        lo = b * BLOCK
        hi = ti.min(lo + BLOCK, n)
        h = 0
        k = 0
        if hi <= m:
            h = s.block_a[b]
        elif lo >= m:
            k = (hi - lo) - s.block_a[b]
        else:  # the block's removals below m, then its survivors at or above m
            for r in range(s.block_a[b]):
                if s.candidate[lo + r] < m:
                    h += 1
            k = (hi - m) - (s.block_a[b] - h)
        s.block_b[b] = h
        s.offset_a[b] = holes
        s.offset_b[b] = movers
        holes += h
        movers += k
    s.n_candidates[0] = holes  # (the projection's count is spent: the merge has run)


@ti.kernel
def list_holes(s: ti.template(), m: ti.i32):
    """slot[k] = the k-th hole below m, in index order: the first block_b[b] entries of each block's list
    of removals (``mark_removal``; in index order, so those below m come first). Copying the lists
    rather than scanning per-surfel flags in every block with a hole (most blocks: ~10 k removals per
    step in a 1 M map) took this pass from 0.33 to 0.10 ms (320×240, two cores)."""
    for b in range((m + BLOCK - 1) // BLOCK):
        k = s.offset_a[b]
        for j in range(s.block_b[b]):
            s.slot[k + j] = s.candidate[b * BLOCK + j]


@ti.func
def copy_surfel(src: ti.template(), i, dst: ti.template(), k):
    dst.position[k] = src.position[i]
    dst.normal[k] = src.normal[i]
    dst.colour[k] = src.colour[i]
    dst.weight[k] = src.weight[i]
    dst.radius[k] = src.radius[i]
    dst.t_created[k] = src.t_created[i]
    dst.t_updated[k] = src.t_updated[i]


@ti.kernel
def fill_holes(s: ti.template(), n: ti.i32, m: ti.i32):
    """The k-th surviving surfel at or above m moves into the k-th hole below m (no overlap). The movers
    are listed first, after the h holes in ``slot``, so that the copies run in parallel over the surfels:
    the tail [m, n) spans too few blocks (~80) for a loop over blocks to use more than one thread."""
    h = s.n_candidates[0]  # holes (``scan_blocks``); h ≤ n / 2, so slot[h : 2h] fits
    for b in range(m // BLOCK, (n + BLOCK - 1) // BLOCK):
        k = h + s.offset_b[b]
        lo = b * BLOCK
        removals = s.block_a[b]
        r = 0  # the next entry of the block's list of removals (in index order) not below m
        while r < removals and s.candidate[lo + r] < m:
            r += 1
        for i in range(ti.max(lo, m), ti.min(lo + BLOCK, n)):
            if r < removals and s.candidate[lo + r] == i:
                r += 1
            else:
                s.slot[k] = i
                k += 1
    for k in range(s.n_candidates[0]):
        copy_surfel(s, s.slot[h + k], s, s.slot[k])


@ti.kernel
def copy_all(src: ti.template(), dst: ti.template(), n: ti.i32):
    for i in range(n):
        copy_surfel(src, i, dst, i)


@ti.kernel
def export_vector(src: ti.template(), out: ti.types.ndarray(), stride: ti.i32):
    """out[k] = src[k · stride] for the rows of ``out``: the live prefix (or a subsample) of one attribute,
    without copying the whole capacity as ``field.to_numpy()`` would."""
    for k in range(out.shape[0]):
        for c in ti.static(range(3)):
            out[k, c] = src[k * stride][c]


@ti.kernel
def export_scalar(src: ti.template(), out: ti.types.ndarray(), stride: ti.i32):
    for k in range(out.shape[0]):
        out[k] = src[k * stride]


# ---------------------------------------------------------------------------------------------------
# Rendering: screen-space surfel splatting with a z-test
#
# Splatting every surfel's disc over its pixel footprint costs (footprint) atomics per surfel: over
# 400 ms for a 1 M-surfel map at 320×240 on two CPU cores. Instead the renderer (1) projects the surfels
# as points into a z-buffer (the index map's two passes, culling back faces and unstable surfels), then
# (2) lets every pixel gather the front surfels of its (2h+1)² neighbourhood and keep the nearest disc
# its ray meets. A disc thus covers up to h pixels around its centre, as a splat would; the one
# difference is that only the front surfel of each pixel's point projection can spill into neighbours.


@ti.kernel
def gather_winners(s: ti.template(), img: ti.template(), pose: Rigid):
    """Camera-frame position, normal and radius of each pixel's front surfel (radius -1: none)."""
    for v, u in img.index:
        R, t = rigid(pose)
        i = img.index[v, u]
        r = -1.0
        if i != INT_MAX:
            img.pc[v, u] = R @ s.position[i] + t
            img.nc[v, u] = R @ s.normal[i]
            r = s.radius[i]
        img.rad[v, u] = r


@ti.kernel
def splat_gather(img: ti.template(), fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32, half: ti.template(),
                 out_vertex: ti.template(), out_normal: ti.template(), out_depth: ti.template()):
    """Per pixel: the pixel's own front surfel, unless a neighbour's disc that the ray meets lies clearly
    in front of it (an occluding edge), or the pixel has none (a hole, filled by the nearest neighbour disc).

    Why not simply the nearest disc of the neighbourhood: with noisy surfels the minimum depth over
    (2h+1)² overlapping discs is biased towards the camera by about the noise level (~5 mm on Kinect
    data), and ICP against such a prediction drifts by that much every frame. A neighbour therefore
    wins only when it is nearer by more than ``occlusion_margin`` (three sigma of Kinect-like noise).

    A surfel always covers its own pixel (at its centre depth if the ray misses the disc), so surfels
    small on screen still show as points. Ties in depth go to the smaller surfel index. Outputs are in
    the camera frame; ``img.view_index`` gets the surfel (INT_MAX = none). ``half`` is a compile-time
    constant: the unrolled neighbourhood runs about twice as fast as a loop.
    """
    H, W = img.index.shape
    for v, u in ti.ndrange(H, W):
        d = Vec3((u - cx) / fx, (v - cy) / fy, 1.0)
        own_z = 0.0
        best_z = 0.0
        best_i = INT_MAX
        best_n = Vec3(0.0, 0.0, 0.0)
        # The pixel's own front surfel first: it is the reference the neighbours must beat.
        if img.rad[v, u] >= 0:
            pc = img.pc[v, u]
            nc = img.nc[v, u]
            z = ray_disc_depth(pc, nc, img.rad[v, u], d)
            if z == 0.0:
                z = pc.z
            if z > 0:
                own_z = z
                best_z = z
                best_i = img.index[v, u]
                best_n = nc
        margin = occlusion_margin(own_z)
        for dv in ti.static(range(-half, half + 1)):
            for du in ti.static(range(-half, half + 1)):
                if ti.static(dv != 0 or du != 0):
                    y = v + dv
                    x = u + du
                    if 0 <= y < H and 0 <= x < W:
                        r = img.rad[y, x]
                        if r >= 0:
                            pc = img.pc[y, x]
                            z = ray_disc_depth(pc, img.nc[y, x], r, d)
                            if z > 0 and (own_z == 0.0 or z < own_z - margin):
                                j = img.index[y, x]
                                if best_i == INT_MAX or best_z == own_z or z < best_z or (z == best_z and j < best_i):
                                    best_z = z
                                    best_i = j
                                    best_n = img.nc[y, x]
        img.view_index[v, u] = best_i
        out_vertex[v, u] = best_z * d
        out_normal[v, u] = best_n
        out_depth[v, u] = best_z


@ti.func
def ray_disc_depth(pc, nc, r, d):
    """Depth along the pixel ray ``d`` (z = 1) where it meets the disc (centre pc, normal nc, radius r); 0 if not."""
    z = 0.0
    denom = nc.dot(d)
    if ti.abs(denom) > 1e-6:
        zz = nc.dot(pc) / denom
        if zz > 0 and (zz * d - pc).norm_sqr() <= r * r:
            z = zz
    return z


@ti.func
def occlusion_margin(z):
    """Three sigma of Kinect-like axial noise at depth z (Nguyen et al. 2012), at least 1 cm."""
    return ti.max(0.01, 3.0 * (0.0012 + 0.0019 * (z - 0.4) ** 2))


@ti.kernel
def shade(s: ti.template(), img: ti.template(), by_normal: ti.i32, background: Vec3):
    """RGB in [0, 1]: the surfel's colour, or its world normal mapped as (n + 1) / 2."""
    for v, u in img.view_index:
        i = img.view_index[v, u]
        c = background
        if i != INT_MAX:
            if by_normal:
                c = 0.5 * (s.normal[i] + 1.0)
            else:
                c = s.colour[i] / 255.0
        img.image[v, u] = c


# ---------------------------------------------------------------------------------------------------


def _weight_bits(radial: bool, depth: bool) -> int:
    return (RADIAL if radial else 0) | (DEPTH if depth else 0)


def _rigid(T: np.ndarray) -> np.ndarray:
    """A 4×4 rigid transform as a ``Rigid`` kernel argument: R row-major, then t, float32."""
    return flatten_pose(T).astype(np.float32)


def _world_to_camera(pose: np.ndarray) -> np.ndarray:
    """The inverse of a camera-to-world pose, as a ``Rigid`` argument."""
    return _rigid(np.linalg.inv(np.asarray(pose, dtype=np.float64)))


def _camera_to_world(pose: np.ndarray) -> np.ndarray:
    return _rigid(np.asarray(pose, dtype=np.float64))


class _Pool:
    """Taichi fields shared by every SurfelMap of the running Taichi program, and surfel arrays to reuse.

    Taichi allows 512 SNode trees per program, and freeing one makes it recompile every kernel (seconds),
    so the arrays of a garbage-collected map go back here for the next map of the same capacity instead
    of being freed, and all maps share one set of scratch images per resolution. Reset with the program.
    """

    _runtime = None  # weak reference to the Taichi runtime the fields belong to
    arrays: dict[int, list[SurfelArrays]] = {}
    scratch: dict[tuple[int, int], ImageScratch] = {}
    small: dict[str, object] = {}

    @classmethod
    def current(cls) -> type["_Pool"]:
        runtime = impl.get_runtime()
        if cls._runtime is None or cls._runtime() is not runtime:  # a new program (ti.reset / init)
            cls._runtime = weakref.ref(runtime)
            cls.arrays, cls.scratch, cls.small = {}, {}, {}
        return cls

    @classmethod
    def take_arrays(cls, capacity: int) -> SurfelArrays:
        spare = cls.current().arrays.get(capacity)
        return spare.pop() if spare else SurfelArrays(capacity)

    @classmethod
    def give_back(cls, runtime_ref, arrays: SurfelArrays) -> None:
        if cls._runtime is not None and cls._runtime is runtime_ref and runtime_ref() is not None:
            cls.arrays.setdefault(arrays.capacity, []).append(arrays)

    @classmethod
    def image_scratch(cls, height: int, width: int) -> ImageScratch:
        pool = cls.current()
        if (height, width) not in pool.scratch:
            pool.scratch[(height, width)] = ImageScratch(height, width)
        return pool.scratch[(height, width)]

    @classmethod
    def field(cls, name: str, make):
        pool = cls.current()
        if name not in pool.small:
            pool.small[name] = make()
        return pool.small[name]


@ti.data_oriented
class SurfelMap:
    """A growable surfel map on the Taichi side, with the stages of one fusion step and the renderer.

    ``count`` surfels are live, at indices [0, count). Stage methods take the frame's level-0 fields
    (``FrameMaps.vertex[0]`` etc.) and 4×4 camera-to-world poses (float64 NumPy).
    """

    def __init__(self, capacity: int = 4_000_000, grow: bool = True):
        if capacity < 1:
            raise MapCapacityError(f"fusion.capacity must be positive (got {capacity})")
        self.grow = grow
        self.count = 0
        self._projected = 0  # surfels that existed at the last projection (their proj_* are current)
        self._adopt(_Pool.take_arrays(int(capacity)))
        # new, merged, overflow, removed, covered: per-call results, so one field serves every map
        self.totals = _Pool.field("totals", lambda: ti.field(ti.i32, shape=5))
        self.covered = 0  # pixels the last ``add`` skipped as covered by a neighbour's surfel

    def _adopt(self, arrays: SurfelArrays) -> None:
        """Use ``arrays`` from now on; they go back to the pool when this map is garbage-collected."""
        if getattr(self, "_finalizer", None) is not None:
            self._finalizer.detach()
        self.arrays = arrays
        self._finalizer = weakref.finalize(self, _Pool.give_back, _Pool._runtime, arrays)

    # -- storage ---------------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return self.arrays.capacity

    def scratch(self, height: int, width: int) -> ImageScratch:
        """Work images of this resolution: shared by all maps, overwritten by the next step or render."""
        return _Pool.image_scratch(height, width)

    def ensure_capacity(self, needed: int) -> None:
        """Make room for ``needed`` surfels in total: grow ×2 until they fit, or raise MapCapacityError."""
        if needed <= self.capacity:
            return
        if not self.grow:
            raise MapCapacityError(
                f"surfel map full: {self.count} surfels + {needed - self.count} new > capacity {self.capacity}; "
                f"raise fusion.capacity (e.g. --set fusion.capacity={2 * needed}) or allow fusion.grow")
        capacity = self.capacity
        while capacity < needed:
            capacity *= 2
        new = SurfelArrays(capacity)
        copy_all(self.arrays, new, self.count)
        old = self.arrays
        self._adopt(new)
        # Freed rather than pooled: a grown map is large. Taichi then recompiles its kernels (once).
        old.destroy()
        self._projected = 0  # the scratch was not copied

    def clear(self) -> None:
        self.count = 0
        self._projected = 0

    # -- 1-3: project, filter pass 1, filter pass 2 ------------------------------------------------------
    def project(self, pose: np.ndarray, intrinsics, height: int, width: int, index_map: bool = True) -> ImageScratch:
        """Filter pass 1 of the surfels in the frame with camera-to-world ``pose`` and, with ``index_map``,
        the index map (per pixel the surfel nearest in depth, ties to the smaller index)."""
        img = self.scratch(height, width)
        to_camera = _world_to_camera(pose)
        clear_index(img)
        if self.count > 0:
            project_surfels(self.arrays, self.count, img, to_camera, *intrinsics.as_tuple(), False, 0.0)
            self._index_map(img, index_map)
        self._projected = self.count
        return img

    def _index_map(self, img: ImageScratch, with_index: bool = True) -> None:
        """List the surfels the last projection kept (in index order) and, with ``with_index``, build the
        index map from them: per pixel the nearest in depth, exact ties to the smaller index."""
        gather_candidates(self.arrays, self.count)
        if with_index:
            nearest_candidates(self.arrays, img)
            claim_candidates(self.arrays, img)

    def associate(self, img: ImageScratch, vertex, normal, pose: np.ndarray, dist_threshold: float,
                  normal_threshold_deg: float) -> None:
        """Filter pass 2 into ``img.assoc`` (turns the index map's "none" into -1)."""
        to_world = _camera_to_world(pose)
        cos_threshold = math.cos(math.radians(normal_threshold_deg))
        associate(self.arrays, img, vertex, normal, to_world, dist_threshold, cos_threshold)

    def associate_compatible(self, pose: np.ndarray, intrinsics, vertex, normal, dist_threshold: float,
                             normal_threshold_deg: float) -> ImageScratch:
        """Keller's order instead of ``project`` + ``associate``: filter passes 1 and 2 for every surfel in
        one projection, then per pixel the nearest surfel that passed: ``img.assoc`` (and ``img.index``,
        the same) hold it or -1."""
        H, W = vertex.shape
        img = self.scratch(H, W)
        to_camera = _world_to_camera(pose)
        cos_threshold = math.cos(math.radians(normal_threshold_deg))
        clear_index(img)
        if self.count > 0:
            world_measurements(img, vertex, normal, _camera_to_world(pose))
            project_compatible(self.arrays, self.count, img, to_camera, *intrinsics.as_tuple(), dist_threshold,
                               cos_threshold)
            self._index_map(img)
        self._projected = self.count
        assoc_from_index(img)
        return img

    def mark_covered(self, img: ImageScratch, vertex, normal, pose: np.ndarray, dist_threshold: float,
                     normal_threshold_deg: float) -> None:
        """After ``merge``: unassociated pixels on the disc of a neighbour's merged surfel are not added
        (``img.assoc`` = COVERED). ``add(..., cover=...)`` does the same in its own pass; this is the test on
        its own (the counts it also makes are made again by ``add``)."""
        count_segments(img, vertex, normal, _camera_to_world(pose), dist_threshold,
                       math.cos(math.radians(normal_threshold_deg)), True)

    def pass1_mask(self) -> np.ndarray:
        """Filter pass 1 of the last projection: surfels inside the image with positive depth."""
        return self.arrays.proj_pixel.to_numpy()[: self._projected] >= 0

    # -- 4-5: merge and add --------------------------------------------------------------------------------
    def merge(self, img: ImageScratch, vertex, normal, pose, intrinsics, frame_index: int,
              confidence: bool, sigma: float, has_colour: bool, depth_weighted: bool = False) -> None:
        if self._projected > 0:
            if confidence:
                img.radial_confidence(intrinsics.cx, intrinsics.cy, sigma)
            merge_candidates(self.arrays, img, vertex, normal, _camera_to_world(pose), intrinsics.fx,
                             _weight_bits(confidence, depth_weighted), int(has_colour), frame_index)

    def add(self, img: ImageScratch, vertex, normal, pose, intrinsics, frame_index: int, confidence: bool,
            sigma: float, has_colour: bool, depth_weighted: bool = False,
            cover: tuple[float, float] | None = None) -> tuple[int, int]:
        """Append the valid unassociated pixels as surfels; returns (added, merged) pixel counts. With
        ``cover`` = (dist_threshold, normal_threshold_deg), pixels that ``mark_covered`` would mark are
        marked first, in the same pass, and not added."""
        dist, angle = cover if cover is not None else (0.0, 0.0)
        count_segments(img, vertex, normal, _camera_to_world(pose), dist, math.cos(math.radians(angle)),
                       cover is not None)
        scan_segments(img, self.totals)
        totals = self.totals.to_numpy()
        new, merged, self.covered = int(totals[0]), int(totals[1]), int(totals[4])
        self.ensure_capacity(self.count + new)  # before any write: grow or raise
        if new > 0:
            if confidence:
                img.radial_confidence(intrinsics.cx, intrinsics.cy, sigma)
            self.totals[2] = 0
            append_new(self.arrays, self.count, img, vertex, normal, _camera_to_world(pose), intrinsics.fx,
                       _weight_bits(confidence, depth_weighted), int(has_colour), frame_index, self.totals)
            lost = int(self.totals[2])
            if lost:  # cannot happen after ensure_capacity; never let it pass silently
                raise MapCapacityError(f"{lost} new surfels did not fit (capacity {self.capacity}): "
                                       f"raise fusion.capacity")
            self.count += new
        return new, merged

    # -- 6: remove ------------------------------------------------------------------------------------------
    def remove(self, frame_index: int, unstable: bool, unstable_weight: float, unstable_age: int,
               free_space: bool = False, free_space_margin: float = 0.05, depth=None) -> int:
        """Drop unstable / free-space-violating surfels and compact in place; returns how many went."""
        n = self.count
        if n == 0 or not (unstable or free_space):
            return 0
        if free_space and depth is None:
            raise ValueError("free-space removal needs the frame's depth field")
        if depth is None:
            depth = self._dummy_depth()  # never read: free-space removal is off
        mark_removal(self.arrays, n, min(self._projected, n), frame_index, int(unstable), unstable_weight,
                     unstable_age, bool(free_space), free_space_margin, depth)
        sum_blocks(self.arrays, n, self.totals)
        removed = int(self.totals[3])
        if removed > 0:
            m = n - removed
            scan_blocks(self.arrays, n, m)
            list_holes(self.arrays, m)
            fill_holes(self.arrays, n, m)
            self.count = m
            self._projected = 0  # indices moved: the projection scratch is stale
        return removed

    def _dummy_depth(self):
        return _Pool.field("no_depth", lambda: ti.field(ti.f32, shape=(1, 1)))

    # -- rendering ------------------------------------------------------------------------------------------
    def render(self, pose: np.ndarray, intrinsics, out_vertex=None, out_normal=None, out_depth=None,
               min_weight: float = 0.0, max_half: int = 1) -> ImageScratch:
        """Predicted vertex / normal / depth maps in the camera frame of ``pose`` (zero = no surfel).

        Outputs are Taichi fields of shape (intrinsics.height, intrinsics.width), e.g. a FrameMaps' level
        0; left out, they are the returned scratch's ``vertex``, ``normal``, ``depth`` fields (valid until
        the next render or fusion step at this resolution). Surfels with weight ≥ ``min_weight`` that face
        the camera are splatted as discs reaching at most ``max_half`` pixels from their centre pixel; the
        vertex lies on the pixel's ray, at the depth where the ray meets the disc.
        """
        img = self.scratch(intrinsics.height, intrinsics.width)
        to_camera = _world_to_camera(pose)
        fx, fy, cx, cy = intrinsics.as_tuple()
        clear_index(img)
        if self.count > 0:
            project_surfels(self.arrays, self.count, img, to_camera, fx, fy, cx, cy, True, float(min_weight))
            self._index_map(img)
        self._projected = 0  # proj_* now hold the render's projection, not the fusion step's
        gather_winners(self.arrays, img, to_camera)
        splat_gather(img, fx, fy, cx, cy, int(max_half),
                     img.vertex if out_vertex is None else out_vertex,
                     img.normal if out_normal is None else out_normal,
                     img.depth if out_depth is None else out_depth)
        return img

    def render_image(self, pose: np.ndarray, intrinsics, by_normal: bool = False, min_weight: float = 0.0,
                     max_half: int = 3, background=(0.12, 0.12, 0.12)) -> np.ndarray:
        """uint8 RGB view of the map from ``pose``: surfel colours, or world normals as (n + 1) / 2."""
        img = self.render(pose, intrinsics, min_weight=min_weight, max_half=max_half)
        shade(self.arrays, img, int(by_normal), np.asarray(background, dtype=np.float32))
        return (np.clip(img.image.to_numpy(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

    # -- NumPy edges ----------------------------------------------------------------------------------------
    def to_numpy(self, names=ATTRIBUTES, stride: int = 1) -> dict[str, np.ndarray]:
        """The live surfels as NumPy arrays (copies), keyed by attribute name; with ``stride`` k, every k-th
        surfel only (a cheap, deterministic subsample for logging). Only those surfels are copied: the
        fields hold the whole capacity, and copying all of it cost ~0.5 s per snapshot of a 4 M map."""
        stride = max(1, int(stride))
        m = (self.count + stride - 1) // stride
        out = {}
        for name in names:
            field = getattr(self.arrays, name)
            dtype = np.float32 if field.dtype == ti.f32 else np.int32
            if getattr(field, "n", 1) == 3:
                out[name] = np.empty((m, 3), dtype)
                if m:
                    export_vector(field, out[name], stride)
            else:
                out[name] = np.empty(m, dtype)
                if m:
                    export_scalar(field, out[name], stride)
        return out

    def from_numpy(self, data: dict[str, np.ndarray]) -> None:
        """Replace the map by the given surfels (every attribute of ATTRIBUTES, same length)."""
        n = len(data["position"])
        self.ensure_capacity(n)
        for name, field in zip(ATTRIBUTES, self.arrays.attributes):
            full = field.to_numpy()
            full[:n] = data[name]
            field.from_numpy(full)
        self.count = n
        self._projected = 0
