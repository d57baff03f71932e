"""Ray casting of a small analytic scene: depth, colour and primitive labels from a camera pose.

The scene is a table of primitives (one float32 row each, columns below): planes (the room's walls, seen
from their front side only), boxes rotated about the vertical z axis, spheres and vertical capped
cylinders. Each row also carries its material: a procedural texture (checker, random tiles, bricks,
plaid or blobs, plus fine value-noise detail) mixing two colours, shaded Lambert-style with one point
light, a sky term and ambient, so colours depend on the geometry and not on the viewpoint.

Rays go through pixel centres exactly as ``Intrinsics`` back-projects them, so with noise off a depth
pixel back-projects onto the surface it hit. With noise on, the depth gets a Kinect-like sensor model:
axial Gaussian noise of ``ti_fusion.sensor``'s σ(z) (Nguyen et al. 2012), disparity quantised to
1/subpixel pixel (of a 640-pixel-wide sensor) for a projector baseline, and drop-outs outside [min_range, max_range] and at grazing
angles. The noise comes from an integer hash of (seed, full-resolution pixel, channel), so a frame is
the same for a seed on every backend, to float rounding, and a subsampled render equals the subsampled
full render. Float rounding depends on the compiled code (Taichi compiles with fast math), so a change
to this kernel may move a few pixels of a frame by one grey level or one disparity step.
"""

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics
from ti_fusion.kernels.common import depth_sigma

# Primitive kinds.
PLANE, BOX, SPHERE, CYLINDER = 0, 1, 2, 3
# Texture patterns.
CHECKER, TILES, BRICKS, PLAID, BLOBS = 0, 1, 2, 3, 4

# Columns of a primitive row.
KIND = 0
CENTER = 1    # 3: box/sphere/cylinder centre; a point on a plane
HALF = 4      # 3: box half extents; sphere (r, r, r); cylinder (r, r, half height)
YAW = 7       # 2: (cos, sin) of the rotation about z (boxes, cylinders' texture)
NORMAL = 9    # 3: plane normal (pointing into the room)
PATTERN = 12
SCALE = 13    # metres: texture cell size along u
ASPECT = 14   # cell size along v = SCALE · ASPECT
DETAIL = 15   # contrast of the fine value-noise detail
COLOR_A = 16  # 3: RGB in [0, 1]
COLOR_B = 19  # 3
SALT = 22     # per-primitive randomisation of its texture
BOUND = 23    # radius of a sphere about CENTER enclosing the primitive; < 0 for planes (unbounded)
NUM_COLUMNS = 24

# Columns of a primitive's row of ``seen``: what depends on the camera position alone, once per frame.
REL = 0         # 3: camera position − CENTER
REL_SQ = 3      # |camera position − CENTER|²
PLANE_DIST = 4  # planes: (point − camera position) · normal
LOCAL = 5       # 3: boxes: camera position − CENTER in the box's own axes
NUM_SEEN = 8

T_MIN = 1e-4
LANES = 8  # pixels per vector in the kernel's second pass
TILE = 16  # pixels: each tile of the image tests only the primitives that may cover it
NO_HIT = 1e30
MORTAR = 0.015  # metres: width of the joints in the bricks pattern

LIGHT = (0.4, -0.3, 2.45)  # point light near the ceiling (world, z up)
AMBIENT = 0.28
DIFFUSE = 1.1
SKY = 0.22


@dataclass(frozen=True)
class SensorModel:
    """Kinect-like depth sensor: drop-outs, axial noise, disparity quantisation, colour noise."""

    min_range: float = 0.4     # metres
    max_range: float = 4.0     # metres
    grazing_deg: float = 80.0  # drop depth where the ray is further than this from the normal
    baseline: float = 0.075    # metres, projector to camera
    subpixel: float = 8.0      # disparity quantised to 1/subpixel pixel ...
    sensor_width: int = 640    # ... of a sensor this many pixels wide with the image's field of view
    color_sigma: float = 2.0   # grey levels per channel
    depth_noise_scale: float = 1.0  # the axial noise is this × ti_fusion.sensor's σ(z)


