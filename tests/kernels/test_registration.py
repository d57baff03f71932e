"""kernels/registration.py: colour reprojected into the depth camera, against a NumPy float64 reference, on
every backend; points outside the colour image, behind it, without depth, and hidden from the colour camera."""

import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.geometry import make_pose, so3_exp
from ti_fusion.kernels.registration import EDGE, MAX_SPLAT, OCCLUSION_MARGIN, ColorRegistration

KD = Intrinsics(fx=60.0, fy=58.0, cx=39.5, cy=29.25, width=80, height=60)
KC = Intrinsics(fx=95.0, fy=96.0, cx=50.0, cy=37.5, width=100, height=76)


def register_ref(depth, color, Kd, Kc, T, margin=OCCLUSION_MARGIN):
    """The kernel's rule in float64: z-buffer of footprints, then bilinear colour where not hidden."""
    h, w = depth.shape
    hc, wc = color.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = depth.astype(np.float64)
    p = np.stack([(u - Kd.cx) / Kd.fx * z, (v - Kd.cy) / Kd.fy * z, z], -1)
    q = p @ T[:3, :3].T + T[:3, 3]
    has = (z > 0) & (q[..., 2] > 0)
    qz = np.where(has, q[..., 2], 1.0)
    uc = Kc.fx * q[..., 0] / qz + Kc.cx
    vc = Kc.fy * q[..., 1] / qz + Kc.cy
    zbuf = np.full((hc, wc), np.inf)
    for y, x in zip(*np.nonzero(has)):
        r = int(min(np.ceil(Kc.fx / Kd.fx * z[y, x] / qz[y, x] - 0.01), MAX_SPLAT)) // 2
        iu, iv = int(np.rint(uc[y, x])), int(np.rint(vc[y, x]))
        y0, y1, x0, x1 = max(iv - r, 0), min(iv + r + 1, hc), max(iu - r, 0), min(iu + r + 1, wc)
        if y0 < y1 and x0 < x1:
            zbuf[y0:y1, x0:x1] = np.minimum(zbuf[y0:y1, x0:x1], qz[y, x])
    inside = has & (uc >= -EDGE) & (uc <= wc - 1 + EDGE) & (vc >= -EDGE) & (vc <= hc - 1 + EDGE)
    out = np.zeros((h, w, 3))
    valid = np.zeros((h, w), bool)
    c = color.astype(np.float64)
    for y, x in zip(*np.nonzero(inside)):
        if qz[y, x] > zbuf[int(np.rint(vc[y, x])), int(np.rint(uc[y, x]))] * (1 + margin):
            continue
        u0 = max(min(int(np.floor(uc[y, x])), wc - 2), 0)
        v0 = max(min(int(np.floor(vc[y, x])), hc - 2), 0)
        a, b = np.clip(uc[y, x] - u0, 0, 1), np.clip(vc[y, x] - v0, 0, 1)
        out[y, x] = (1 - a) * (1 - b) * c[v0, u0] + a * (1 - b) * c[v0, u0 + 1] + (1 - a) * b * c[v0 + 1, u0] \
            + a * b * c[v0 + 1, u0 + 1]
        valid[y, x] = True
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), valid


