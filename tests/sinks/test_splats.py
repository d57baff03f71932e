"""slam --splats: splats.ply in 3D Gaussian Splatting's layout, read back and checked against the map (the
quaternions by the rotation 3D Gaussian Splatting builds from them), and the sink's registration."""

import json

import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.config import Config
from ti_fusion.io.ply import read_ply
from ti_fusion.sinks import make_sinks
from ti_fusion.sinks.splats import PROPERTIES, SH_C0, SplatSink, gaussians, write_splats, z_onto


def rotation(q: np.ndarray) -> np.ndarray:
    """N×3×3 rotations of N quaternions (w, x, y, z), as 3D Gaussian Splatting's build_rotation makes them."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    r, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)], axis=1),
        np.stack([2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)], axis=1),
        np.stack([2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)], axis=1)], axis=1)


def test_the_quaternion_turns_z_onto_the_normal(rng):
    normals = rng.normal(size=(500, 3))
    normals = np.concatenate([normals, [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [1e-9, 0, -1]]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    q = z_onto(normals)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    R = rotation(q)
    # the thin axis (scale_2) along the normal: to float64's rounding, but for a normal within 1e-6 of −z, which
    # z_onto turns about x (the shortest arc's axis is lost there), so onto −z itself, |n + z| away from it
    err = np.abs(R[:, :, 2] - normals).max(axis=1)
    near_minus_z = np.linalg.norm(normals - [0, 0, -1], axis=1) < 1e-6
    assert near_minus_z.sum() == 2 and np.all(err[near_minus_z] <= 1e-6) and np.all(err[~near_minus_z] <= 1e-12)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


def _check_against(splats: np.ndarray, position, normal, color, confidence, radius, confirmed: float) -> None:
    """Every property of ``splats`` (read back) against the surfels it was made from."""
    assert splats.dtype.names == PROPERTIES and all(splats.dtype[n] == np.float32 for n in PROPERTIES)
    xyz = np.stack([splats["x"], splats["y"], splats["z"]], axis=1)
    np.testing.assert_allclose(xyz, position, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.stack([splats["nx"], splats["ny"], splats["nz"]], axis=1), normal, atol=1e-6)
    rgb = (np.stack([splats[f"f_dc_{i}"] for i in range(3)], axis=1) * SH_C0 + 0.5) * 255
    np.testing.assert_allclose(rgb, color, atol=1e-3)
    alpha = 1 / (1 + np.exp(-splats["opacity"].astype(np.float64)))
    np.testing.assert_allclose(alpha, np.clip(1 - np.exp(-confidence / confirmed), 1e-3, 1 - 1e-3), atol=1e-5)
    scales = np.exp(np.stack([splats[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float64))
    np.testing.assert_allclose(scales[:, 0], radius / 3, rtol=1e-5)
    np.testing.assert_allclose(scales[:, 1], radius / 3, rtol=1e-5)
    np.testing.assert_allclose(scales[:, 2], radius / 300, rtol=1e-5)
    R = rotation(np.stack([splats[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float64))
    np.testing.assert_allclose(R[:, :, 2], normal, atol=1e-5)


def test_gaussians_read_back_from_the_file(rng, tmp_path):
    n = 300
    position = rng.uniform(-3, 3, size=(n, 3))
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    color = rng.uniform(0, 255, size=(n, 3))
    confidence = rng.uniform(0, 40, size=n)  # unconfirmed ones too: nearly transparent
    radius = rng.uniform(0.002, 0.05, size=n)
    path = write_splats(tmp_path / "splats.ply", gaussians(position, normal, color, confidence, radius, 3.0))
    text = path.read_bytes()[:600].decode("ascii", "replace")
    assert text.startswith("ply\nformat binary_little_endian 1.0\n") and f"element vertex {n}\n" in text
    _check_against(read_ply(path), position, normal, color, confidence, radius, 3.0)


def test_the_sink_is_registered_behind_its_switch():
    cfg = Config()
    assert not any(isinstance(s, SplatSink) for s in make_sinks("slam", cfg))
    assert any(isinstance(s, SplatSink) for s in make_sinks("slam", cfg, {"splats": True}))
    assert not any(isinstance(s, SplatSink) for s in make_sinks("fuse", cfg, {"splats": True}))
    with pytest.raises(ValueError, match="no output named splat"):
        make_sinks("slam", cfg, {"splat": True})


def test_slam_splats_match_the_map(cpu, tmp_path):
    """splats.ply of a short run holds one Gaussian per surfel of map.ply, in the same order."""
    out = tmp_path / "run"
    assert main(["slam", "--frames", "6", "--downsample", "2", "--out", str(out), "--quiet", "--splats"]) == 0
    surfels, splats = read_ply(out / "map.ply"), read_ply(out / "splats.ply")
    summary = json.loads((out / "summary.json").read_text())
    assert len(splats) == len(surfels) == summary["surfels"] == summary["splats"]["gaussians"] > 1000
    position = np.stack([surfels["x"], surfels["y"], surfels["z"]], axis=1)
    normal = np.stack([surfels["nx"], surfels["ny"], surfels["nz"]], axis=1).astype(np.float64)
    # map.ply rounds the colour to uint8: the splats keep the map's float colour
    color = np.stack([surfels["red"], surfels["green"], surfels["blue"]], axis=1).astype(np.float64)
    rgb = (np.stack([splats[f"f_dc_{i}"] for i in range(3)], axis=1) * SH_C0 + 0.5) * 255
    assert np.abs(rgb - color).max() <= 0.5 + 1e-3
    _check_against(splats, position, normal, rgb, surfels["confidence"].astype(np.float64),
                   surfels["radius"].astype(np.float64), Config().fusion.unstable_weight)