# -- hashing: uniform and Gaussian numbers from integers, identical on every backend ------------------
@ti.func
def hash_u32(x):
    x = ti.cast(x, ti.u32)
    x ^= x >> 16
    x *= ti.u32(0x7FEB352D)
    x ^= x >> 15
    x *= ti.u32(0x846CA68B)
    x ^= x >> 16
    return x


@ti.func
def to_unit(h):
    """u32 → [0, 1) with 24 bits."""
    return ti.cast(h >> 8, ti.f32) * (1.0 / 16777216.0)


@ti.func
def cell_random(i, j, salt):
    """Uniform [0, 1) for an integer lattice cell (offset keeps the small negative indices positive)."""
    h = hash_u32(ti.cast(i + 65536, ti.u32) * ti.u32(0x8DA6B343) ^ ti.cast(j + 65536, ti.u32) * ti.u32(0xD8163841)
                 ^ ti.cast(salt, ti.u32) * ti.u32(0xCB1AB31F))
    return to_unit(h)


@ti.func
def gaussian(key, seed):
    """Standard normal (Box–Muller) for an integer key and a seed."""
    h1 = hash_u32(hash_u32(key) ^ seed)
    h2 = hash_u32(h1 ^ ti.u32(0x9E3779B9))
    u1 = (ti.cast(h1 >> 8, ti.f32) + 1.0) * (1.0 / 16777216.0)
    u2 = to_unit(h2)
    return ti.sqrt(-2.0 * log_unit(u1)) * cos_turns(u2)


@ti.func
def log_unit(x):
    """ln x for x in (0, 1], to about one float32 ulp (Cephes' logf). Inline arithmetic rather than a call
    to the C library, so that LLVM can put LANES of it in one vector."""
    bits = ti.bit_cast(x, ti.i32)
    e = ti.cast(((bits >> 23) & 255) - 127, ti.f32)
    m = ti.bit_cast((bits & 0x7FFFFF) | 0x3F800000, ti.f32)  # x = m 2^e, m in [1, 2)
    high = m > 1.41421356
    m = ti.select(high, m * 0.5, m)
    e = ti.select(high, e + 1.0, e)
    f = m - 1.0  # in [√½ − 1, √2 − 1)
    z = f * f
    p = ti.abs(f) * 0.0 + 7.0376836292e-2  # shaped as f: a scalar or LANES of them
    for c in ti.static((-1.1514610310e-1, 1.1676998740e-1, -1.2420140846e-1, 1.4249322787e-1,
                        -1.6668057665e-1, 2.0000714765e-1, -2.4999993993e-1, 3.3333331174e-1)):
        p = p * f + c
    return f + (z * f * p - 0.5 * z) + e * 0.693147180559945


@ti.func
def cos_turns(u):
    """cos(2πu) for u in [0, 1], to 2e-7 (Taylor's series to x¹², folded to x in [0, π/2]): as close as cosf of
    the float32 product 2πu."""
    a = ti.abs(u - ti.round(u))  # cos(2πu) is even and of period 1: a in [0, ½]
    flip = a > 0.25
    x = 2.0 * math.pi * ti.select(flip, 0.5 - a, a)
    x2 = x * x
    c = x2 * 0.0 + 1.0 / 479001600.0
    for k in ti.static((-1.0 / 3628800.0, 1.0 / 40320.0, -1.0 / 720.0, 1.0 / 24.0, -0.5, 1.0)):
        c = c * x2 + k
    return ti.select(flip, -c, c)


# -- geometry ------------------------------------------------------------------------------------------
@ti.func
def row3(prims: ti.template(), k, col):
    return ti.Vector([prims[k, col], prims[k, col + 1], prims[k, col + 2]])


@ti.func
def to_local(w, c, s):
    """World direction → frame rotated by yaw about z (cos c, sin s)."""
    return ti.Vector([c * w.x + s * w.y, -s * w.x + c * w.y, w.z])


@ti.func
def to_world(l, c, s):
    return ti.Vector([c * l.x - s * l.y, s * l.x + c * l.y, l.z])


