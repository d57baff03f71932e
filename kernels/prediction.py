"""The model prediction: vertex, normal and depth maps of the surfel map seen from a pose (what ICP
tracks against), and RGB views of it. Screen-space surfel splatting with a z-test.

Splatting every surfel's disc over its pixel footprint costs an atomic per covered pixel per surfel, far
too slow for maps of millions of surfels. Instead the renderer (1) projects the surfels as points into a
z-buffer (``index_map``, leaving out back faces and unstable surfels), then (2) lets every pixel gather the
front surfels of its (2h+1)² neighbourhood and keep the nearest disc its ray meets (``splat_gather_loop``). A
disc thus covers up to h pixels around its centre, as a splat would; the one difference is that only the
front surfel of each pixel's point projection can spill into neighbours.
"""

import taichi as ti

from ti_fusion.kernels.common import INT_MAX, Rigid, Vec3, data_oriented, depth_sigma, rigid
from ti_fusion.kernels.index_map import IndexMap, build_loops, project_surfels_loop

FAR_DEPTH = 3.0e38  # beyond any disc: "none met yet" in ``splat_apart_loop``


@data_oriented
class PredictionImages:
    """The renderer's per-pixel images at one resolution."""

    def __init__(self, height: int, width: int):
        self.height, self.width = height, width
        shape = (height, width)
        self.index_map = IndexMap(height, width)
        # the front surfel of each pixel's point projection, camera frame (``gather_front_loop``)
        self.front_position = ti.Vector.field(3, ti.f32, shape=shape)
        self.front_normal = ti.Vector.field(3, ti.f32, shape=shape)
        self.front_radius = ti.field(ti.f32, shape=shape)  # -1 = no surfel
        # the splat result: the surfel seen at the pixel (INT_MAX = none) and the default outputs
        self.view_index = ti.field(ti.i32, shape=shape)
        self.vertex = ti.Vector.field(3, ti.f32, shape=shape)
        self.normal = ti.Vector.field(3, ti.f32, shape=shape)
        self.depth = ti.field(ti.f32, shape=shape)
        self.image = ti.Vector.field(3, ti.f32, shape=shape)  # RGB in [0, 1] (``shade``)
        # the depth with the holes filled, beside outputs that keep them (``splat_apart_loop``), by default
        self.filled_depth = ti.field(ti.f32, shape=shape)


@ti.kernel
def render(s: ti.template(), n: ti.i32, img: ti.template(), pose: Rigid, fx: ti.f32, fy: ti.f32, cx: ti.f32,
           cy: ti.f32, min_weight: ti.f32, min_time: ti.i32, half: ti.i32, fill_half: ti.i32,
           out_vertex: ti.template(), out_normal: ti.template(), out_depth: ti.template(), apart: ti.template(),
           out_filled: ti.template()):
    """A prediction of the first ``n`` surfels in one launch, as consecutive loops: the projection with the
    render's filters (``index_map.project_surfels_loop``), the index map (``index_map.build_loops``: cleared,
    then the nearest surfel per pixel), ``gather_front_loop`` and ``splat_gather_loop`` (with ``apart``
    ``splat_apart_loop``, whose outputs are those of ``half`` = 0, ``fill_half`` = 1 and ``clear_holes``, and
    ``out_filled`` the filled depth). ``pose`` maps world to camera; with n = 0 every pixel is empty."""
    project_surfels_loop(s, n, img.index_map, pose, fx, fy, cx, cy, True, min_weight, min_time)
    # with packed keys (the CPU) the index map's last loop clears the front radius too (a parallel loop fewer)
    build_loops(s, n, img.index_map, True, img.front_radius if ti.static(img.index_map.packed_keys) else None)
    gather_front_loop(s, img, pose)
    if ti.static(apart):
        splat_apart_loop(img, fx, fy, cx, cy, out_vertex, out_normal, out_depth, out_filled)
    else:
        splat_gather_loop(img, fx, fy, cx, cy, half, fill_half, out_vertex, out_normal, out_depth)


