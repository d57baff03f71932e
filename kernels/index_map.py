"""Projection of the surfels into an image, and the index map: per pixel, the surfel nearest in depth.

Both the fusion step (to find each pixel's surfel) and the prediction (as a z-buffer) start here.
``project_surfels`` projects every surfel (pixel u = ⌊fx x/z + cx + ½⌋, v likewise: rounded to the
nearest, so a frame vertex at pixel u projects back to u) and lists, per block of BLOCK surfels, those it
keeps; ``gather_listed`` joins the lists in index order, and the index map's two passes run over that list
only (about half the map when rendering, a few percent with Keller's association order).

On the CPU the projection takes eight surfels at a time as 8-vectors (``project_pack``), which LLVM
vectorises where it leaves a loop over surfels scalar; the few whose packed result could round to another
pixel or facing than one at a time are projected again one at a time (``project_one``).

On the CPU one pass does it (``nearest_packed``): an atomic min of the 64-bit key depth bits << 32 | index
per pixel, whose low half is then the index (``unpack_loop``): the same winner, one pass over the list
fewer. Elsewhere two passes. Why two: Vulkan guarantees only 32-bit atomics, so a 64-bit key (depth << 32 | index) is out, and
a packed 32-bit key would leave too few bits for either (4 M surfels need 22 bits, leaving 10 bits of
depth: 4 mm steps over 4 m, so surfels a few millimetres apart would tie and be ranked by index). So pass 1
(``nearest_listed``) takes an atomic min of the depth's float bits (``depth_bits``) per pixel, and pass 2
(``claim_listed``) lets every surfel whose depth bits equal its pixel's minimum take an atomic min of its
index. The winner is the nearest surfel, exact ties broken by the smallest index: deterministic on every
backend.
"""

import taichi as ti

from ti_fusion.backend import on_cpu
from ti_fusion.kernels.common import BLOCK, INT_MAX, LANES, Pack, Rigid, data_oriented, depth_bits, given, rigid

INT64_MAX = 2**63 - 1  # "no surfel" in a packed key


@data_oriented
class IndexMap:
    """The index map of one resolution."""

    def __init__(self, height: int, width: int):
        shape = (height, width)
        self.index = ti.field(ti.i32, shape=shape)  # the nearest surfel, INT_MAX = none
        # CPU: one pass with 64-bit keys (module docstring); elsewhere the two 32-bit passes
        self.packed_keys = on_cpu()
        if self.packed_keys:
            self.key = ti.field(ti.i64, shape=shape)  # depth bits << 32 | index of the nearest, INT64_MAX = none
        else:
            self.depth_key = ti.field(ti.i32, shape=shape)  # float bits of the nearest depth, INT_MAX = none


@ti.func
def clear_loop(imap: ti.template()):
    for v, u in imap.index:
        if ti.static(imap.packed_keys):
            imap.key[v, u] = ti.i64(INT64_MAX)
        else:
            imap.depth_key[v, u] = INT_MAX
            imap.index[v, u] = INT_MAX


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
    s.listed_by_block[b * BLOCK + found] = i
    return found + ti.select(keep, 1, 0)


@ti.kernel
def project_surfels(s: ti.template(), n: ti.i32, imap: ti.template(), pose: Rigid, fx: ti.f32, fy: ti.f32,
                    cx: ti.f32, cy: ti.f32, render: ti.template(), min_weight: ti.f32, min_time: ti.i32):
    """``project_surfels_loop`` in one launch."""
    project_surfels_loop(s, n, imap, pose, fx, fy, cx, cy, render, min_weight, min_time)


# A packed projection whose pixel coordinate lies this close to a pixel edge is done again one surfel at a time
# (``project_pack``).
EDGE = 1e-3


@ti.func
def near_edge(f):
    r = f - ti.floor(f)
    return (r < EDGE) | (r > 1.0 - EDGE)


@ti.func
def project_one(s: ti.template(), i, pose: ti.template(), fx, fy, cx, cy, H, W, render: ti.template(), min_weight,
                min_time):
    """``proj_pixel`` and ``proj_depth`` of surfel i, one at a time; returns whether it is kept."""
    R, t = rigid(pose)  # per surfel: see docs/KERNELS.md
    pc = R @ s.position[i] + t
    keep, u, v = project_to_pixel(pc, fx, fy, cx, cy, H, W)
    if ti.static(render):
        keep = keep & (s.weight[i] >= min_weight) & ((R @ s.normal[i]).dot(pc) < 0) \
            & (s.t_updated[i] >= min_time)
    s.proj_pixel[i] = ti.select(keep, v * W + u, -1)
    s.proj_depth[i] = depth_bits(ti.abs(pc.z))
    return keep