@ti.func
def intersect(prims: ti.template(), seen: ti.template(), k, d):
    """Distance along the unit ray d from the camera to primitive k's front surface; NO_HIT when missed.
    ``seen`` holds what depends on the camera position alone (``SceneRenderer._seen_from``)."""
    kind = ti.cast(prims[k, KIND], ti.i32)
    oc = ti.Vector([seen[k, REL], seen[k, REL + 1], seen[k, REL + 2]])  # camera − centre
    t = NO_HIT
    if kind == PLANE:
        n = row3(prims, k, NORMAL)
        denom = d.dot(n)
        if denom < -1e-8:
            s = seen[k, PLANE_DIST] / denom
            if s > T_MIN:
                t = s
    elif kind == BOX:
        cs, sn = prims[k, YAW], prims[k, YAW + 1]
        h = row3(prims, k, HALF)
        ol = ti.Vector([seen[k, LOCAL], seen[k, LOCAL + 1], seen[k, LOCAL + 2]])
        dl = to_local(d, cs, sn)
        t_near = -NO_HIT
        t_far = NO_HIT
        for i in ti.static(range(3)):
            di = dl[i]
            if ti.abs(di) < 1e-12:
                di = 1e-12
            t1 = (-h[i] - ol[i]) / di
            t2 = (h[i] - ol[i]) / di
            t_near = ti.max(t_near, ti.min(t1, t2))
            t_far = ti.min(t_far, ti.max(t1, t2))
        if t_near <= t_far and t_near > T_MIN:
            t = t_near
    elif kind == SPHERE:
        r = prims[k, HALF]
        b = oc.dot(d)
        perp = oc - b * d  # closest approach: better conditioned than b² − |oc|² + r²
        disc = r * r - perp.dot(perp)
        if disc >= 0:
            s = -b - ti.sqrt(disc)
            if s > T_MIN:
                t = s
    elif kind == CYLINDER:
        r = prims[k, HALF]
        hz = prims[k, HALF + 2]
        a = d.x * d.x + d.y * d.y
        if a > 1e-12:  # side wall
            b = oc.x * d.x + oc.y * d.y
            px = oc.x - b / a * d.x
            py = oc.y - b / a * d.y
            disc = r * r - (px * px + py * py)
            if disc >= 0:
                s = (-b - ti.sqrt(disc * a)) / a
                if s > T_MIN and ti.abs(oc.z + s * d.z) <= hz:
                    t = s
        if ti.abs(d.z) > 1e-12:  # the cap facing the ray origin
            zc = hz if oc.z > 0 else -hz
            s = (zc - oc.z) / d.z
            qx = oc.x + s * d.x
            qy = oc.y + s * d.y
            if s > T_MIN and qx * qx + qy * qy <= r * r and s < t:
                t = s
    return t


@ti.func
def surface(prims: ti.template(), k, p):
    """World normal at the hit point p of primitive k and the point's texture coordinates (metres)."""
    kind = ti.cast(prims[k, KIND], ti.i32)
    c = row3(prims, k, CENTER)
    cs, sn = prims[k, YAW], prims[k, YAW + 1]
    n = ti.Vector([0.0, 0.0, 1.0])
    uv = ti.Vector([0.0, 0.0])
    if kind == PLANE:
        n = row3(prims, k, NORMAL)
        a = ti.abs(n)
        if a.x >= a.y and a.x >= a.z:
            uv = ti.Vector([p.y, p.z])
        elif a.y >= a.z:
            uv = ti.Vector([p.x, p.z])
        else:
            uv = ti.Vector([p.x, p.y])
    elif kind == BOX:
        h = row3(prims, k, HALF)
        pl = to_local(p - c, cs, sn)
        q = pl / h
        nl = ti.Vector([0.0, 0.0, 0.0])
        if ti.abs(q.x) >= ti.abs(q.y) and ti.abs(q.x) >= ti.abs(q.z):
            nl.x = 1.0 if q.x > 0 else -1.0
            uv = ti.Vector([pl.y, pl.z + 1.7])
        elif ti.abs(q.y) >= ti.abs(q.z):
            nl.y = 1.0 if q.y > 0 else -1.0
            uv = ti.Vector([pl.x + 3.1, pl.z])
        else:
            nl.z = 1.0 if q.z > 0 else -1.0
            uv = ti.Vector([pl.x, pl.y + 5.3])
        n = to_world(nl, cs, sn)
    elif kind == SPHERE:
        r = prims[k, HALF]
        q = to_local(p - c, cs, sn) / r
        n = (p - c) / r
        n = n / n.norm()
        uv = ti.Vector([ti.atan2(q.y, q.x) * r, ti.acos(ti.min(ti.max(q.z, -1.0), 1.0)) * r])
    elif kind == CYLINDER:
        r = prims[k, HALF]
        hz = prims[k, HALF + 2]
        ql = to_local(p - c, cs, sn)
        rho = ti.sqrt(ql.x * ql.x + ql.y * ql.y)
        if ti.abs(rho - r) <= ti.abs(ti.abs(ql.z) - hz):
            n = ti.Vector([(p.x - c.x) / rho, (p.y - c.y) / rho, 0.0])
            uv = ti.Vector([ti.atan2(ql.y, ql.x) * r, ql.z])
        else:
            n = ti.Vector([0.0, 0.0, 1.0 if ql.z > 0 else -1.0])
            uv = ti.Vector([ql.x + 2.3, ql.y])
    return n, uv


