"""The surfels splatted into a sparse signed-distance grid: the kernel behind ``ti_fusion.mapping.mesh``.

Each confirmed surfel writes, into every voxel centre within its lateral reach ``R`` (across its normal) and
within ``band`` along its normal, the signed distance of that centre to its plane, ``d = n·(x − p)``
(positive in front of the surface), with the weight ``w·exp(−2 l²/R²)`` (``w`` its confidence, ``l`` the
centre's distance from the normal line through ``p``), and its colour with the same weight. The weighted
mean of those plane distances is an implicit moving-least-squares surface (Kolluri 2005) of the surfels,
whose zero level is the mesh; a voxel no surfel reaches keeps weight 0 and no surface is made there.

Voxels live in blocks of ``BLOCK_EDGE``³; only the blocks the surfels reach exist (their packed keys,
sorted, found by binary search), so memory grows with the surface, not with the bounding box. Voxel
(i, j, k) of the grid has its centre at (i, j, k)·voxel in the world; block keys pack the block's
coordinates relative to ``origin`` into 10 bits each. Sums are 32-bit float atomics, so that Vulkan runs
the kernel too; the order of the additions, and so the last bits, may differ between runs.
"""

import taichi as ti

from ti_fusion.kernels.common import depth_sigma

BLOCK_EDGE = 8                       # voxels along each edge of a block
BLOCK_VOXELS = BLOCK_EDGE ** 3
KEY_BITS = 10                        # bits per axis of a packed block key: 1024 blocks per axis at most
KEY_SPAN = 1 << KEY_BITS

Vec3Array = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
FloatArray = ti.types.ndarray(dtype=ti.f32, ndim=1)
IntArray = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def find_block(keys: ti.template(), n_blocks: ti.i32, key: ti.i32) -> ti.i32:
    """Index of ``key`` in the sorted ``keys[:n_blocks]``, or −1."""
    lo, hi = 0, n_blocks
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    found = -1
    if lo < n_blocks and keys[lo] == key:
        found = lo
    return found


@ti.kernel
def splat(position: Vec3Array, normal: Vec3Array, color: Vec3Array, weight: FloatArray, reach: FloatArray,
          n: ti.i32, keys: IntArray, n_blocks: ti.i32, origin: ti.math.ivec3, voxel: ti.f32, band: ti.f32,
          sdf: FloatArray, wsum: FloatArray, rgb: Vec3Array):
    """Add surfels ``[0, n)`` into the blocks ``keys[:n_blocks]`` (``sdf`` holds Σ w·d, ``wsum`` Σ w, ``rgb``
    Σ w·colour, at ``block·BLOCK_VOXELS + (lx·E + ly)·E + lz``). A voxel whose block is not listed is skipped:
    the caller lists every block the surfels reach."""
    for i in range(n):
        p = position[i]
        nrm = normal[i]
        r = reach[i]
        # the disc's voxels: a cylinder of radius r and half-height band about the normal; walk the two axes
        # across the normal's largest component over the cylinder's bounding box, and along that axis only
        # the voxels within band of the plane (a few per column instead of the whole box)
        a = 2
        if ti.abs(nrm.x) >= ti.abs(nrm.y) and ti.abs(nrm.x) >= ti.abs(nrm.z):
            a = 0
        elif ti.abs(nrm.y) >= ti.abs(nrm.z):
            a = 1
        o1 = (a + 1) % 3
        o2 = (a + 2) % 3
        half = cylinder_half_extent(nrm, r, band)
        lo = ti.cast(ti.ceil((p - half) / voxel), ti.i32)
        hi = ti.cast(ti.floor((p + half) / voxel), ti.i32)
        na = pick(nrm, a)
        for i1 in range(pick(lo, o1), pick(hi, o1) + 1):
            for i2 in range(pick(lo, o2), pick(hi, o2) + 1):
                s = pick(nrm, o1) * (i1 * voxel - pick(p, o1)) + pick(nrm, o2) * (i2 * voxel - pick(p, o2))
                centre = pick(p, a) - s / na  # where this column meets the plane
                hw = band / ti.abs(na)
                for ia in range(ti.cast(ti.ceil((centre - hw) / voxel), ti.i32),
                                ti.cast(ti.floor((centre + hw) / voxel), ti.i32) + 1):
                    g = ti.math.ivec3(0)
                    for k in ti.static(range(3)):
                        g[k] = i1 if k == o1 else (i2 if k == o2 else ia)
                    add_voxel(g, p, nrm, color[i], weight[i], r, voxel, band, keys, n_blocks, origin, sdf, wsum, rgb)


@ti.func
def pick(v, k: ti.i32):
    """Component ``k`` of a 3-vector (a run-time index), in the vector's own type."""
    out = v.z
    if k == 0:
        out = v.x
    elif k == 1:
        out = v.y
    return out


