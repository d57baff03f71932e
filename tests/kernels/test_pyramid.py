"""FramePyramid kernels (pyramid, back-projection, normals) against NumPy float64 references, on every backend.

Random depths are multiples of 1/1024 m: exactly representable in float32 with exact differences, so
the depth-jump and range tests of the kernels and of the references never disagree by a rounding.
"""

import weakref
from types import SimpleNamespace

import numpy as np
import pytest

from ti_fusion import backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import PyramidConfig
from ti_fusion.kernels.pyramid import FramePyramid, jpeg_blockiness
from tests.conftest import ARCHES, use_arch

K = Intrinsics(fx=150.0, fy=140.0, cx=39.5, cy=30.25, width=80, height=60)
JUMP = 0.05 + 1 / 4096  # never equal to a difference of two depths on the 1/1024 grid
PYR = 0.09 + 1 / 4096


def settings(jump=JUMP, max_diff=PYR, radius=0) -> PyramidConfig:
    """FramePyramid settings: normals up to depth jumps of ``jump``, depth means over ``max_diff`` (3σ)."""
    return PyramidConfig(normal_max_depth_jump=jump, depth_sigma=max_diff / 3, depth_smooth_radius=radius)


def random_depth(rng, shape=(60, 80), invalid=0.15):
    """A smooth surface with rough patches, steps and holes (metres, 0 = invalid)."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W]
    z = 1.5 + 0.3 * np.sin(u / 9.0 + rng.uniform(0, 6)) + 0.2 * np.cos(v / 7.0) + 0.004 * rng.normal(size=shape)
    z[:, W // 2:] += 0.08  # a depth step down the middle column
    z[rng.random(shape) < 0.02] += 0.06  # isolated jumps
    z[rng.random(shape) < invalid] = 0.0
    return (np.round(z * 1024) / 1024).astype(np.float32)


def backproject_ref(depth, K):
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = depth.astype(np.float64)
    V = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=-1)
    V[z <= 0] = 0.0
    return V


def normals_ref(V, max_jump):
    """Cross product of central differences, facing the camera; zero on the border, next to an invalid
    pixel, or across a depth jump larger than max_jump."""
    H, W, _ = V.shape
    N = np.zeros_like(V)
    c = V[1:-1, 1:-1]
    l, r, t, b = V[1:-1, :-2], V[1:-1, 2:], V[:-2, 1:-1], V[2:, 1:-1]
    zs = np.stack([c[..., 2], l[..., 2], r[..., 2], t[..., 2], b[..., 2]])
    ok = np.all(zs > 0, axis=0) & (np.max(np.abs(zs[1:] - zs[0]), axis=0) <= max_jump)
    m = np.cross(r - l, b - t)
    length = np.linalg.norm(m, axis=-1)
    ok &= length > 0
    m = m / np.where(ok, length, 1.0)[..., None]
    m *= np.where(np.einsum("hwk,hwk->hw", m, c) > 0, -1.0, 1.0)[..., None]
    N[1:-1, 1:-1] = np.where(ok[..., None], m, 0.0)
    return N


def pyramid_ref(fine, max_diff):
    H, W = fine.shape
    h, w = (H + 1) // 2, (W + 1) // 2
    out = np.zeros((h, w))
    f = fine.astype(np.float64)
    for v in range(h):
        for u in range(w):
            c = f[2 * v, 2 * u]
            if c <= 0:
                continue
            ry = min(1, 2 * v, H - 1 - 2 * v)  # symmetric window on the border
            rx = min(1, 2 * u, W - 1 - 2 * u)
            win = f[2 * v - ry:2 * v + ry + 1, 2 * u - rx:2 * u + rx + 1]
            sel = win[(win > 0) & (np.abs(win - c) < max_diff)]
            out[v, u] = sel.mean()
    return out


def test_backprojection_matches_reference(arch, rng):
    depth = random_depth(rng)
    pyramid = FramePyramid(settings(), *depth.shape, levels=1)
    pyramid.compute(depth, K)
    V = pyramid.vertex[0].to_numpy()
    np.testing.assert_allclose(V, backproject_ref(depth, K), rtol=2e-6, atol=1e-7)
    assert np.all(V[depth == 0] == 0)


@pytest.fixture(params=[(a, how) for a in ARCHES for how in (("serial", "parallel") if a == "cpu" else ("parallel",))],
                ids=lambda p: f"{p[0]}-{p[1]}")
def arch_loops(request, monkeypatch):
    """The backend, and where the loops run. On the CPU small images run their loops on the calling thread
    (``SERIAL_BELOW``); "parallel" lowers the threshold so that these small test images take the parallel
    build of every kernel as well. Off the CPU every loop is parallel (``serial_for``): one case."""
    arch, how = request.param
    use_arch(arch)
    if how == "parallel":
        monkeypatch.setattr(backend, "SERIAL_BELOW", 0)
    return request.param


@pytest.mark.parametrize("shape", [(60, 80), (61, 83), (9, 7)])  # 83, 7: a partial last pack of 8 pixels
def test_normals_match_reference(arch_loops, rng, shape):
    depth = random_depth(rng, shape)
    Ks = Intrinsics(150.0, 140.0, shape[1] / 2, shape[0] / 2, shape[1], shape[0])
    pyramid = FramePyramid(settings(), *depth.shape, levels=1)
    pyramid.compute(depth, Ks)
    N = pyramid.normal[0].to_numpy()
    # The reference starts from the kernel's float32 vertices, so only the normal arithmetic is compared.
    ref = normals_ref(pyramid.vertex[0].to_numpy().astype(np.float64), np.float32(JUMP))
    valid_ref = np.any(ref != 0, axis=-1)
    valid = np.any(N != 0, axis=-1)
    np.testing.assert_array_equal(valid, valid_ref)
    if min(shape) > 20:
        assert 0.3 < valid.mean() < 0.9  # the test exercises both outcomes
    np.testing.assert_allclose(N, ref, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(N[valid], axis=-1), 1.0, atol=1e-5)


def test_normals_invalid_neighbours_depth_jumps_and_border(arch):
    H, W = 12, 16
    depth = np.full((H, W), 1.0, dtype=np.float32)
    depth[5, 5] = 0.0                       # a hole: its 4 neighbours lose their normal
    depth[2, 10] = 1.0 + 0.05               # a jump just below max_depth_jump: still a normal
    depth[8, 10] = 1.0 + 0.0625             # a jump just above: no normal around it
    pyramid = FramePyramid(settings(jump=0.0546875, max_diff=0.09), H, W, levels=1)
    pyramid.compute(depth, Intrinsics(100.0, 100.0, 7.5, 5.5, W, H))
    N = pyramid.normal[0].to_numpy()
    has = np.any(N != 0, axis=-1)
    assert not has[0].any() and not has[-1].any() and not has[:, 0].any() and not has[:, -1].any()
    for v, u in [(5, 5), (4, 5), (6, 5), (5, 4), (5, 6)]:
        assert not has[v, u]
    assert has[2, 10] and has[1, 10] and has[2, 9]
    for v, u in [(8, 10), (7, 10), (9, 10), (8, 9), (8, 11)]:
        assert not has[v, u]
    assert has[3, 3]
    # A fronto-parallel plane: the normal points back at the camera.
    np.testing.assert_allclose(N[3, 3], [0.0, 0.0, -1.0], atol=1e-6)


def test_normal_faces_the_camera_on_a_slanted_plane(arch):
    H, W = 20, 24
    Kp = Intrinsics(60.0, 60.0, 11.5, 9.5, W, H)
    v, u = np.mgrid[0:H, 0:W]
    # plane n·X = d with n = (0.3, -0.2, -0.93) (unit after normalising), seen from the origin
    n = np.array([0.3, -0.2, -0.93])
    n /= np.linalg.norm(n)
    rays = np.stack([(u - Kp.cx) / Kp.fx, (v - Kp.cy) / Kp.fy, np.ones_like(u, dtype=float)], -1)
    z = -1.5 / (rays @ n)
    pyramid = FramePyramid(settings(jump=1.0, max_diff=0.09), H, W, levels=1)
    pyramid.compute(z.astype(np.float32), Kp)
    N = pyramid.normal[0].to_numpy()[1:-1, 1:-1].reshape(-1, 3)
    np.testing.assert_allclose(N, np.broadcast_to(n, N.shape), atol=2e-4)


def smooth_ref(depth, radius, max_diff, margins: bool = False):
    """Range-checked mean along rows, then along columns (each against its own centre); near the border
    the window shrinks to the symmetric radius that fits. ``margins``: also, per pass, each pixel's least distance
    between a neighbour's |difference| from its centre and ``max_diff`` (where rounding could flip the check)."""
    out = depth.astype(np.float64)
    passes = []
    for axis in (1, 0):
        src = out
        n = src.shape[axis]
        total = np.zeros_like(src)
        count = np.zeros_like(src)
        margin = np.full(src.shape, np.inf)
        pos = np.arange(n)
        fit = np.minimum(pos, n - 1 - pos)  # symmetric window at the border
        for k in range(-radius, radius + 1):
            shifted = np.roll(src, -k, axis=axis)
            inside = (abs(k) <= fit)[None, :] if axis == 1 else (abs(k) <= fit)[:, None]
            seen = inside & (shifted > 0) & (src > 0)
            margin = np.where(seen, np.minimum(margin, np.abs(np.abs(shifted - src) - max_diff)), margin)
            ok = inside & (shifted > 0) & (np.abs(shifted - src) < max_diff)
            total += np.where(ok, shifted, 0.0)
            count += ok
        out = np.where(src > 0, total / np.maximum(count, 1), 0.0)
        out = out.astype(np.float32).astype(np.float64)  # the kernel stores the row pass in float32
        passes.append(margin)
    return (out, passes) if margins else out