# -- texture -------------------------------------------------------------------------------------------
@ti.func
def fade(wavelength, footprint):
    """1 for structure of ≥ 4 pixels, 0 below 2 pixels: a cheap stand-in for mip-mapping."""
    return ti.min(ti.max(wavelength / footprint * 0.5 - 1.0, 0.0), 1.0)


@ti.func
def value_noise(x, y, salt):
    i = ti.floor(x)
    j = ti.floor(y)
    fx = x - i
    fy = y - j
    ii = ti.cast(i, ti.i32)
    jj = ti.cast(j, ti.i32)
    wx = fx * fx * (3.0 - 2.0 * fx)
    wy = fy * fy * (3.0 - 2.0 * fy)
    a = cell_random(ii, jj, salt)
    b = cell_random(ii + 1, jj, salt)
    c = cell_random(ii, jj + 1, salt)
    e = cell_random(ii + 1, jj + 1, salt)
    return (a + (b - a) * wx) + ((c + (e - c) * wx) - (a + (b - a) * wx)) * wy


@ti.func
def pattern_value(pattern, uv, su, sv, salt, footprint):
    """Mix factor in [0, 1] between the two colours, or −1 on a brick joint."""
    x = uv.x / su
    y = uv.y / sv
    ix = ti.cast(ti.floor(x), ti.i32)
    iy = ti.cast(ti.floor(y), ti.i32)
    m = 0.5
    if pattern == CHECKER:
        m = 0.7 * ti.cast((ix + iy) & 1, ti.f32) + 0.3 * cell_random(ix, iy, salt)
    elif pattern == TILES:
        m = cell_random(ix, iy, salt)
    elif pattern == BRICKS:
        xs = x + 0.5 * ti.cast(iy & 1, ti.f32)
        col = ti.floor(xs)
        if (xs - col) * su < MORTAR or (y - iy) * sv < MORTAR:
            m = -1.0
        else:
            m = 0.1 + 0.9 * cell_random(ti.cast(col, ti.i32), iy, salt)
    elif pattern == PLAID:
        m = 0.5 * (cell_random(ix, 7, salt) + cell_random(13, iy, salt + 1))
    else:  # BLOBS
        n = 0.65 * value_noise(x, y, salt) + 0.35 * value_noise(2.3 * x, 2.3 * y, salt + 1)
        m = ti.min(ti.max((n - 0.3) * 2.5, 0.0), 1.0)
    if m >= 0:  # far away, cells blur into their mean
        m = 0.5 + (m - 0.5) * fade(ti.min(su, sv), footprint)
    return m


@ti.func
def base_albedo(prims: ti.template(), k, uv, footprint):
    """The material's colour at texture coordinates ``uv`` before its fine detail (``detail``)."""
    su = prims[k, SCALE]
    sv = su * prims[k, ASPECT]
    salt = ti.cast(prims[k, SALT], ti.i32)
    m = pattern_value(ti.cast(prims[k, PATTERN], ti.i32), uv, su, sv, salt, footprint)
    a = row3(prims, k, COLOR_A)
    b = row3(prims, k, COLOR_B)
    col = a * 0.3
    if m >= 0:
        col = a + (b - a) * m
    return col


