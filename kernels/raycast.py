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
the same for a seed on every backend and a subsampled render equals the subsampled full render.
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

T_MIN = 1e-4
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
    return ti.sqrt(-2.0 * ti.log(u1)) * ti.cos(2.0 * math.pi * u2)


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
def intersect(prims: ti.template(), k, o, d):
    """Distance along the unit ray (o, d) to primitive k's front surface; NO_HIT when missed."""
    kind = ti.cast(prims[k, KIND], ti.i32)
    c = row3(prims, k, CENTER)
    t = NO_HIT
    if kind == PLANE:
        n = row3(prims, k, NORMAL)
        denom = d.dot(n)
        if denom < -1e-8:
            s = (c - o).dot(n) / denom
            if s > T_MIN:
                t = s
    elif kind == BOX:
        cs, sn = prims[k, YAW], prims[k, YAW + 1]
        h = row3(prims, k, HALF)
        ol = to_local(o - c, cs, sn)
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
        oc = o - c
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
        oc = o - c
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
def albedo(prims: ti.template(), k, uv, footprint):
    su = prims[k, SCALE]
    sv = su * prims[k, ASPECT]
    salt = ti.cast(prims[k, SALT], ti.i32)
    m = pattern_value(ti.cast(prims[k, PATTERN], ti.i32), uv, su, sv, salt, footprint)
    a = row3(prims, k, COLOR_A)
    b = row3(prims, k, COLOR_B)
    col = a * 0.3
    if m >= 0:
        col = a + (b - a) * m
    # fine detail: two octaves of value noise below the cell size, faded where smaller than a pixel
    detail = 0.0
    lam = 0.5 * ti.min(su, sv)
    for octave in ti.static(range(2)):
        w = fade(lam, footprint)
        detail += w * (value_noise(uv.x / lam, uv.y / lam, salt + 17 + octave) - 0.5) * (0.7 ** octave)
        lam *= 0.4
    return col * (1.0 + prims[k, DETAIL] * 1.8 * detail)


@ti.func
def shade(p, n):
    light = ti.Vector(LIGHT)
    to_light = light - p
    dist2 = to_light.dot(to_light)
    ndl = ti.max(n.dot(to_light) / ti.sqrt(dist2), 0.0)
    return AMBIENT + DIFFUSE * ndl / (1.0 + 0.12 * dist2) + SKY * (0.5 + 0.5 * n.z)