def test_smoothing_and_pyramid_keep_a_ramp_up_to_the_border(arch):
    u = np.arange(40, dtype=np.float64)
    depth = np.broadcast_to(1.0 + 0.004 * u + 0.002 * u[:, None][:30], (30, 40)).astype(np.float32)
    pyramid = FramePyramid(settings(jump=0.05, max_diff=0.09, radius=2), 30, 40, levels=3)
    pyramid.compute(depth, Intrinsics(50.0, 50.0, 19.5, 14.5, 40, 30))
    np.testing.assert_allclose(pyramid.depth[0].to_numpy(), depth, rtol=1e-6)
    np.testing.assert_allclose(pyramid.depth[1].to_numpy(), depth[::2, ::2], rtol=1e-6)
    np.testing.assert_allclose(pyramid.depth[2].to_numpy(), depth[::4, ::4], rtol=1e-6)


@pytest.mark.parametrize("radius, shape", [pytest.param(1, (60, 80), marks=pytest.mark.slow), pytest.param(2, (60, 80), marks=pytest.mark.slow),
                                           (6, (61, 83)), (12, (37, 85))])
def test_smoothing_matches_reference(arch_loops, rng, radius, shape):
    """Also widths that are no multiple of the 8-pixel packs, and radii whose window spans several packs."""
    depth = random_depth(rng, shape)
    K = Intrinsics(150.0, 140.0, shape[1] / 2, shape[0] / 2, shape[1], shape[0])
    pyramid = FramePyramid(settings(radius=radius), *depth.shape, levels=2)
    pyramid.compute(depth, K)
    got = pyramid.depth[0].to_numpy()
    expected, (row_margin, column_margin) = smooth_ref(depth, radius, np.float32(PYR), margins=True)
    np.testing.assert_array_equal(got > 0, depth > 0)
    # each pass a mean of at most n = 2r + 1 positive values, summed in float32: within n·u of the exact mean
    # (u = 2⁻²⁴); the row pass off the reference's float32 row by (n + 1)u, the column pass adding its own n·u
    n, u = 2 * radius + 1, 2.0 ** -24
    # The column pass's range check compares two row-pass values, each up to (n + 1)u d off the reference's: a
    # neighbour whose difference lies that close to the threshold may be taken on one side only, which no
    # rounding bound covers, so those pixels are left out (the row pass's inputs are multiples of 1/1024 m, a
    # quarter step from the threshold: its checks cannot flip).
    band = 2 * (n + 1) * u * depth.max()
    assert row_margin.min() > band
    clear = column_margin > band
    assert clear.mean() > 0.95
    np.testing.assert_allclose(got[clear], expected[clear], rtol=(2 * n + 2) * u)
    assert np.abs(got - depth).max() > 1e-3  # it did smooth
    np.testing.assert_allclose(pyramid.vertex[0].to_numpy(), backproject_ref(got, K), rtol=2e-6, atol=1e-7)