def random_depth(rng, shape=(60, 80), invalid=0.1):
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    z = 1.2 + 0.3 * np.sin(u / 8.0 + rng.uniform(0, 6)) + 0.2 * np.cos(v / 6.0)
    z[h // 3: 2 * h // 3, w // 3: w // 2] -= 0.6  # a near block: it hides a strip of what is behind it
    z[rng.random(shape) < invalid] = 0.0
    return z.astype(np.float32)


def test_random_scenes_match_the_float64_reference(arch, rng):
    for _ in range(3):
        depth = random_depth(rng)
        color = rng.integers(0, 256, (KC.height, KC.width, 3), dtype=np.uint8)
        T = make_pose(so3_exp(rng.normal(0, 0.03, 3)), rng.uniform(-0.06, 0.06, 3))
        reg = ColorRegistration(depth.shape, color.shape[:2])
        out, valid = reg.register(depth, color, KD, KC, T)
        ref, ref_valid = register_ref(depth, color, KD, KC, T)
        assert (valid != ref_valid).mean() < 0.003  # float32 against float64 at the borders and the margin
        both = valid & ref_valid
        assert both.sum() > 0.4 * valid.size
        assert np.abs(out[both].astype(int) - ref[both]).max() <= 1
        assert np.all(out[~valid] == 0) and not np.any(valid[depth == 0])


def test_the_same_camera_gives_the_color_back(arch, rng):
    """Identity extrinsics and the depth camera's intrinsics: every pixel with depth keeps its colour."""
    depth = random_depth(rng)
    color = rng.integers(0, 256, (KD.height, KD.width, 3), dtype=np.uint8)
    out, valid = ColorRegistration(depth.shape, depth.shape).register(depth, color, KD, KD, np.eye(4))
    np.testing.assert_array_equal(valid, depth > 0)
    np.testing.assert_array_equal(out[valid], color[valid])


def test_outside_behind_and_hidden_points_get_no_color(arch):
    """A wall at 2 m and a near square at 1 m; the colour camera 10 cm to the right (x): in its image the
    square moves 6 pixels left and the wall 3, so the strip of wall just left of the square, seen by depth,
    is hidden from colour; points that land outside
    the colour image, or behind the colour camera, have none either."""
    h, w = 60, 80
    depth = np.full((h, w), 2.0, np.float32)
    depth[20:40, 30:50] = 1.0
    depth[0, 0] = 0.0
    color = np.full((KD.height, KD.width, 3), 100, np.uint8)
    T = make_pose(np.eye(3), [-0.10, 0.0, 0.0])  # p_color = p_depth - (0.1, 0, 0): colour camera at x = +0.1
    out, valid = ColorRegistration(depth.shape, color.shape[:2]).register(depth, color, KD, KD, T)
    ref, ref_valid = register_ref(depth, color, KD, KD, T)
    np.testing.assert_array_equal(valid, ref_valid)
    assert not valid[25:35, 27:30].any() and valid[25:35, 20:27].all() and valid[25:35, 50:60].all()
    assert valid[25:35, 30:50].all()  # the square itself is seen
    assert not valid[:, :3].any() and not valid[0, 0]  # the colour camera's image ends 3 px in; no depth
    behind = make_pose(np.eye(3), [0.0, 0.0, -3.0])  # every point behind the colour camera
    _, valid = ColorRegistration(depth.shape, color.shape[:2]).register(depth, color, KD, KD, behind)
    assert not valid.any()


@pytest.mark.parametrize("scene", ["room", "wall", "corridor"])
def test_the_synthetic_scene_seen_by_an_offset_color_camera(cpu, scene):
    """The target: a colour camera 2.5 cm aside, turned 1.3 degrees, with its own intrinsics: the registered
    colour matches the colour rendered at the depth camera within 2 grey levels (median) on the pixels both
    see, where the unregistered colour is off by many."""
    import cv2

    from ti_fusion.config import SynthConfig
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig(scene=scene, width=320, height=240, fx=262.5))
    T = make_pose(so3_exp(np.array([0.01, -0.02, 0.01])), [0.025, 0.003, -0.002])
    Kc = Intrinsics(fx=300.0, fy=301.0, cx=165.0, cy=118.0, width=320, height=240)
    reg = ColorRegistration((240, 320), (240, 320))
    for i in (0, len(seq) // 2):
        depth, at_depth = seq.render(seq.poses[i], noise=False)
        offset = seq.render_offset_color(seq.poses[i], T, Kc, noise=False)
        out, valid = reg.register(depth, offset, seq.intrinsics, Kc, T)
        grey = [cv2.cvtColor(c, cv2.COLOR_RGB2GRAY).astype(int) for c in (out, at_depth, offset)]
        assert valid.mean() > 0.6
        assert np.median(np.abs(grey[0] - grey[1])[valid]) <= 2
        if scene == "room":  # textured everywhere: the unregistered colour is visibly off
            assert np.mean(np.abs(grey[2] - grey[1])[valid]) > 3 * np.mean(np.abs(grey[0] - grey[1])[valid])