@ti.func
def detail(u, v, lam, footprint, salt):
    """Fine detail: two octaves of value noise below the cell size (``lam`` = half of it), faded where
    smaller than a pixel. Scalars or LANES-vectors alike: the arithmetic is the same on each lane."""
    w0 = fade(lam, footprint)
    n0 = value_noise(u / lam, v / lam, salt + 17)
    lam1 = lam * 0.4
    w1 = fade(lam1, footprint)
    n1 = value_noise(u / lam1, v / lam1, salt + 18)
    return w0 * (n0 - 0.5) + w1 * (n1 - 0.5) * 0.7


@ti.func
def shade(p, n):
    light = ti.Vector(LIGHT)
    to_light = light - p
    dist2 = to_light.dot(to_light)
    ndl = ti.max(n.dot(to_light) / ti.sqrt(dist2), 0.0)
    return AMBIENT + DIFFUSE * ndl / (1.0 + 0.12 * dist2) + SKY * (0.5 + 0.5 * n.z)


# -- the kernel ----------------------------------------------------------------------------------------
# Per pixel, what the first pass (the nearest hit, its surface and base colour) leaves for the second (the
# fine detail, the sensor model and the colour's rounding, LANES pixels at a time).
COS_INC, COL, SCALE_LIT, U, V, LAM, FOOTPRINT, SALT_LIT, CONTRAST, NUM_LIT = 0, 1, 4, 5, 6, 7, 8, 9, 10, 11