def test_pyramid_matches_reference(arch_loops, rng):
    depth = random_depth(rng, shape=(61, 81))  # odd sizes: the last coarse pixel sees a clipped window
    pyramid = FramePyramid(settings(), *depth.shape, levels=3)
    pyramid.compute(depth, Intrinsics(150.0, 140.0, 40.0, 30.0, 81, 61))
    assert pyramid.shapes == [(61, 81), (31, 41), (16, 21)]
    expected = depth
    for level in range(1, 3):
        expected = pyramid_ref(expected, np.float32(PYR))
        got = pyramid.depth[level].to_numpy()
        np.testing.assert_array_equal(got > 0, expected > 0)
        np.testing.assert_allclose(got, expected, rtol=1e-6)
        expected = got  # the next level is built from this level's float32 values
        K_l = pyramid.intrinsics[level]
        assert (K_l.width, K_l.height) == pyramid.shapes[level][::-1]
        np.testing.assert_allclose(pyramid.vertex[level].to_numpy(), backproject_ref(got, K_l), rtol=2e-6, atol=1e-7)
        # odd widths (41, 21): the last pack of the vertex/normal kernel is partial
        ref_n = normals_ref(pyramid.vertex[level].to_numpy().astype(np.float64), np.float32(JUMP * 2**level))
        np.testing.assert_allclose(pyramid.normal[level].to_numpy(), ref_n, atol=2e-5)