@ti.func
def cylinder_half_extent(nrm, r: ti.f32, band: ti.f32):
    """Half the axis-aligned box of a cylinder of radius r and half-height band about the unit axis nrm."""
    return r * ti.sqrt(ti.max(1.0 - nrm * nrm, 0.0)) + band * ti.abs(nrm)


@ti.func
def add_voxel(g, p, nrm, c, w: ti.f32, r: ti.f32, voxel: ti.f32, band: ti.f32, keys: ti.template(),
              n_blocks: ti.i32, origin, sdf: ti.template(), wsum: ti.template(), rgb: ti.template()):
    x = ti.cast(g, ti.f32) * voxel
    off = x - p
    d = nrm.dot(off)
    l2 = off.dot(off) - d * d
    if ti.abs(d) <= band and l2 <= r * r:
        bx = (g.x >> 3) - origin.x  # floor division by BLOCK_EDGE, negatives included
        by = (g.y >> 3) - origin.y
        bz = (g.z >> 3) - origin.z
        b = -1
        if 0 <= bx < KEY_SPAN and 0 <= by < KEY_SPAN and 0 <= bz < KEY_SPAN:
            b = find_block(keys, n_blocks, (bx << (2 * KEY_BITS)) | (by << KEY_BITS) | bz)
        if b >= 0:
            slot = b * BLOCK_VOXELS + ((g.x & 7) * BLOCK_EDGE + (g.y & 7)) * BLOCK_EDGE + (g.z & 7)
            wt = w * ti.exp(-2.0 * ti.max(l2, 0.0) / (r * r))
            ti.atomic_add(sdf[slot], wt * d)
            ti.atomic_add(wsum[slot], wt)
            ti.atomic_add(rgb[slot], wt * c)


# --- the depth frames re-integrated (mesh.method = "depth"): a truncated signed distance per voxel ---------------
#
# Each valid pixel walks its ray from depth − trunc to depth + trunc in steps of ``step`` (along z) and writes, into
# every voxel whose centre is nearest to a sample, the projective signed distance d − z_c (the pixel's depth minus
# the voxel centre's depth in the camera; positive in front of the surface) where |d − z_c| ≤ trunc, with weight 1,
# and the pixel's colour. A voxel seen by many pixels of a frame gets many samples: near views, whose pixels are
# finer and whose depth is less noisy, weigh more. Blocks are looked up in ``table``, a dense int32 array over the
# frame's box of blocks (block − lo), holding each block's slot in the pool or −1; ``touch_blocks`` marks that box's
# blocks the samples reach, so that the caller can give them slots before ``integrate_depth`` runs.

DepthArray = ti.types.ndarray(dtype=ti.f32, ndim=2)
ColorArray = ti.types.ndarray(dtype=ti.math.vec3, ndim=2)
TableArray = ti.types.ndarray(dtype=ti.i32, ndim=3)
Mat3 = ti.types.matrix(3, 3, ti.f32)


@ti.func
def ray_direction(u: ti.i32, v: ti.i32, K: ti.math.vec4, rot):
    """Pixel (u, v)'s ray in the world, per metre of depth (z = 1 in the camera)."""
    return rot @ ti.math.vec3((u - K[2]) / K[0], (v - K[3]) / K[1], 1.0)


@ti.func
def nearest_voxel(x, voxel: ti.f32):
    """The voxel (grid coordinates) whose centre is nearest to the world point x."""
    return ti.cast(ti.floor(x / voxel + 0.5), ti.i32)


@ti.func
def table_block(g, lo, table: ti.template()):
    """Voxel g's block relative to ``lo``, or (−1, −1, −1) outside the table."""
    b = ti.math.ivec3((g.x >> 3) - lo.x, (g.y >> 3) - lo.y, (g.z >> 3) - lo.z)
    out = ti.math.ivec3(-1)
    if 0 <= b.x < table.shape[0] and 0 <= b.y < table.shape[1] and 0 <= b.z < table.shape[2]:
        out = b
    return out


@ti.kernel
def touch_blocks(depth: DepthArray, K: ti.math.vec4, rot: Mat3, trans: ti.math.vec3, voxel: ti.f32, trunc: ti.f32,
                 step: ti.f32, lo: ti.math.ivec3, table: TableArray):
    """Set ``table[block − lo]`` to 1 for every block in the box of the blocks of a pixel's first and last sample
    (its samples' blocks lie in that box: the nearest voxel moves monotonically along each axis), others left."""
    n = ti.cast(ti.floor(2.0 * trunc / step), ti.i32)
    for v, u in depth:
        d = depth[v, u]
        if d > 0:
            r = ray_direction(u, v, K, rot)
            a = nearest_voxel(trans + r * ti.max(d - trunc, 0.0), voxel) >> 3
            b = nearest_voxel(trans + r * (d - trunc + n * step), voxel) >> 3
            for x, y, z in ti.ndrange((ti.min(a.x, b.x), ti.max(a.x, b.x) + 1), (ti.min(a.y, b.y), ti.max(a.y, b.y) + 1),
                                      (ti.min(a.z, b.z), ti.max(a.z, b.z) + 1)):
                c = ti.math.ivec3(x, y, z) - lo
                if 0 <= c.x < table.shape[0] and 0 <= c.y < table.shape[1] and 0 <= c.z < table.shape[2]:
                    table[c] = 1