@ti.func
def gather_front_loop(s: ti.template(), img: ti.template(), pose: ti.template()):
    """Camera-frame position, normal and radius of each pixel's front surfel (radius -1: none): every pixel
    cleared (on the CPU by the index map's ``unpack_loop``, before), then each listed surfel that won its
    pixel in the index map writes it there. Visiting the listed surfels in index order reads their
    attributes in memory order, where a loop over the pixels reached them in random order
    (docs/PERFORMANCE.md)."""
    if ti.static(not img.index_map.packed_keys):
        for v, u in img.front_radius:
            img.front_radius[v, u] = -1.0
    W = img.front_radius.shape[1]
    for k in range(s.n_listed[None]):
        R, t = rigid(pose)
        i = s.listed[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        if img.index_map.index[v, u] == i:
            img.front_position[v, u] = R @ s.position[i] + t
            img.front_normal[v, u] = R @ s.normal[i]
            img.front_radius[v, u] = s.radius[i]


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
    """Three sigma of the sensor's depth noise at depth z, at least 1 cm."""
    return ti.max(0.01, 3.0 * depth_sigma(z, ti.f32))


@ti.func
def splat_gather_loop(img: ti.template(), fx, fy, cx, cy, half, fill_half, out_vertex: ti.template(),
                      out_normal: ti.template(), out_depth: ti.template()):
    """Per pixel: the pixel's own front surfel, unless a neighbour's disc that the ray meets lies clearly
    in front of it (an occluding edge), or the pixel has none (a hole, filled by the nearest neighbour disc).

    Why not simply the nearest disc of the neighbourhood: with noisy surfels the minimum depth over
    (2h+1)² overlapping discs is biased towards the camera by about the noise level, and ICP against such
    a prediction drifts by that much every frame. A neighbour therefore wins only when it is nearer by
    more than ``occlusion_margin``.

    A surfel always covers its own pixel (at its centre depth if the ray misses the disc), so surfels
    small on screen still show as points. Ties in depth go to the smaller surfel index. Outputs are in
    the camera frame; ``img.view_index`` gets the surfel (INT_MAX = none). ``half`` is a runtime argument: one
    compiled kernel serves every neighbourhood size. A pixel without a front surfel of its own searches
    max(half, ``fill_half``) pixels around it instead: the fusion step adds no surfel at a pixel whose
    point lies on the disc of a surfel at one of its 8 neighbours (``fusion.count_segments``), so
    ``fill_half`` = 1 renders what the map was built to cover, while pixels with their own surfel keep
    it (no dilation of occluding edges).
    """
    H, W = img.front_radius.shape
    for v, u in ti.ndrange(H, W):
        d = Vec3((u - cx) / fx, (v - cy) / fy, 1.0)
        own_z = 0.0
        best_z = 0.0
        best_i = INT_MAX
        best_n = Vec3(0.0, 0.0, 0.0)
        # The pixel's own front surfel first: it is the reference the neighbours must beat.
        if img.front_radius[v, u] >= 0:
            pc = img.front_position[v, u]
            nc = img.front_normal[v, u]
            z = ray_disc_depth(pc, nc, img.front_radius[v, u], d)
            if z == 0.0:
                z = pc.z
            if z > 0:
                own_z = z
                best_z = z
                best_i = img.index_map.index[v, u]
                best_n = nc
        margin = occlusion_margin(own_z)
        reach = half
        if best_i == INT_MAX:
            reach = ti.max(half, fill_half)
        # A runtime loop, in the order the unrolled one had (rows, then columns): unrolled, its (2h+1)²
        # copies made this by far the slowest kernel to compile.
        for dv in range(-reach, reach + 1):
            for du in range(-reach, reach + 1):
                if dv != 0 or du != 0:
                    y = v + dv
                    x = u + du
                    if 0 <= y < H and 0 <= x < W:
                        r = img.front_radius[y, x]
                        if r >= 0:
                            pc = img.front_position[y, x]
                            z = ray_disc_depth(pc, img.front_normal[y, x], r, d)
                            if z > 0 and (own_z == 0.0 or z < own_z - margin):
                                j = img.index_map.index[y, x]
                                if best_i == INT_MAX or best_z == own_z or z < best_z or (z == best_z and j < best_i):
                                    best_z = z
                                    best_i = j
                                    best_n = img.front_normal[y, x]
        img.view_index[v, u] = best_i
        out_vertex[v, u] = best_z * d
        out_normal[v, u] = best_n
        out_depth[v, u] = best_z


@ti.func
def splat_apart_loop(img: ti.template(), fx, fy, cx, cy, out_vertex: ti.template(), out_normal: ti.template(),
                     out_depth: ti.template(), out_filled: ti.template()):
    """``splat_gather_loop`` with ``half`` = 0 and ``fill_half`` = 1, its holes kept apart: the outputs and
    ``img.view_index`` hold each pixel's own front surfel and zero (INT_MAX) where it has none, what
    ``clear_holes_loop`` leaves of the filled render, and ``out_filled`` the filled render's depth (the
    nearest disc the ray meets among the 8 neighbours' front surfels at a hole, the own depth elsewhere), from
    which the model's coarse levels are built (``SurfelMapper.render_pyramid``).

    The same arithmetic as ``splat_gather_loop``, bit for bit, at a fraction of its cost: a hole's depth is
    all that is kept of it, so it takes the minimum depth (which surfel and normal won a tie does not matter),
    and the 3×3 neighbourhood is unrolled (docs/PERFORMANCE.md). A pixel whose own disc lies behind the
    camera (z ≤ 0, which the projection's z > 0 rules out) counts as a hole here."""
    H, W = img.front_radius.shape
    for v, u in ti.ndrange(H, W):
        d = Vec3((u - cx) / fx, (v - cy) / fy, 1.0)
        own_z = 0.0
        if img.front_radius[v, u] >= 0:
            pc = img.front_position[v, u]
            z = ray_disc_depth(pc, img.front_normal[v, u], img.front_radius[v, u], d)
            if z == 0.0:
                z = pc.z
            own_z = ti.max(z, 0.0)
        filled = own_z
        if own_z > 0:
            img.view_index[v, u] = img.index_map.index[v, u]
            out_vertex[v, u] = own_z * d
            out_normal[v, u] = img.front_normal[v, u]
            out_depth[v, u] = own_z
        else:
            nearest = ti.f32(FAR_DEPTH)
            for dv in ti.static(range(-1, 2)):
                for du in ti.static(range(-1, 2)):
                    if ti.static(dv != 0 or du != 0):
                        y = v + dv
                        x = u + du
                        if 0 <= y < H and 0 <= x < W:
                            r = img.front_radius[y, x]
                            if r >= 0:
                                z = ray_disc_depth(img.front_position[y, x], img.front_normal[y, x], r, d)
                                if z > 0:
                                    nearest = ti.min(nearest, z)
            filled = ti.select(nearest < FAR_DEPTH, nearest, 0.0)
            img.view_index[v, u] = INT_MAX
            out_vertex[v, u] = Vec3(0.0, 0.0, 0.0)
            out_normal[v, u] = Vec3(0.0, 0.0, 0.0)
            out_depth[v, u] = 0.0
        out_filled[v, u] = filled


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
                c = s.color[i] / 255.0
        img.image[v, u] = c


@ti.kernel
def clear_holes(img: ti.template(), out_vertex: ti.template(), out_normal: ti.template(), out_depth: ti.template()):
    """``clear_holes_loop`` over every pixel, in one launch."""
    clear_holes_loop(img, out_vertex, out_normal, out_depth, 1)


@ti.func
def clear_holes_loop(img: ti.template(), out_vertex: ti.template(), out_normal: ti.template(),
                     out_depth: ti.template(), clear):
    """Zero the outputs at the pixels no surfel projects to (``img.index_map``): after a render with
    ``splat_gather_loop``'s ``fill_half`` and the pyramid built from it, level 0 goes back to the surfels' own
    pixels (and ``img.view_index`` to none). The outputs are indexed as the image (row 0 of a stacked field
    is level 0). With ``clear`` = 0 the loop runs over no rows (a run-time choice: one compiled instance
    serves both)."""
    H, W = img.index_map.index.shape
    for v, u in ti.ndrange(H * clear, W):  # (the outputs may be levels of a stacked field: no struct-for)
        if img.index_map.index[v, u] == INT_MAX:
            img.view_index[v, u] = INT_MAX
            out_vertex[v, u] = Vec3(0.0, 0.0, 0.0)
            out_normal[v, u] = Vec3(0.0, 0.0, 0.0)
            out_depth[v, u] = 0.0