@pytest.mark.parametrize("input_level, radius", [(1, 0), pytest.param(1, 2, marks=pytest.mark.slow), pytest.param(2, 1, marks=pytest.mark.slow)])
def test_input_level_averages_down_first(arch_loops, rng, input_level, radius):
    """FramePyramid(input_level=L): level 0 is the input averaged down L times (then smoothed), the same
    maps as level L of full-resolution maps built without smoothing."""
    depth = random_depth(rng, shape=(61, 81))
    K_in = Intrinsics(150.0, 140.0, 40.0, 30.0, 81, 61)
    pyramid = FramePyramid(settings(radius=radius), *depth.shape, levels=2, input_level=input_level)
    pyramid.compute(depth, K_in)
    expected = depth
    for _ in range(input_level):
        expected = pyramid_ref(expected, np.float32(PYR)).astype(np.float32)
    assert pyramid.shapes[0] == expected.shape and pyramid.input_shape == depth.shape
    if radius:
        expected = smooth_ref(expected, radius, np.float32(PYR))
    got = pyramid.depth[0].to_numpy()
    np.testing.assert_array_equal(got > 0, expected > 0)
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    K_0 = pyramid.intrinsics[0]
    assert K_0 == K_in.downsampled(2**input_level) and (K_0.height, K_0.width) == pyramid.shapes[0]
    np.testing.assert_allclose(pyramid.vertex[0].to_numpy(), backproject_ref(got, K_0), rtol=2e-6, atol=1e-7)
    with pytest.raises(ValueError, match="shape"):
        pyramid.compute(expected.astype(np.float32), K_0)  # the input resolution is expected


def test_pyramid_does_not_average_across_an_edge(arch):
    depth = np.full((8, 8), 1.0, dtype=np.float32)
    depth[:, 3:] = 2.0  # the coarse pixel at u = 1 (fine u = 2) has fine neighbours on both sides
    pyramid = FramePyramid(settings(jump=0.05, max_diff=0.09), 8, 8, levels=2)
    pyramid.compute(depth, Intrinsics(10.0, 10.0, 3.5, 3.5, 8, 8))
    coarse = pyramid.depth[1].to_numpy()
    np.testing.assert_array_equal(coarse[:, :2], 1.0)
    np.testing.assert_array_equal(coarse[:, 2:], 2.0)


def test_wrong_depth_shape_is_refused(cpu):
    pyramid = FramePyramid(settings(), 10, 12, levels=1)
    with pytest.raises(ValueError, match="shape"):
        pyramid.compute(np.zeros((12, 10), np.float32), Intrinsics(10.0, 10.0, 5.0, 5.0, 12, 10))