@ti.kernel
def integrate_depth(depth: DepthArray, color: ColorArray, has_color: ti.i32, K: ti.math.vec4, rot: Mat3,
                    trans: ti.math.vec3, voxel: ti.f32, trunc: ti.f32, step: ti.f32, lo: ti.math.ivec3,
                    table: TableArray, sdf: FloatArray, wsum: FloatArray, rgb: Vec3Array):
    """Add one frame's samples: ``sdf`` Σ w·(d − z_c), ``wsum`` Σ w, ``rgb`` Σ w·colour at
    ``slot·BLOCK_VOXELS + (lx·E + ly)·E + lz``; a voxel whose block has no slot (−1) is skipped."""
    n = ti.cast(ti.floor(2.0 * trunc / step), ti.i32) + 1
    axis = ti.math.vec3(rot[0, 2], rot[1, 2], rot[2, 2])  # the camera's z axis in the world
    for v, u in depth:
        d = depth[v, u]
        if d > 0:
            c = ti.math.vec3(200.0)
            if has_color:
                c = color[v, u]
            r = ray_direction(u, v, K, rot)
            prev = ti.math.ivec3(-(1 << 30))
            for s in range(n):
                z = d - trunc + s * step
                g = nearest_voxel(trans + r * z, voxel)
                if z > 0 and (g != prev).any():
                    prev = g  # a ray stays in a voxel for consecutive samples only: write each voxel once
                    sd = d - axis.dot(ti.cast(g, ti.f32) * voxel - trans)
                    b = table_block(g, lo, table)
                    if ti.abs(sd) <= trunc and b.x >= 0:
                        slot = table[b]
                        if slot >= 0:
                            i = slot * BLOCK_VOXELS + ((g.x & 7) * BLOCK_EDGE + (g.y & 7)) * BLOCK_EDGE + (g.z & 7)
                            ti.atomic_add(sdf[i], sd)
                            ti.atomic_add(wsum[i], 1.0)
                            ti.atomic_add(rgb[i], c)


BlockArray = ti.types.ndarray(dtype=ti.math.ivec3, ndim=1)


@ti.kernel
def carve_depth(depth: DepthArray, K: ti.math.vec4, rot: Mat3, trans: ti.math.vec3, voxel: ti.f32, trunc: ti.f32,
                sigmas: ti.f32, band: ti.f32, blocks: BlockArray, slots: IntArray, n_blocks: ti.i32,
                free: FloatArray, near: FloatArray):
    """Count, for every voxel of the given blocks (absolute block coordinates, their pool slots), the frame if it
    saw through it: ``free`` += 1 where all four pixels around the voxel centre's projection have depth and the
    nearest of them lies beyond it by more than ``trunc`` + ``sigmas``·σ(depth); ``near`` += 1 where the nearest
    pixel's depth is within ``band`` of it (the frame saw a surface there)."""
    for i, k in ti.ndrange(n_blocks, BLOCK_VOXELS):
        g = blocks[i] * BLOCK_EDGE + ti.math.ivec3(k // (BLOCK_EDGE * BLOCK_EDGE), (k // BLOCK_EDGE) % BLOCK_EDGE,
                                                   k % BLOCK_EDGE)
        p = rot.transpose() @ (ti.cast(g, ti.f32) * voxel - trans)  # the voxel centre in the camera
        if p.z > 0:
            u = K[0] * p.x / p.z + K[2]
            v = K[1] * p.y / p.z + K[3]
            u0 = ti.cast(ti.floor(u), ti.i32)
            v0 = ti.cast(ti.floor(v), ti.i32)
            if 0 <= u0 and u0 + 1 < depth.shape[1] and 0 <= v0 and v0 + 1 < depth.shape[0]:
                a, b = depth[v0, u0], depth[v0, u0 + 1]
                c, e = depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]
                j = slots[i] * BLOCK_VOXELS + k
                if ti.min(a, b, c, e) > 0:
                    nearest = ti.min(a, b, c, e)
                    if nearest - p.z > trunc + sigmas * depth_sigma(nearest, ti.f32):
                        free[j] += 1.0  # one thread per voxel: no other thread writes it
                dn = depth[ti.cast(ti.floor(v + 0.5), ti.i32), ti.cast(ti.floor(u + 0.5), ti.i32)]
                if dn > 0 and ti.abs(dn - p.z) <= band:
                    near[j] += 1.0