@ti.func
def project_pack(s: ti.template(), i0, pose: ti.template(), fx, fy, cx, cy, H, W):
    """``project_one`` without the render's filters for surfels i0 .. i0 + 7 as 8-vectors (LLVM vectorises
    them; a loop over surfels it leaves scalar). Taichi compiles with fast math, so the packed arithmetic may
    round differently from ``project_one``'s: where that could move a point to another pixel (``EDGE``) the
    surfel is projected again by ``project_one``, so the pixels are the one-at-a-time ones. (The depths
    agreed bit for bit with the scalar loop's on redkitchen, not by construction: docs/PERFORMANCE.md.)"""
    R, t = rigid(pose)
    px = Pack([s.position[i0 + l][0] for l in ti.static(range(LANES))])
    py = Pack([s.position[i0 + l][1] for l in ti.static(range(LANES))])
    pz = Pack([s.position[i0 + l][2] for l in ti.static(range(LANES))])
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    inv_z = 1.0 / z
    uf = fx * x * inv_z + cx + 0.5
    vf = fy * y * inv_z + cy + 0.5
    inside = (z > 0) & (uf >= 0.0) & (uf < W) & (vf >= 0.0) & (vf < H)
    u = ti.min(ti.cast(ti.select(inside, uf, 0.0), ti.i32), W - 1)
    v = ti.min(ti.cast(ti.select(inside, vf, 0.0), ti.i32), H - 1)
    again = (near_edge(uf) | near_edge(vf)) & (z > 0)
    pix = ti.select(inside, v * W + u, -1)
    az = ti.abs(z)
    redo = 0
    for l in ti.static(range(LANES)):
        s.proj_pixel[i0 + l] = pix[l]
        s.proj_depth[i0 + l] = depth_bits(az[l])
        redo |= ti.select(again[l], 1 << l, 0)
    if redo != 0:  # rare: a branch that predicts
        for l in range(LANES):
            if (redo >> l) & 1:
                project_one(s, i0 + l, pose, fx, fy, cx, cy, H, W, False, 0.0, 0)