# -- intensity (the photometric tracking term) -----------------------------------------------------------
def intensity_down_ref(fine):
    """[1 2 1] ⊗ [1 2 1] mean of the valid (≥ 0) fine intensities of the 3×3 window at (2v, 2u) inside the image."""
    H, W = fine.shape
    out = np.full(((H + 1) // 2, (W + 1) // 2), -1.0)
    for v in range(out.shape[0]):
        for u in range(out.shape[1]):
            total = weight = 0.0
            for dv in (-1, 0, 1):
                for du in (-1, 0, 1):
                    y, x = 2 * v + dv, 2 * u + du
                    if 0 <= y < H and 0 <= x < W and fine[y, x] >= 0:
                        w = (2 - abs(dv)) * (2 - abs(du))
                        total += w * fine[y, x]
                        weight += w
            if weight:
                out[v, u] = total / weight
    return out


def gradient_ref(image):
    """(I, Sobel_x / 8, Sobel_y / 8); (−1, 0, 0) on the border and next to an invalid intensity."""
    I = image.astype(np.float64)
    H, W = I.shape
    out = np.zeros((H, W, 3))
    out[..., 0] = -1.0
    c = I[1:-1, 1:-1]
    win = np.stack([I[1 + dv:H - 1 + dv, 1 + du:W - 1 + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)])
    k = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], dtype=np.float64).ravel() / 8
    ok = win.min(axis=0) >= 0
    inner = np.stack([c, np.tensordot(k, win, 1), np.tensordot(k.reshape(3, 3).T.ravel(), win, 1)], axis=-1)
    out[1:-1, 1:-1] = np.where(ok[..., None], inner, [-1.0, 0.0, 0.0])
    return out


def random_grey(rng, shape, invalid=0.05):
    g = rng.uniform(0, 1, shape)
    g[rng.random(shape) < invalid] = -1.0
    return g.astype(np.float32)


def test_intensity_pyramid_and_gradients_match_reference(arch_loops, rng):
    check_intensity_pyramid(rng, input_level=1)


@pytest.mark.parametrize("input_level", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_intensity_pyramid_of_other_input_levels(arch, rng, input_level):
    """The grey image uploaded as level 0 (input_level 0), or averaged down twice before ``intensity_maps``."""
    check_intensity_pyramid(rng, input_level)


@pytest.mark.parametrize("input_level, radius", [(1, 2), pytest.param(0, 0, marks=pytest.mark.slow)])
def test_depth_and_grey_together(arch, rng, input_level, radius):
    """``compute(depth, K, grey)``: at input level 1 with smoothing the grey image crosses in the depth's
    launch (``input_images``), elsewhere one call after the other; the maps and the intensity pyramid as from
    ``compute`` and ``compute_intensity`` apart, and as the reference."""
    used = check_intensity_pyramid(rng, input_level, radius, together=True)
    depth, K_in = used.depth, used.intrinsics
    apart = FramePyramid(settings(radius=radius), *depth.shape, levels=3, input_level=input_level)
    apart.compute(depth, K_in)
    apart.compute_intensity(used.image)
    for level in range(3):
        for name in ("depth", "vertex", "normal", "intensity", "intensity_grad"):
            np.testing.assert_allclose(getattr(used.pyramid, name)[level].to_numpy(),
                                       getattr(apart, name)[level].to_numpy(), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="grey image of shape"):
        used.pyramid.compute(depth, K_in, used.image[:-1])


@pytest.mark.parametrize("input_level, radius, level", [pytest.param(1, 2, 1, marks=pytest.mark.slow), (2, 1, 0)])
def test_colour_packed_with_the_depth(arch, rng, monkeypatch, input_level, radius, level):
    """``compute(depth, K, grey, color, color_level)``: the uint8 RGB input packed r | g << 8 | b << 16 at
    every 2**(input level + level)-th pixel (the fusion step's colour), in ``input_images``' launch at input
    level 1 with smoothing, by a launch of its own elsewhere (that the maps are as without it, the fusion
    test of the packed colour shows). ``packed_color`` names only the image and level the last ``compute``
    packed."""
    grey = random_grey(rng, (37, 51))
    depth = random_depth(rng, shape=grey.shape)
    K_in = Intrinsics(150.0, 140.0, 25.0, 18.0, 51, 37)
    color = rng.integers(0, 256, (*grey.shape, 3), dtype=np.uint8)
    color[-1, -1] = 255  # the largest value of every channel: the packed word stays below 2**24
    pyramid = FramePyramid(settings(radius=radius), *grey.shape, levels=3, input_level=input_level)
    if input_level == 1:  # packed inside input_images, not by a launch of its own
        from ti_fusion.kernels import pyramid as kmaps

        monkeypatch.setattr(kmaps, "pack_color", lambda *args: pytest.fail("packed by a launch of its own"))
    pyramid.compute(depth, K_in, grey, color, level)
    step = 2**(input_level + level)
    c = color[::step, ::step].astype(np.int64)
    packed = pyramid.packed_color(level, color)
    assert packed.shape == pyramid.shapes[level]
    np.testing.assert_array_equal(packed.to_numpy(), c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16))
    assert pyramid.packed_color(level, color.copy()) is None  # another image
    assert pyramid.packed_color((level + 1) % 3, color) is None  # another level
    again = color.copy()
    pyramid.compute(depth, K_in, grey, again, level)
    assert pyramid.packed_color(level, again) is not None and pyramid.packed_color(level, color) is None
    gone = weakref.ref(again)
    del again
    assert gone() is None  # the pyramid keeps no frame's image alive
    pyramid.compute(depth, K_in)
    assert pyramid.packed_color(level, color) is None  # the next frame came without colour
    with pytest.raises(ValueError, match="colour of shape"):
        pyramid.compute(depth, K_in, None, color[:, :-1])
    with pytest.raises(ValueError, match="color_level 3"):
        pyramid.compute(depth, K_in, None, color, 3)


