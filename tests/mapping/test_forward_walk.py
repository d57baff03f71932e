"""Walking towards a surface: the model prediction's coarse levels must not empty out.

Surfels fused from afar lie farther apart on screen than the pixels once the camera comes nearer, and the
fusion step adds no surfel at a pixel whose point lies on the disc of a surfel merged at a neighbouring
pixel (``fusion.skip_covered``), so a render that shows each surfel at its own pixel only has holes in a
lattice up to two pixels wide. A coarse pyramid pixel exists only where its centre fine pixel has depth,
so the coarse levels aliased against that lattice and emptied: on the synthetic corridor loop tracking
was lost at the coarsest level. ``SurfelMapper.render_pyramid`` therefore builds the pyramid from a render
whose holes take a neighbour's disc (``mapper.FILL_HALF``), and level 0 keeps the surfels' own
pixels (filling it too doubled the synthetic room's ATE).
"""

import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import FusionConfig, PyramidConfig
from ti_fusion.kernels.pyramid import FramePyramid
from ti_fusion.mapping import mapper
from ti_fusion.mapping.mapper import SurfelMapper

K = Intrinsics(fx=64.0, fy=64.0, cx=39.5, cy=29.5, width=80, height=60)
RAW = PyramidConfig(depth_smooth_radius=0)
STEPS = 11  # 5 cm each: from 2.6 m to 2.1 m in front of the wall


def wall_depth(c: float) -> np.ndarray:
    """Depth of the plane z + 0.3 x = 3 m (a slanted wall) seen from the camera at (0, 0, c), looking along +z."""
    v, u = np.mgrid[0 : K.height, 0 : K.width].astype(np.float64)
    return ((3.0 - c) / (1.0 + 0.3 * (u - K.cx) / K.fx)).astype(np.float32)


def walk() -> tuple[np.ndarray, list[np.ndarray]]:
    """Fuse the wall at known poses while walking towards it. Before each frame, the prediction at its pose:
    per step the fraction of pixels with depth at levels 0, 1, 2, and level 0's depth."""
    mapper = SurfelMapper(FusionConfig(capacity=100_000))
    pyramid = FramePyramid(RAW, K.height, K.width, levels=1)
    predicted = FramePyramid(RAW, K.height, K.width, levels=3)
    covered, level0 = [], []
    for k in range(STEPS):
        pose = np.eye(4)
        pose[2, 3] = 0.4 + 0.05 * k
        if k > 0:
            mapper.render_pyramid(predicted, pose, K)
            depth = [predicted.depth[level].to_numpy() for level in range(3)]
            covered.append([float((d > 0).mean()) for d in depth])
            level0.append(depth[0])
        pyramid.compute(wall_depth(pose[2, 3]), K)
        mapper.integrate(pyramid, None, pose, k)
    return np.array(covered), level0


@pytest.mark.slow
def test_coarse_levels_stay_dense_walking_forward(cpu, monkeypatch):
    filled, level0 = walk()
    assert filled[:, 1:].min() > 0.95, filled
    # what the default prevents: without the fill, level 0 thins out and the coarse levels alias against it
    monkeypatch.setattr(mapper, "FILL_HALF", 0)
    sparse, level0_sparse = walk()
    assert sparse[-1, 0] < 0.8 and sparse[-1, 2] < filled[-1, 2] - 0.15, sparse
    # level 0 is the surfels' own pixels either way
    for a, b in zip(level0, level0_sparse):
        np.testing.assert_array_equal(a, b)
