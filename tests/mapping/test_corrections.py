"""Loop-closure map correction: surfel anchors (written by fusion, moved with the surfels by compaction and
growth) and the per-anchor rigid corrections (``fusion.apply_corrections``) against a NumPy float64
reference, on cpu and vulkan. Maps are a few hundred surfels and frames 70 × 72, so the Vulkan runs stay short.
"""

import numpy as np
import pytest

from ti_fusion.config import FusionConfig
from ti_fusion.geometry import se3_exp
from ti_fusion.kernels.common import BLOCK
from ti_fusion.kernels.surfel_map import SurfelMap
from ti_fusion.kernels.surfels import STORED
from ti_fusion.mapping.mapper import SurfelMapper
from tests.mapping.test_fusion import K, plane_frame


def random_surfels(rng, n, anchors):
    unit = rng.normal(size=(n, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    return {
        "position": rng.uniform(-3.0, 3.0, (n, 3)).astype(np.float32),
        "normal": unit.astype(np.float32),
        "color": rng.uniform(0, 255, (n, 3)).astype(np.float32),
        "weight": rng.uniform(0, 10, n).astype(np.float32),
        "radius": rng.uniform(0, 0.1, n).astype(np.float32),
        "t_created": np.arange(n, dtype=np.int32),  # the surfel's original index
        "t_updated": rng.integers(0, 100, n).astype(np.int32),
        "anchor": np.asarray(anchors, np.int32),
    }


def random_corrections(rng, k):
    return np.stack([se3_exp(np.concatenate([rng.normal(scale=0.2, size=3), rng.normal(scale=0.5, size=3)]))
                     for _ in range(k)])


def ref_apply(data, corrections):
    """float64: surfels of anchor k < K (k ≥ 0) get p ← R_k p + t_k, n ← R_k n; the others keep theirs."""
    p = data["position"].astype(np.float64)
    n = data["normal"].astype(np.float64)
    a = data["anchor"]
    hit = (a >= 0) & (a < len(corrections))
    T = corrections[np.where(hit, a, 0)]
    p_new = np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]
    n_new = np.einsum("nij,nj->ni", T[:, :3, :3], n)
    return np.where(hit[:, None], p_new, p), np.where(hit[:, None], n_new, n), hit


def live_and_stale(smap, n):
    """Every stored attribute of slots [0, n) of the map's arrays, live or not."""
    return {name: getattr(smap.arrays, name).to_numpy()[:n] for name in STORED}


def test_apply_corrections_matches_reference(arch, rng):
    """Random surfels over several blocks with anchors below, inside and above [0, K); one anchor's
    correction is the identity. Surfels removed before (stale slots above the count) are not touched."""
    n_corr = 6
    n = 3 * BLOCK + 17
    data = random_surfels(rng, n, rng.integers(-2, n_corr + 3, n))
    data["weight"][rng.random(n) < 0.2] = 0.5  # removed below: stale slots [count, n) must stay as they are
    corrections = random_corrections(rng, n_corr)
    corrections[2] = np.eye(4)
    smap = SurfelMap(4 * BLOCK)
    smap.from_numpy(data)
    removed = smap.remove(200, True, 1.0, 0)
    assert removed > 20
    m = smap.count
    before = live_and_stale(smap, n)
    live = {k: a[:m] for k, a in before.items()}

    assert smap.apply_corrections(corrections) == n_corr - 1
    after = live_and_stale(smap, n)
    want_p, want_n, hit = ref_apply(live, corrections)
    np.testing.assert_allclose(after["position"][:m], want_p, atol=2e-5, rtol=0)
    np.testing.assert_allclose(after["normal"][:m], want_n, atol=2e-6, rtol=0)
    untouched = ~hit | (live["anchor"] == 2)  # out of range, or the identity
    assert untouched.sum() > 20 and (~untouched).sum() > 100
    for name in ("position", "normal"):
        np.testing.assert_array_equal(after[name][:m][untouched], before[name][:m][untouched])
        np.testing.assert_array_equal(after[name][m:], before[name][m:])  # removed surfels
    for name in set(STORED) - {"position", "normal"}:  # nothing else changes
        np.testing.assert_array_equal(after[name], before[name])


def test_identity_corrections_leave_the_map_bit_identical(arch, rng):
    n = BLOCK + 5
    data = random_surfels(rng, n, rng.integers(0, 4, n))
    data["position"][:7] = -0.0  # a rotation by I would turn -0 + 0 into +0
    data["normal"][7:14] = [0.0, -0.0, -1.0]
    smap = SurfelMap(2 * BLOCK)
    smap.from_numpy(data)
    before = smap.to_numpy(STORED)
    assert smap.apply_corrections(np.stack([np.eye(4)] * 4)) == 0
    assert smap.apply_corrections(np.zeros((0, 4, 4))) == 0
    after = smap.to_numpy(STORED)
    for name in STORED:
        assert after[name].tobytes() == before[name].tobytes(), name


def test_bad_corrections_are_refused(cpu):
    smap = SurfelMap(16)
    with pytest.raises(ValueError, match="shape"):
        smap.apply_corrections(np.eye(4))
    bad = np.eye(4)[None].copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        smap.apply_corrections(bad)


def test_fusion_writes_the_anchor_and_corrections_move_the_map(arch):
    """Two frames of a plane with different anchors: the second frame's merged and new surfels take its
    anchor, the rest keep the first's; correcting the second anchor moves exactly its surfels."""
    pyramid, _ = plane_frame()
    mapper = SurfelMapper(FusionConfig(capacity=20_000, confidence_weighting=False))
    mapper.anchor = 3
    mapper.integrate(pyramid, None, np.eye(4), 0)
    assert np.all(mapper.anchors() == 3)
    shifted = np.eye(4)
    shifted[0, 3] = 0.3  # 15 pixels to the side: part of the plane is seen again, part is new
    mapper.anchor = 7
    stats = mapper.integrate(pyramid, None, shifted, 1)
    got = mapper.to_numpy()
    anchors = mapper.anchors()
    assert stats.merged > 1000 and stats.added > 200
    np.testing.assert_array_equal(anchors, np.where(got["t_updated"] == 1, 7, 3))
    assert (anchors == 3).sum() > 200

    T = np.stack([np.eye(4)] * 8)
    T[7] = se3_exp(np.array([0.0, 0.05, 0.0, 0.1, -0.2, 0.05]))
    assert mapper.apply_corrections(T) == 1
    after = mapper.to_numpy()
    want_p, want_n, _ = ref_apply({**got, "anchor": np.where(anchors == 7, 7, 99)}, T)
    np.testing.assert_allclose(after["position"], want_p, atol=2e-5, rtol=0)
    np.testing.assert_allclose(after["normal"], want_n, atol=2e-6, rtol=0)
    np.testing.assert_array_equal(after["position"][anchors == 3], got["position"][anchors == 3])


def test_anchors_follow_their_surfels_through_growth_and_compaction(arch, rng):
    # growth: the map doubles while the second frame is added; the first frame's anchors are copied over
    pyramid, _ = plane_frame()
    mapper = SurfelMapper(FusionConfig(capacity=100, grow=True, remove_unstable=False))
    mapper.anchor = 1
    mapper.integrate(pyramid, None, np.eye(4), 0)
    n_first = mapper.count
    capacity = mapper.map.capacity
    away = np.eye(4)
    away[:3, 3] = [0.0, 0.0, 1.0]  # the same plane 1 m further: all new surfels
    mapper.anchor = 2
    mapper.integrate(pyramid, None, away, 1)
    assert mapper.map.capacity > capacity
    np.testing.assert_array_equal(mapper.anchors(), np.repeat([1, 2], [n_first, mapper.count - n_first]))
    # compaction: survivors from above the new count move into the holes, their anchors with them
    n = 4 * BLOCK + 9
    data = random_surfels(rng, n, rng.integers(0, 1000, n))
    data["weight"][:] = 5.0
    data["weight"][rng.random(n) < 0.3] = 1.0
    smap = SurfelMap(8 * BLOCK)
    smap.from_numpy(data)
    removed = smap.remove(200, True, 3.0, 0)
    got = smap.to_numpy(STORED)
    assert removed > 50 and smap.count == n - removed
    np.testing.assert_array_equal(got["anchor"], data["anchor"][got["t_created"]])  # t_created = old index
    np.testing.assert_array_equal(got["position"], data["position"][got["t_created"]])


def test_reactivate_matches_reference(arch, rng):
    """Live surfels of weight ≥ the threshold (exactly at it included) get ``t_updated`` = the frame; weaker
    ones and stale slots above the count keep theirs, and nothing else changes."""
    n = 2 * BLOCK + 9
    data = random_surfels(rng, n, rng.integers(0, 4, n))
    data["weight"][rng.random(n) < 0.1] = 3.0
    smap = SurfelMap(3 * BLOCK)
    smap.from_numpy(data)
    removed = smap.remove(200, True, 0.8, 0)  # leaves stale slots [count, n)
    assert removed > 5
    m = smap.count
    before = live_and_stale(smap, n)
    smap.reactivate(250, 3.0)
    after = live_and_stale(smap, n)
    want = np.where(before["weight"][:m].astype(np.float64) >= 3.0, 250, before["t_updated"][:m])
    np.testing.assert_array_equal(after["t_updated"][:m], want)
    assert 0 < (want == 250).sum() < m
    np.testing.assert_array_equal(after["t_updated"][m:], before["t_updated"][m:])
    for name in set(STORED) - {"t_updated"}:
        np.testing.assert_array_equal(after[name], before[name])


def test_unstable_surfels_are_removed_although_loops_reactivate_the_map(cpu, rng):
    """A loop every few frames reactivates the map; the unstable surfels still go after ``unstable_age``
    frames without an update (before, every slot's ``t_updated`` was overwritten and none ever went)."""
    n = BLOCK + 40
    data = random_surfels(rng, n, np.zeros(n))
    data["t_updated"][:] = 0
    smap = SurfelMap(2 * BLOCK)
    smap.from_numpy(data)
    weak = int((data["weight"] < 3.0).sum())
    for frame in range(1, 30):
        if frame % 5 == 0:
            smap.reactivate(frame, 3.0)
        smap.remove(frame, True, 3.0, 20)
    assert smap.count == n - weak


def test_exports_copy_the_live_surfels_and_every_stride_th(arch, rng):
    """``to_numpy``: each attribute asked for (any subset of STORED, in one launch of ``export_stored``) holds
    the live surfels, or every stride-th of them, as the fields do; a name outside STORED (scratch) too."""
    n = BLOCK + 37
    data = random_surfels(rng, n, rng.integers(0, 4, n))
    smap = SurfelMap(2 * BLOCK)
    smap.from_numpy(data)
    fields = {name: getattr(smap.arrays, name).to_numpy()[:n] for name in STORED}
    for names in (STORED, ("position", "color"), ("anchor",), ("weight", "t_updated", "normal")):
        for stride in (1, 3, n + 5):
            got = smap.to_numpy(names, stride)
            assert list(got) == list(names)
            for name in names:
                assert got[name].dtype == fields[name].dtype and got[name].flags.c_contiguous
                np.testing.assert_array_equal(got[name], fields[name][::stride], err_msg=f"{name} / {stride}")
    got = smap.to_numpy(("position", "proj_pixel"), 2)
    np.testing.assert_array_equal(got["proj_pixel"], smap.arrays.proj_pixel.to_numpy()[:n:2])
    np.testing.assert_array_equal(got["position"], fields["position"][::2])
    smap.clear()
    assert {k: v.shape for k, v in smap.to_numpy(("position", "weight")).items()} == {"position": (0, 3), "weight": (0,)}