def check_intensity_pyramid(rng, input_level, radius=0, together=False):
    """The intensity pyramid against the reference (``together``: computed by ``compute`` with the depth);
    returns what it used (the pyramid, the grey image, the depth and the camera)."""
    grey = random_grey(rng, (37, 51))
    grey[8:24, 16:36] = -1.0  # a hole that survives averaging down twice
    depth = random_depth(rng, shape=grey.shape)
    K_in = Intrinsics(150.0, 140.0, 25.0, 18.0, 51, 37)
    pyramid = FramePyramid(settings(radius=radius), *grey.shape, levels=3, input_level=input_level)
    if together:
        pyramid.compute(depth, K_in, grey)
    else:
        pyramid.compute(depth, K_in)
        pyramid.compute_intensity(grey)
    expected = grey.astype(np.float64)
    for _ in range(input_level):
        expected = intensity_down_ref(expected.astype(np.float32))
    for level in range(3):
        if level:
            expected = intensity_down_ref(pyramid.intensity[level - 1].to_numpy())
        got = pyramid.intensity[level].to_numpy()
        assert got.shape == pyramid.shapes[level]
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(pyramid.intensity_grad[level].to_numpy(), gradient_ref(got), atol=1e-6)
    assert np.any(pyramid.intensity_grad[0].to_numpy()[1:-1, 1:-1, 0] < 0)  # invalid windows inside exercised
    with pytest.raises(ValueError, match="shape"):
        pyramid.compute_intensity(grey[:-1])
    return SimpleNamespace(pyramid=pyramid, image=grey, depth=depth, intrinsics=K_in)


