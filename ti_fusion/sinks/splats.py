"""``slam --splats``: splats.ply, the surfel map as 3D Gaussians in the PLY layout of 3D Gaussian Splatting
(Kerbl et al. 2023), which splat viewers and converters read (PlayCanvas's splat-transform and SuperSplat,
the three.js viewer @mkkellogg/gaussian-splats-3d; docs/OUTPUTS.md).

One Gaussian per surfel, every property float32:
    x y z                  the surfel's position (world frame, metres)
    nx ny nz               its normal (3D Gaussian Splatting writes zeros here; viewers ignore it)
    f_dc_0 f_dc_1 f_dc_2   its colour c in [0, 1] as the zeroth spherical-harmonic coefficient, (c − 0.5) / SH_C0
    opacity                logit(α), α = 1 − exp(−confidence / fusion.unstable_weight): a just confirmed surfel
                           0.63, three times as confident 0.95 (clipped to ALPHA_RANGE)
    scale_0 scale_1 scale_2  log σ: a flat Gaussian, σ = radius / 3 across the disc (the 3σ that viewers draw
                           out to is the disc's edge) and FLAT × that along the normal
    rot_0..rot_3           the unit quaternion (w, x, y, z) that turns the Gaussian's z axis onto the normal
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.io.outputs import atomic_write
from ti_fusion.sinks.base import Run, Sink

SH_C0 = 0.28209479177387814  # the zeroth real spherical harmonic, 1 / (2 √π)
SIGMA_PER_RADIUS = 1 / 3  # σ across the disc: the disc's radius is 3σ
FLAT = 0.01  # σ along the normal, a fraction of σ across: a flat Gaussian, as the surfel is a disc
ALPHA_RANGE = (1e-3, 1 - 1e-3)  # the opacity's logit stays finite
PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
              "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def z_onto(normal: np.ndarray) -> np.ndarray:
    """N×4 unit quaternions (w, x, y, z) of the shortest rotation that turns +z onto each unit ``normal``
    (N×3); a normal along −z turns about x."""
    n = np.asarray(normal, dtype=np.float64)
    # q = (1 + z·n, z × n), normalised: half the angle between z and n
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)
    norm = np.linalg.norm(q, axis=1)
    opposite = norm < 1e-6
    q[opposite] = (0.0, 1.0, 0.0, 0.0)
    norm[opposite] = 1.0
    return q / norm[:, None]


def gaussians(position: np.ndarray, normal: np.ndarray, color: np.ndarray, confidence: np.ndarray,
              radius: np.ndarray, confirmed: float) -> np.ndarray:
    """The Gaussians of N surfels as a structured array with ``PROPERTIES`` (float32); ``color`` in [0, 255],
    ``confirmed`` the confidence at which a surfel is confirmed (fusion.unstable_weight)."""
    out = np.zeros(len(position), dtype=[(name, "<f4") for name in PROPERTIES])
    for i, axis in enumerate("xyz"):
        out[axis] = position[:, i]
        out["n" + axis] = normal[:, i]
    dc = (np.asarray(color, dtype=np.float64) / 255.0 - 0.5) / SH_C0
    for i in range(3):
        out[f"f_dc_{i}"] = dc[:, i]
    alpha = np.clip(1.0 - np.exp(-np.asarray(confidence, dtype=np.float64) / confirmed), *ALPHA_RANGE)
    out["opacity"] = np.log(alpha / (1.0 - alpha))
    sigma = np.maximum(np.asarray(radius, dtype=np.float64), 1e-6) * SIGMA_PER_RADIUS
    out["scale_0"] = out["scale_1"] = np.log(sigma)
    out["scale_2"] = np.log(sigma * FLAT)
    for i, value in enumerate(z_onto(normal).T):
        out[f"rot_{i}"] = value
    return out


def write_splats(path: str | Path, splats: np.ndarray) -> Path:
    """A binary little-endian PLY of ``splats`` (``gaussians``), written whole or not at all."""
    header = ["ply", "format binary_little_endian 1.0", "comment written by ti-fusion: the surfel map as 3D Gaussians",
              f"element vertex {len(splats)}", *(f"property float {name}" for name in splats.dtype.names),
              "end_header"]
    with atomic_write(Path(path), "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(splats.tobytes())
    return Path(path)


class SplatSink(Sink):
    name = "splats"
    commands = ("slam",)
    flag = "--splats"
    help = ("also splats.ply: the surfel map as 3D Gaussians in 3D Gaussian Splatting's PLY layout (SuperSplat, "
            "PlayCanvas splat-transform, three.js splat viewers; docs/OUTPUTS.md)")

    def finish(self, run: Run) -> dict:
        data = run.step.mapper.to_numpy()
        splats = gaussians(data["position"], data["normal"], data["color"], data["weight"], data["radius"],
                           run.config.fusion.unstable_weight)
        path = write_splats(run.out.file("splats.ply"), splats)
        return {"splats": {"gaussians": len(splats), "file": str(path)}}