@ti.func
def project_surfels_loop(s: ti.template(), n, imap: ti.template(), pose: ti.template(), fx, fy, cx, cy,
                         render: ti.template(), min_weight, min_time):
    """``proj_pixel`` ≥ 0 (and a listing per block) for the surfels inside the image of ``imap`` with
    z > 0: filter pass 1 of the fusion step. With ``render``, surfels below ``min_weight``, facing away or
    last updated before frame ``min_time`` (inactive, ElasticFusion's time window) are left out too.
    ``pose`` (R, t) maps world to camera. Branch-free, as ``fusion.project_compatible_loop``; without
    ``render``, on the CPU eight surfels at a time (``project_pack``; with the render's filters packing did
    not pay: docs/PERFORMANCE.md).
    """
    H, W = imap.index.shape
    for b in range((n + BLOCK - 1) // BLOCK):  # parallel over blocks, serial inside one
        found = 0
        m = ti.min(BLOCK, n - b * BLOCK)
        packs = 0
        if ti.static(on_cpu() and not render):
            packs = m // LANES
        for g in range(packs):
            i0 = b * BLOCK + g * LANES
            project_pack(s, i0, pose, fx, fy, cx, cy, H, W)
            for l in ti.static(range(LANES)):
                found = list_if(s, b, found, i0 + l, s.proj_pixel[i0 + l] >= 0)
        for j in range(packs * LANES, m):  # a trip count, not a break at n
            i = b * BLOCK + j
            keep = project_one(s, i, pose, fx, fy, cx, cy, H, W, render, min_weight, min_time)
            found = list_if(s, b, found, i, keep)
        s.block_listed[b] = found


@ti.func
def gather_listed(s: ti.template(), n, clear: ti.template()):
    """The per-block lists of the last projection (``project_surfels`` or ``fusion.project_compatible_loop``)
    into one list in index order, ``listed[:n_listed]``: a serial scan over the blocks, then one parallel
    copy per block. With ``clear`` (an ``IndexMap`` with a packed key, else None), that copy's loop also empties
    the key image, a row per iteration (``clear_loop``'s work, a parallel loop fewer; still just before
    ``nearest_packed``, whose scattered atomics then find the image in the cache)."""
    total = 0
    ti.loop_config(serialize=True)
    for b in range((n + BLOCK - 1) // BLOCK):
        s.listed_offset[b] = total
        total += s.block_listed[b]
    s.n_listed[None] = total
    if ti.static(given(clear)):
        blocks = (n + BLOCK - 1) // BLOCK
        rows = clear.key.shape[0]
        for b in range(ti.max(blocks, rows)):
            if b < blocks:
                for k in range(s.block_listed[b]):
                    s.listed[s.listed_offset[b] + k] = s.listed_by_block[b * BLOCK + k]
            if b < rows:
                for u in range(clear.key.shape[1]):
                    clear.key[b, u] = ti.i64(INT64_MAX)
    else:
        for b in range((n + BLOCK - 1) // BLOCK):
            for k in range(s.block_listed[b]):
                s.listed[s.listed_offset[b] + k] = s.listed_by_block[b * BLOCK + k]


@ti.func
def nearest_listed(s: ti.template(), imap: ti.template()):
    """Pass 1 of the index map, over the listed surfels: the nearest depth per pixel."""
    W = imap.index.shape[1]
    for k in range(s.n_listed[None]):
        i = s.listed[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        key = s.proj_depth[i]
        if key < imap.depth_key[v, u]:  # plain read first: most lose, and skip the atomic
            ti.atomic_min(imap.depth_key[v, u], key)


@ti.func
def claim_listed(s: ti.template(), imap: ti.template()):
    """Pass 2 of the index map, over the listed surfels: among those at a pixel's nearest depth, the
    smallest index wins."""
    W = imap.index.shape[1]
    for k in range(s.n_listed[None]):
        i = s.listed[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        if s.proj_depth[i] == imap.depth_key[v, u]:
            ti.atomic_min(imap.index[v, u], i)


@ti.func
def nearest_packed(s: ti.template(), imap: ti.template()):
    """The index map in one pass over the listed surfels (CPU): per pixel the smallest key depth bits << 32 |
    index, so the nearest depth and, among exact ties, the smallest index, as the two passes choose."""
    W = imap.index.shape[1]
    for k in range(s.n_listed[None]):
        i = s.listed[k]
        pix = s.proj_pixel[i]
        v, u = pix // W, pix % W
        key = (ti.cast(s.proj_depth[i], ti.i64) << 32) | ti.cast(i, ti.i64)
        if key < imap.key[v, u]:  # plain read first: most lose, and skip the atomic
            ti.atomic_min(imap.key[v, u], key)


@ti.func
def unpack_loop(imap: ti.template(), front_radius: ti.template()):
    """index = the packed key's low half, INT_MAX where no surfel projects; with ``front_radius`` (a field,
    else None) −1 everywhere too, the renderer's clearing before ``gather_front_loop`` writes the winners': a
    parallel loop (a wake-up and join of the worker threads) fewer. (The association's ``assoc`` written here
    too was slower than its own loop: docs/PERFORMANCE.md.)"""
    for v, u in imap.index:
        key = imap.key[v, u]
        imap.index[v, u] = ti.select(key == ti.i64(INT64_MAX), INT_MAX, ti.cast(key & ti.i64(0xFFFFFFFF), ti.i32))
        if ti.static(given(front_radius)):
            front_radius[v, u] = -1.0


@ti.kernel
def build_listed(s: ti.template(), n: ti.i32, imap: ti.template(), with_index: ti.template()):
    """``build_loops`` in one launch."""
    build_loops(s, n, imap, with_index, None)


@ti.func
def build_loops(s: ti.template(), n, imap: ti.template(), with_index: ti.template(), front_radius: ti.template()):
    """``gather_listed``, then with ``with_index`` ``clear_loop``, ``nearest_listed`` and ``claim_listed`` (on the
    CPU ``gather_listed`` with ``clear_loop``'s work in its copy loop, ``nearest_packed`` and ``unpack_loop``, with
    ``front_radius``: None, or a field the caller clears itself off the CPU): their loops one after the other
    (each reads what the one before wrote, ``n_listed`` included)."""
    if ti.static(with_index and imap.packed_keys):
        gather_listed(s, n, imap)  # with clear_loop's work
        nearest_packed(s, imap)
        unpack_loop(imap, front_radius)
    else:
        gather_listed(s, n, None)
        if ti.static(with_index):
            clear_loop(imap)
            nearest_listed(s, imap)
            claim_listed(s, imap)


def build(s, n: int, imap: IndexMap, with_index: bool = True) -> None:
    """After a projection of the first ``n`` surfels of arrays ``s``: list the surfels it kept in index
    order and, with ``with_index``, clear ``imap`` and fill it from them, in one launch."""
    build_listed(s, n, imap, bool(with_index))
