"""slam.active_window (ElasticFusion's active model): surfels last updated before the window are not
rendered for tracking; without a window (the default) the whole map is."""

import numpy as np
import taichi as ti

from ti_fusion.camera import Intrinsics
from ti_fusion.kernels.common import INT_MAX
from ti_fusion.kernels.surfel_map import SurfelMap

K = Intrinsics(fx=40.0, fy=40.0, cx=19.5, cy=14.5, width=40, height=30)


def test_surfels_older_than_the_window_are_not_rendered(arch, rng):
    n = 600
    u = rng.uniform(0, K.width, n)
    v = rng.uniform(0, K.height, n)
    z = rng.uniform(1.0, 2.0, n)
    pos = np.column_stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z]).astype(np.float32)
    t_updated = rng.integers(0, 20, n).astype(np.int32)
    data = {"position": pos, "normal": np.tile(np.float32([0, 0, -1]), (n, 1)),
            "color": np.full((n, 3), 128, np.float32), "weight": np.full(n, 5.0, np.float32),
            "radius": np.full(n, 0.01, np.float32), "t_created": np.zeros(n, np.int32), "t_updated": t_updated}
    smap = SurfelMap(2048)
    smap.from_numpy(data)
    out = ti.Vector.field(3, ti.f32, shape=(K.height, K.width)), ti.Vector.field(3, ti.f32, shape=(
        K.height, K.width)), ti.field(ti.f32, shape=(K.height, K.width))
    pose = np.eye(4)

    def rendered(**kw):
        img = smap.render(pose, K, *out, max_half=0, **kw)
        index = img.view_index.to_numpy()
        return set(index[index != INT_MAX].tolist())

    everything = rendered()
    assert any(t_updated[i] < 10 for i in everything)  # the old surfels are there without a window
    active = rendered(min_time=10)
    assert active and all(t_updated[i] >= 10 for i in active)
    # each active surfel that won its pixel in the whole map still wins it in the active model
    assert {i for i in everything if t_updated[i] >= 10} <= active
    assert rendered(min_time=0) == everything