# -- the kernel ----------------------------------------------------------------------------------------
@ti.kernel
def render_kernel(
    depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
    color: ti.types.ndarray(dtype=ti.i32, ndim=2),
    label: ti.types.ndarray(dtype=ti.i32, ndim=2),
    prims: ti.types.ndarray(dtype=ti.f32, ndim=2),
    tile_prims: ti.types.ndarray(dtype=ti.i32, ndim=3),
    tile_count: ti.types.ndarray(dtype=ti.i32, ndim=2),
    rot: ti.types.matrix(3, 3, ti.f32),
    origin: ti.types.vector(3, ti.f32),
    fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
    step: ti.i32, full_width: ti.i32,
    noise: ti.i32, seed: ti.u32,
    min_range: ti.f32, max_range: ti.f32, cos_grazing: ti.f32,
    fx_baseline: ti.f32, subpixel: ti.f32, color_sigma: ti.f32,
):
    """Per pixel: nearest hit → depth (along the optical axis), packed RGB (r | g<<8 | b<<16), label."""
    H, W = depth.shape
    for v, u in ti.ndrange(H, W):
        ui = u * step  # the full-resolution pixel this one samples
        vi = v * step
        ray_cam = ti.Vector([(ti.cast(ui, ti.f32) - cx) / fx, (ti.cast(vi, ti.f32) - cy) / fy, 1.0])
        inv_len = 1.0 / ray_cam.norm()
        d = (rot @ ray_cam) * inv_len
        best = NO_HIT
        hit = -1
        for j in range(tile_count[v // TILE, u // TILE]):
            k = tile_prims[v // TILE, u // TILE, j]
            bound = prims[k, BOUND]
            if bound >= 0:  # cheap rejection by the bounding sphere: off the ray, or behind the best hit
                oc = row3(prims, k, CENTER) - origin
                b = oc.dot(d)
                if oc.dot(oc) - b * b > bound * bound or b - bound > best:
                    continue
            t = intersect(prims, k, origin, d)
            if t < best:
                best = t
                hit = k
        z = 0.0
        cos_inc = 0.0
        rgb = ti.Vector([0.0, 0.0, 0.0])
        if hit >= 0:
            p = origin + best * d
            n, uv = surface(prims, hit, p)
            z = best * inv_len
            cos_inc = -n.dot(d)
            footprint = z / fx / ti.max(ti.abs(n.dot(d)), 0.25)  # metres per full-resolution pixel
            rgb = albedo(prims, hit, uv, footprint) * shade(p, n) * 255.0
        pixel = ti.cast(vi * full_width + ui, ti.u32) * ti.u32(4)
        if noise != 0:
            if hit >= 0:
                if z < min_range or z > max_range or cos_inc < cos_grazing:
                    z = 0.0
                else:
                    zn = z + depth_sigma(z, ti.f32) * gaussian(pixel, seed)
                    disparity = ti.round(fx_baseline / zn * subpixel) / subpixel
                    z = fx_baseline / disparity if disparity > 0 else 0.0
            # colour: a cheap near-Gaussian (sum of four uniform bytes of one hash, unit variance)
            for ch in ti.static(range(3)):
                h = hash_u32(hash_u32(pixel + ti.u32(ch + 1)) ^ seed)
                bytes_sum = ti.cast((h & 255) + ((h >> 8) & 255) + ((h >> 16) & 255) + (h >> 24), ti.f32)
                rgb[ch] += color_sigma * (bytes_sum - 510.0) * (1.7320508 / 255.0)
        r = ti.cast(ti.min(ti.max(ti.round(rgb.x), 0.0), 255.0), ti.i32)
        g = ti.cast(ti.min(ti.max(ti.round(rgb.y), 0.0), 255.0), ti.i32)
        b = ti.cast(ti.min(ti.max(ti.round(rgb.z), 0.0), 255.0), ti.i32)
        depth[v, u] = z
        color[v, u] = r | (g << 8) | (b << 16)
        label[v, u] = hit


class RayCaster:
    """Renders a primitive table (rows as above) from any camera pose."""

    def __init__(self, table: np.ndarray):
        table = np.ascontiguousarray(table, dtype=np.float32)
        if table.ndim != 2 or table.shape[1] != NUM_COLUMNS:
            raise ValueError(f"primitive table must be P×{NUM_COLUMNS}, got {table.shape}")
        self.table = table

    def _tile_lists(self, pose: np.ndarray, K: Intrinsics, step: int, H: int, W: int):
        """Per TILE×TILE tile, the primitives that may cover it: (lists TH×TW×P, counts TH×TW), int32.

        Conservative: a bounded primitive goes to the tiles its bounding cube projects to; a plane to the
        tiles where some corner ray points at its front side (ray directions are affine in the pixel, so
        a tile's rays are convex combinations of its corner rays). Each list holds planes first, then the
        others near to far, so an early hit lets the farther ones be skipped by the bounding test.
        """
        table = self.table.astype(np.float64)
        R, o = pose[:3, :3], pose[:3, 3]
        TH, TW = -(-H // TILE), -(-W // TILE)
        P = len(table)
        bound = table[:, BOUND]
        centers = table[:, CENTER:CENTER + 3]
        visible = np.zeros((TH, TW, P), bool)
        # corner pixels of every tile, as full-resolution pixel coordinates
        us = np.stack([np.arange(TW) * TILE, np.minimum(np.arange(TW) * TILE + TILE - 1, W - 1)], 1) * step
        vs = np.stack([np.arange(TH) * TILE, np.minimum(np.arange(TH) * TILE + TILE - 1, H - 1)], 1) * step
        cam = (centers - o) @ R  # centres in the camera frame
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        for k in range(P):
            if bound[k] < 0:  # plane
                n_cam = R.T @ table[k, NORMAL:NORMAL + 3]
                dx = (us - K.cx) / K.fx * n_cam[0]  # TW×2
                dy = (vs - K.cy) / K.fy * n_cam[1]  # TH×2
                lowest = dy.min(1)[:, None] + dx.min(1)[None, :] + n_cam[2]
                visible[:, :, k] = lowest < 1e-6
                continue
            r = bound[k] * 1.001 + 1e-3
            z = cam[k, 2]
            if z + r <= 0:
                continue
            if z - r <= 1e-3:  # reaches behind the camera: anywhere
                visible[:, :, k] = True
                continue
            corners = cam[k] + r * signs
            u = K.fx * corners[:, 0] / corners[:, 2] + K.cx
            v = K.fy * corners[:, 1] / corners[:, 2] + K.cy
            i0, i1 = int(np.ceil(u.min() / step)), int(np.floor(u.max() / step))
            j0, j1 = int(np.ceil(v.min() / step)), int(np.floor(v.max() / step))
            i0, i1, j0, j1 = max(i0, 0), min(i1, W - 1), max(j0, 0), min(j1, H - 1)
            if i0 <= i1 and j0 <= j1:
                visible[j0 // TILE:j1 // TILE + 1, i0 // TILE:i1 // TILE + 1, k] = True
        dist = np.linalg.norm(centers - o, axis=1) - bound
        dist[bound < 0] = -np.inf
        order = np.argsort(dist, kind="stable")
        ranked = visible[:, :, order]
        lists = order[np.argsort(~ranked, axis=-1, kind="stable")]
        return np.ascontiguousarray(lists, dtype=np.int32), ranked.sum(-1).astype(np.int32)

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, step: int = 1,
               sensor: SensorModel | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth float32 H×W metres 0 = invalid, colour uint8 H×W×3 RGB, label int32 H×W, −1 = no hit).

        ``pose`` is camera-to-world (x right, y down, z forward). ``step`` > 1 renders every step-th
        pixel of the ``intrinsics`` image (exactly ``full[::step, ::step]``); ``sensor`` None = no noise.
        """
        H = (intrinsics.height + step - 1) // step
        W = (intrinsics.width + step - 1) // step
        depth = np.empty((H, W), np.float32)
        packed = np.empty((H, W), np.int32)
        label = np.empty((H, W), np.int32)
        pose = np.asarray(pose, dtype=np.float64)
        s = sensor or SensorModel()
        lists, counts = self._tile_lists(pose, intrinsics, step, H, W)
        render_kernel(
            depth, packed, label, self.table, lists, counts,
            ti.Matrix(pose[:3, :3].astype(np.float32)), ti.Vector(pose[:3, 3].astype(np.float32)),
            intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy,
            int(step), int(intrinsics.width),
            int(sensor is not None), int(seed) & 0xFFFFFFFF,
            s.min_range, s.max_range, math.cos(math.radians(s.grazing_deg)),
            intrinsics.fx * s.sensor_width / intrinsics.width * s.baseline, s.subpixel, s.color_sigma,
        )
        little = packed if np.little_endian else packed.byteswap()  # bytes r, g, b, 0 in memory order
        color = np.ascontiguousarray(little.view(np.uint8).reshape(H, W, 4)[..., :3])
        return depth, color, label
