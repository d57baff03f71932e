"""The depth sensor's noise model, written once: Kinect's axial noise σ(z) = A + B (z − Z0)² metres at depth
z metres (Nguyen, Izadi and Lovell 2012, "Modeling Kinect sensor noise for improved 3D reconstruction and
tracking").

Everything that needs σ(z) takes it from here: ``depth_sigma`` below (NumPy float64: the references and
benchmarks), ``ti_fusion.kernels.common.depth_sigma`` (the kernels: ICP's depth weighting, fusion's
depth-weighted measurements, the renderer's occlusion margin, the synthetic sensor's noise) and, through
``c_defines``, the C programs of the ceiling benchmarks.
"""

from __future__ import annotations

import numpy as np

SIGMA_A = 0.0012  # metres: the noise at Z0
SIGMA_B = 0.0019  # 1/metre: its quadratic growth away from Z0
SIGMA_Z0 = 0.4  # metres
SIGMA_1M = SIGMA_A + SIGMA_B * (1.0 - SIGMA_Z0) ** 2  # σ(1 m): weights are relative to a point at 1 m


def depth_sigma(z) -> np.ndarray:
    """σ(z) in metres of depths z in metres (float64)."""
    dz = np.asarray(z, dtype=np.float64) - SIGMA_Z0
    return SIGMA_A + SIGMA_B * dz * dz


def c_defines() -> tuple[str, ...]:
    """The constants as C compiler flags (``-DSIGMA_A=0.0012`` …), each the shortest decimal that reads
    back as the same double."""
    constants = {"SIGMA_A": SIGMA_A, "SIGMA_B": SIGMA_B, "SIGMA_Z0": SIGMA_Z0, "SIGMA_1M": SIGMA_1M}
    return tuple(f"-D{name}={value!r}" for name, value in constants.items())