@ti.kernel
def render_kernel(
    depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
    color: ti.types.ndarray(dtype=ti.u8, ndim=3),
    label: ti.types.ndarray(dtype=ti.i32, ndim=2),
    prims: ti.types.ndarray(dtype=ti.f32, ndim=2),
    seen: ti.types.ndarray(dtype=ti.f32, ndim=2),
    tile_prims: ti.types.ndarray(dtype=ti.i32, ndim=3),
    tile_count: ti.types.ndarray(dtype=ti.i32, ndim=2),
    rot: ti.types.matrix(3, 3, ti.f32),
    origin: ti.types.vector(3, ti.f32),
    fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
    step: ti.i32, full_width: ti.i32,
    noise: ti.i32, seed: ti.u32,
    min_range: ti.f32, max_range: ti.f32, cos_grazing: ti.f32,
    fx_baseline: ti.f32, subpixel: ti.f32, color_sigma: ti.f32, depth_noise_scale: ti.f32,
):
    """Per pixel: nearest hit → depth (along the optical axis), RGB, label.

    One iteration is one row of one tile: its primitive list is read once, and its TILE pixels go through
    the per-pixel pass into ``lit`` (a stack buffer, lanes contiguous per channel), then through the
    straight-line second pass LANES at a time, which LLVM turns into vector instructions. The groups of
    LANES are a loop rather than unrolled: that halves the kernel's compile time at no cost per frame."""
    H, W = depth.shape
    for v, tx in ti.ndrange(H, (W + TILE - 1) // TILE):
        ty = v // TILE
        u0 = tx * TILE
        n_px = ti.min(TILE, W - u0)
        count = tile_count[ty, tx]
        lit = ti.Matrix.zero(ti.f32, NUM_LIT, TILE)
        zs = ti.Vector.zero(ti.f32, TILE)
        hits = ti.Vector.zero(ti.i32, TILE)
        vi = v * step
        for i in range(n_px):
            ui = (u0 + i) * step  # the full-resolution pixel this one samples
            ray_cam = ti.Vector([(ti.cast(ui, ti.f32) - cx) / fx, (ti.cast(vi, ti.f32) - cy) / fy, 1.0])
            inv_len = 1.0 / ray_cam.norm()
            d = (rot @ ray_cam) * inv_len
            best = NO_HIT
            hit = -1
            for j in range(count):
                k = tile_prims[ty, tx, j]
                bound = prims[k, BOUND]
                if bound >= 0:  # cheap rejection by the bounding sphere: off the ray, or behind the best hit
                    b = -(seen[k, REL] * d.x + seen[k, REL + 1] * d.y + seen[k, REL + 2] * d.z)
                    if seen[k, REL_SQ] - b * b > bound * bound or b - bound > best:
                        continue
                t = intersect(prims, seen, k, d)
                if t < best:
                    best = t
                    hit = k
            lit[LAM, i] = 1.0  # keeps the detail pass finite where nothing is hit
            lit[FOOTPRINT, i] = 1.0
            if hit >= 0:
                p = origin + best * d
                n, uv = surface(prims, hit, p)
                z = best * inv_len
                footprint = z / fx / ti.max(ti.abs(n.dot(d)), 0.25)  # metres per full-resolution pixel
                col = base_albedo(prims, hit, uv, footprint)
                su = prims[hit, SCALE]
                zs[i] = z
                lit[COS_INC, i] = -n.dot(d)
                for c in ti.static(range(3)):
                    lit[COL + c, i] = col[c]
                lit[SCALE_LIT, i] = shade(p, n) * 255.0
                lit[U, i] = uv.x
                lit[V, i] = uv.y
                lit[LAM, i] = 0.5 * ti.min(su, su * prims[hit, ASPECT])
                lit[FOOTPRINT, i] = footprint
                lit[SALT_LIT, i] = prims[hit, SALT]
                lit[CONTRAST, i] = prims[hit, DETAIL] * 1.8
            hits[i] = hit
            label[v, u0 + i] = hit
        for g in range((n_px + LANES - 1) // LANES):
            z = ti.Vector([zs[g * LANES + l] for l in ti.static(range(LANES))])
            hit = ti.Vector([hits[g * LANES + l] for l in ti.static(range(LANES))])
            ch = [ti.Vector([lit[c, g * LANES + l] for l in ti.static(range(LANES))])
                  for c in ti.static(range(NUM_LIT))]
            salt = ti.cast(ch[SALT_LIT], ti.i32)
            fine = detail(ch[U], ch[V], ch[LAM], ch[FOOTPRINT], salt)
            gain = (1.0 + ch[CONTRAST] * fine) * ch[SCALE_LIT]
            rgb = [ch[COL + c] * gain for c in ti.static(range(3))]
            px = ti.Vector([ti.cast((vi * full_width + (u0 + g * LANES + l) * step) * 4, ti.u32)
                            for l in ti.static(range(LANES))])
            if noise != 0:
                zn = z + depth_noise_scale * depth_sigma(z, ti.f32) * gaussian(px, seed)
                disparity = ti.round(fx_baseline / zn * subpixel) / subpixel
                quantised = ti.select(disparity > 0, fx_baseline / disparity, 0.0)
                dropped = (z < min_range) | (z > max_range) | (ch[COS_INC] < cos_grazing)
                z = ti.select(hit >= 0, ti.select(dropped, 0.0, quantised), z)
                # colour: a cheap near-Gaussian (sum of four uniform bytes of one hash, unit variance)
                for c in ti.static(range(3)):
                    h = hash_u32(hash_u32(px + ti.u32(c + 1)) ^ seed)
                    bytes_sum = ti.cast((h & 255) + ((h >> 8) & 255) + ((h >> 16) & 255) + (h >> 24), ti.f32)
                    rgb[c] += color_sigma * (bytes_sum - 510.0) * (1.7320508 / 255.0)
            q = [ti.cast(ti.min(ti.max(ti.round(rgb[c]), 0.0), 255.0), ti.u8) for c in ti.static(range(3))]
            for l in ti.static(range(LANES)):
                if g * LANES + l < n_px:
                    depth[v, u0 + g * LANES + l] = z[l]
                    for c in ti.static(range(3)):
                        color[v, u0 + g * LANES + l, c] = q[c][l]


class SceneRenderer:
    """Renders a primitive table (rows as above) from any camera pose."""

    def __init__(self, table: np.ndarray):
        table = np.ascontiguousarray(table, dtype=np.float32)
        if table.ndim != 2 or table.shape[1] != NUM_COLUMNS:
            raise ValueError(f"primitive table must be P×{NUM_COLUMNS}, got {table.shape}")
        self.table = table

    def _seen_from(self, o: np.ndarray) -> np.ndarray:
        """P × NUM_SEEN float32: the columns of ``seen`` for a camera at ``o`` (computed in float64)."""
        table = self.table.astype(np.float64)
        rel = np.asarray(o, np.float64) - table[:, CENTER:CENTER + 3]
        c, s = table[:, YAW], table[:, YAW + 1]
        seen = np.zeros((len(table), NUM_SEEN))
        seen[:, REL:REL + 3] = rel
        seen[:, REL_SQ] = (rel * rel).sum(1)
        seen[:, PLANE_DIST] = -(rel * table[:, NORMAL:NORMAL + 3]).sum(1)
        seen[:, LOCAL:LOCAL + 3] = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                                             rel[:, 2]], 1)
        return seen.astype(np.float32)

    def _tile_lists(self, pose: np.ndarray, K: Intrinsics, step: int, H: int, W: int):
        """Per TILE×TILE tile, the primitives that may be the nearest hit of one of its pixels: (lists
        TH×TW×P, counts TH×TW), int32.

        Ray directions are affine in the pixel, so a tile's rays are the positive combinations of its four
        corner rays, and a test that is linear in the ray direction holds for every ray of the tile when it
        holds for the corners. A bounded primitive is kept where its bounding sphere meets the tile's
        frustum (the four side planes through the camera). A plane is kept where some corner ray points at
        its front side, unless another plane is nearer along every ray of the tile. Both tests keep a
        margin far above float32 rounding, so the kernel finds the same nearest hit as with every
        primitive in every list. Each list holds planes first, then the others near to far, so an early
        hit lets the farther ones be skipped by the bounding test.
        """
        table = self.table.astype(np.float64)
        R, o = pose[:3, :3], pose[:3, 3]
        TH, TW = -(-H // TILE), -(-W // TILE)
        P = len(table)
        bound = table[:, BOUND]
        centers = table[:, CENTER:CENTER + 3]
        visible = np.zeros((TH, TW, P), bool)
        # corner pixels of every tile, as full-resolution pixel coordinates, and their camera-ray slopes
        us = np.stack([np.arange(TW) * TILE, np.minimum(np.arange(TW) * TILE + TILE - 1, W - 1)], 1) * step
        vs = np.stack([np.arange(TH) * TILE, np.minimum(np.arange(TH) * TILE + TILE - 1, H - 1)], 1) * step
        ax = (us - K.cx) / K.fx  # TW×2: x/z of the tile's left and right rays
        ay = (vs - K.cy) / K.fy  # TH×2: y/z of its top and bottom rays
        nx, ny = np.hypot(1, ax), np.hypot(1, ay)  # lengths of the side planes' normals (1, 0, −a), (0, 1, −a)
        cam = (centers - o) @ R  # centres in the camera frame
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        planes = np.flatnonzero(bound < 0)
        for k in planes:
            n_cam = R.T @ table[k, NORMAL:NORMAL + 3]
            lowest = (ay * n_cam[1]).min(1)[:, None] + (ax * n_cam[0]).min(1)[None, :] + n_cam[2]
            visible[:, :, k] = lowest < 1e-6
        bounded = np.flatnonzero(bound >= 0)
        r = bound[bounded] * 1.001 + 1e-3
        x, y, z = (c[:, None] for c in cam[bounded].T)
        # The sphere meets a tile's frustum only if it is not wholly outside one of its side planes (x = a z
        # with a the left or right slope, y = a z likewise), at distances (x − a z)/√(1 + a²).
        cols = ((x - ax[:, 0] * z) / nx[:, 0] >= -r[:, None]) & ((ax[:, 1] * z - x) / nx[:, 1] >= -r[:, None])
        rows = ((y - ay[:, 0] * z) / ny[:, 0] >= -r[:, None]) & ((ay[:, 1] * z - y) / ny[:, 1] >= -r[:, None])
        keep = rows[:, :, None] & cols[:, None, :]  # B×TH×TW
        # In front of the camera, also only the tiles its bounding cube projects to.
        front = (z[:, 0] - r > 1e-3)
        corners = cam[bounded][:, None, :] + r[:, None, None] * signs  # B×8×3
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K.fx * corners[..., 0] / corners[..., 2] + K.cx
            v = K.fy * corners[..., 1] / corners[..., 2] + K.cy
        i0, i1 = np.maximum(np.ceil(u.min(1) / step), 0), np.minimum(np.floor(u.max(1) / step), W - 1)
        j0, j1 = np.maximum(np.ceil(v.min(1) / step), 0), np.minimum(np.floor(v.max(1) / step), H - 1)
        tx, ty = np.arange(TW), np.arange(TH)
        in_x = (tx >= (i0 // TILE)[:, None]) & (tx <= (i1 // TILE)[:, None]) & (i0 <= i1)[:, None]
        in_y = (ty >= (j0 // TILE)[:, None]) & (ty <= (j1 // TILE)[:, None]) & (j0 <= j1)[:, None]
        keep &= ~front[:, None, None] | (in_y[:, :, None] & in_x[:, None, :])
        keep &= (z[:, 0] + r > 0)[:, None, None]  # wholly behind the camera: nowhere
        visible[:, :, bounded] = keep.transpose(1, 2, 0)
        if len(planes) > 1:
            visible[:, :, planes] &= ~self._hidden_planes(table[planes], R, o, ax, ay)
        dist = np.linalg.norm(centers - o, axis=1) - bound
        dist[bound < 0] = -np.inf
        order = np.argsort(dist, kind="stable")
        ranked = visible[:, :, order]
        lists = order[np.argsort(~ranked, axis=-1, kind="stable")]
        return np.ascontiguousarray(lists, dtype=np.int32), ranked.sum(-1).astype(np.int32)

    @staticmethod
    def _hidden_planes(rows: np.ndarray, R: np.ndarray, o: np.ndarray, ax: np.ndarray, ay: np.ndarray):
        """TH×TW×Q: whether plane g of the Q ``rows`` lies, along every ray of the tile, more than 0.1%
        beyond another plane f that every ray of the tile hits.

        Along a ray d (camera frame, any length), plane p is at t_p = s_p / (d·n_p) with s_p = (c_p − o)·n_p
        < 0 in front of the camera. For d·n_f < 0, t_g > (1 + m) t_f or no hit on g at all is
        |s_g| (d·n_f) − (1 + m) |s_f| (d·n_g) < 0: linear in d, so the four corner rays decide it.
        """
        margin = 1e-3
        n_cam = rows[:, NORMAL:NORMAL + 3] @ R  # Q×3 normals in the camera frame
        s = np.einsum("qi,qi->q", rows[:, CENTER:CENTER + 3] - o, rows[:, NORMAL:NORMAL + 3])
        # d·n at the four corners of every tile: TH×TW×4×Q
        dn = (ay[:, None, :, None, None] * n_cam[:, 1] + ax[None, :, None, :, None] * n_cam[:, 0]
              + n_cam[:, 2]).reshape(len(ay), len(ax), 4, -1)
        a = np.abs(s)
        # [..., f, g]: every ray of the tile hits f (the camera in front of it), and g lies beyond f
        hits = (dn < -1e-6).all(2) & (s < -T_MIN)
        farther = (a[None, :] * dn[..., :, None] - (1 + margin) * a[:, None] * dn[..., None, :] < 0).all(2)
        farther[..., np.arange(len(rows)), np.arange(len(rows))] = False
        return (hits[..., :, None] & farther).any(-2)

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, step: int = 1,
               sensor: SensorModel | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth float32 H×W metres 0 = invalid, colour uint8 H×W×3 RGB, label int32 H×W, −1 = no hit).

        ``pose`` is camera-to-world (x right, y down, z forward). ``step`` > 1 renders every step-th
        pixel of the ``intrinsics`` image (exactly ``full[::step, ::step]``); ``sensor`` None = no noise.
        """
        H = (intrinsics.height + step - 1) // step
        W = (intrinsics.width + step - 1) // step
        depth = np.empty((H, W), np.float32)
        color = np.empty((H, W, 3), np.uint8)
        label = np.empty((H, W), np.int32)
        pose = np.asarray(pose, dtype=np.float64)
        s = sensor or SensorModel()
        lists, counts = self._tile_lists(pose, intrinsics, step, H, W)
        render_kernel(
            depth, color, label, self.table, self._seen_from(pose[:3, 3]), lists, counts,
            ti.Matrix(pose[:3, :3].astype(np.float32)), ti.Vector(pose[:3, 3].astype(np.float32)),
            intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy,
            int(step), int(intrinsics.width),
            int(sensor is not None), int(seed) & 0xFFFFFFFF,
            s.min_range, s.max_range, math.cos(math.radians(s.grazing_deg)),
            intrinsics.fx * s.sensor_width / intrinsics.width * s.baseline, s.subpixel, s.color_sigma,
            s.depth_noise_scale,
        )
        return depth, color, label