def test_surfel_intensity_matches_reference(arch, rng):
    import taichi as ti

    from ti_fusion.kernels.common import INT_MAX
    from ti_fusion.kernels.pyramid import GREY, grey_image

    n = 50
    color = rng.uniform(0, 255, (n, 3)).astype(np.float32)
    index = rng.integers(0, n, (13, 17)).astype(np.int32)
    index[rng.random(index.shape) < 0.2] = INT_MAX
    view, col = ti.field(ti.i32, shape=index.shape), ti.Vector.field(3, ti.f32, shape=n)
    view.from_numpy(index)
    col.from_numpy(color)
    pyramid = FramePyramid(settings(), 13, 17, levels=2)
    pyramid.intensity_from_surfels(view, col)
    expected = np.where(index == INT_MAX, -1.0, (color[np.minimum(index, n - 1)] @ np.array(GREY)) / 255.0)
    np.testing.assert_allclose(pyramid.intensity[0].to_numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(pyramid.intensity[1].to_numpy(), intensity_down_ref(pyramid.intensity[0].to_numpy()),
                               rtol=1e-5, atol=1e-6)
    rgb = rng.integers(0, 256, (4, 5, 3)).astype(np.uint8)
    np.testing.assert_allclose(grey_image(rgb), (rgb @ np.array(GREY)) / 255.0, atol=0.51 / 255)  # rounded to 1/255


# -- stacked levels (one kernel instance for every level) ---------------------------------------------------
def _instances(kernel) -> int:
    """Instances Taichi has compiled of a kernel in this process (one per set of template arguments)."""
    return len(kernel._primal.compiled_kernels)


def test_a_pair_builds_both_pyramids_in_one_set_of_fields_with_the_same_instances(arch, rng):
    """``FramePyramid.pair``: the second pyramid's levels lie below the first's in the first's fields, so building
    it adds no instance of ``pyramid_down`` or ``maps_levels``; both hold the maps that pyramids of their own
    build, bit for bit, and neither overwrites the other's. Levels of other sizes make two pyramids as before."""
    from ti_fusion.kernels import pyramid as kmaps

    H, W = 40, 48
    K = Intrinsics(60.0, 60.0, 24.0, 20.0, W, H)
    frame_depth, model_depth = random_depth(rng, shape=(H, W)), random_depth(rng, shape=(H, W))
    one, two = FramePyramid.pair(settings(), (H, W, 3), (H, W, 3))
    assert two.depth[0].field is one.depth[0].field and two.vertex[0].field is one.vertex[0].field
    one.compute(frame_depth, K)
    kernels = (kmaps.pyramid_down, kmaps.maps_levels)
    counts = [len(k._primal.compiled_kernels) for k in kernels]
    two.depth[0].from_numpy(model_depth)
    two.compute_from_field(K)
    assert [len(k._primal.compiled_kernels) for k in kernels] == counts
    alone_one, alone_two = FramePyramid(settings(), H, W, 3), FramePyramid(settings(), H, W, 3)
    alone_one.compute(frame_depth, K)
    alone_two.depth[0].from_numpy(model_depth)
    alone_two.compute_from_field(K)
    for paired, alone in ((one, alone_one), (two, alone_two)):
        for name in ("depth", "vertex", "normal"):
            for level in range(3):
                np.testing.assert_array_equal(getattr(paired, name)[level].to_numpy(),
                                              getattr(alone, name)[level].to_numpy())
    with pytest.raises(ValueError, match="compute_from_field"):
        two.compute(model_depth, K)
    other_one, other_two = FramePyramid.pair(settings(), (H, W, 3), (H // 2, W // 2, 3))
    assert other_two.depth[0].field is not other_one.depth[0].field and other_two.row0[0] == 0


@pytest.mark.slow
def test_every_level_shares_one_kernel_instance(cpu, rng):
    """The levels of a pyramid are rows of one field per quantity, so a new FramePyramid adds one instance
    of each kernel that builds the pyramid (``pyramid_down``, a launch per level) and the vertex/normal maps
    of all of its levels (``maps_levels``, one launch), not one per level, and none of the one-level maps."""
    from ti_fusion.kernels import pyramid as kmaps

    depth = random_depth(rng, shape=(40, 48))
    kernels = (kmaps.pyramid_down, kmaps.maps_levels, kmaps.vertex_normal_maps)
    counts = [_instances(k) for k in kernels]
    pyramid = FramePyramid(settings(), *depth.shape, levels=4)
    pyramid.compute(depth, Intrinsics(60.0, 60.0, 24.0, 20.0, 48, 40))
    pyramid.compute(depth, Intrinsics(60.0, 60.0, 24.0, 20.0, 48, 40))
    assert [_instances(k) - n for k, n in zip(kernels, counts)] == [1, 1, 0]
    assert pyramid.depth[3].shape == (5, 6) and pyramid.depth[3].row0 == 40 + 20 + 10


def test_level_views_read_and_write_their_own_pixels(arch, rng):
    """A ``Level`` indexes like its own H × W field inside another kernel and in NumPy round trips, and
    leaves the other levels of its stacked field alone."""
    import taichi as ti

    from ti_fusion.kernels.pyramid import Level, as_level

    stack = ti.field(ti.f32, shape=(9, 7))
    stack.from_numpy(np.full((9, 7), -1.0, np.float32))
    level = Level(stack, 5, (4, 5))  # rows 5..8, columns 0..4
    values = rng.uniform(0, 1, level.shape).astype(np.float32)
    level.from_numpy(values)
    np.testing.assert_array_equal(level.to_numpy(), values)

    @ti.kernel
    def double_into(src: ti.template(), dst: ti.template()):
        for v, u in ti.ndrange(*src.shape):
            dst[v, u] = 2.0 * src[v, u]

    out = ti.field(ti.f32, shape=(4, 5))
    double_into(level, out)
    np.testing.assert_array_equal(out.to_numpy(), 2.0 * values)
    double_into(as_level(out), level)  # a plain field is the level at its row 0
    np.testing.assert_array_equal(level.to_numpy(), 4.0 * values)
    level.fill(0.5)
    whole = stack.to_numpy()
    np.testing.assert_array_equal(whole[5:, :5], 0.5)
    assert np.all(whole[:5] == -1.0) and np.all(whole[5:, 5:] == -1.0)
    with pytest.raises(ValueError, match="shape"):
        level.from_numpy(values[:, :4])


def test_copy_rows_matches_reference(arch, rng):
    """``copy_rows``: a band of rows of one stacked field into another band of a field of the same width (vector
    fields, as the kept maps of a localisation), the other rows of the destination unchanged."""
    import taichi as ti

    from ti_fusion.kernels.pyramid import copy_rows

    src64, dst64 = rng.normal(size=(13, 7, 3)), rng.normal(size=(11, 7, 3))
    src, dst = ti.Vector.field(3, ti.f32, shape=(13, 7)), ti.Vector.field(3, ti.f32, shape=(11, 7))
    src.from_numpy(src64.astype(np.float32))
    dst.from_numpy(dst64.astype(np.float32))
    copy_rows(src, 6, dst, 2, 5)
    expected = dst64.copy()
    expected[2:7] = src64[6:11]
    np.testing.assert_array_equal(dst.to_numpy(), expected.astype(np.float32))
    copy_rows(src, 0, dst, 11, 0)  # no rows: nothing written
    np.testing.assert_array_equal(dst.to_numpy(), expected.astype(np.float32))


# -- JPEG blockiness of the grey image (host NumPy) ----------------------------------------------------------
def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    import cv2

    return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_GRAYSCALE)


def test_jpeg_blockiness_tells_compressed_from_clean_images():
    """About 1 on a clean image however noisy, well above 2 on the same through JPEG at quality 75 (the grid at
    any offset, or subsampled by 2 at a lower quality), 1 where an image is flat or too small to tell
    (docs/PHOTOMETRIC.md, real colour)."""
    from ti_fusion.tracking.terms.photometric import CLEAN_BLOCKINESS, JPEG_BLOCKINESS

    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:480, 0:640]
    shading = 128 + 60 * np.sin(u / 23.0) * np.cos(v / 17.0) + 30 * (((u // 40) + (v // 55)) % 2)
    for sigma in (0.0, 2.0, 5.0):  # grey levels of sensor noise
        clean = np.clip(np.round(shading + sigma * rng.standard_normal(shading.shape)), 0, 255).astype(np.uint8)
        assert jpeg_blockiness(clean / np.float32(255)) < CLEAN_BLOCKINESS - 0.2, sigma
        assert jpeg_blockiness(clean[::2, ::2] / np.float32(255)) < CLEAN_BLOCKINESS - 0.1, sigma
        if sigma < 5:  # strong noise hides the blocks of a mild compression
            compressed = _jpeg(clean, 75) / np.float32(255)
            assert jpeg_blockiness(compressed) > JPEG_BLOCKINESS + 0.4, sigma
            assert jpeg_blockiness(compressed[3:, 5:]) > JPEG_BLOCKINESS + 0.4, sigma  # cropped: the grid moved
            assert jpeg_blockiness(_jpeg(clean, 50)[::2, ::2] / np.float32(255)) > JPEG_BLOCKINESS, sigma
    assert jpeg_blockiness(np.full((480, 640), 0.5, np.float32)) == 1.0
    assert jpeg_blockiness(_jpeg(clean, 50)[:60, :60] / np.float32(255)) == 1.0  # under 16 periods a side
