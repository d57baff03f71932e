"""Tracking terms behind one interface (``ti_fusion.tracking.terms``): the registry, and a third term registered
from this test by one line, its sums against NumPy float64 and what it does to the solve.

The third term, ``TranslationPrior``, pulls the translation of ICP's pose along one axis towards a target:
r = t[axis] − t*[axis], one row per correspondence. With the left update T ← exp(δξ) T the translation moves by
δt = ω × t + v, so its row is A = [(t × e)ᵀ, eᵀ], e the axis' unit vector."""

import numpy as np
import pytest
import taichi as ti

from ti_fusion.backend import current_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import ICPConfig
from ti_fusion.kernels import icp as kicp
from ti_fusion.reference import icp as icp_numpy
from ti_fusion.tracking import terms
from ti_fusion.tracking.icp import ICP
from ti_fusion.tracking.terms.base import TrackingTerm
from ti_fusion.tracking.terms.point_to_plane import point_to_plane
from tests.tracking.test_icp import (THETA, THR, assert_sums_close, cs_scale, pass_for,  # noqa: F401
                                     random_pass_inputs, random_pose, sequence, synthetic_pair, vec_field)


def prior_row(real):
    @ti.func
    def prior(c: ti.template(), mode: ti.template(), src: ti.template(), tgt: ti.template(), settings):
        e = ti.Vector.unit(3, mode, real)
        te = c.t.cross(e)
        return True, ti.Vector([te.x, te.y, te.z, e.x, e.y, e.z], dt=real), c.t[mode] - settings[mode], \
            ti.cast(1.0, real)

    return prior


class TranslationPrior(TrackingTerm):
    name = "prior"
    row = staticmethod(prior_row)
    axis, target, strength = 0, (0.0, 0.0, 0.0), 0.0  # set by the tests

    def weight(self) -> float:
        return self.strength

    def mode(self) -> int:
        return self.axis

    def settings(self) -> tuple:
        return tuple(self.target)


def test_the_registry_starts_with_the_geometry():
    names = [cls.name for cls in terms.term_classes()]
    assert names[:2] == ["point_to_plane", "photometric"] and len(set(names)) == len(names)
    icp = ICP(ICPConfig())
    assert [t.name for t in icp.terms] == names
    with pytest.raises(ValueError, match="no tracking term 'nope'"):
        icp.term("nope")


def test_a_term_s_sums_match_numpy(arch, rng):
    """Each term's 29 sums in the one pass: the prior's are the count of correspondences times its row's
    (float64 to rounding; float32 within 1e-4 of each sum's Cauchy–Schwarz bound, counts exact)."""
    T = random_pose(rng, 0.1)
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t)
    kp = pass_for(P.shape[0] * P.shape[1])
    target = (0.03, -0.02, 0.01)
    passes = [point_to_plane("huber", 0.05), kicp.TermPass(prior_row, 1, (), (), 2.0, target)]
    sums = kp.reduce(vec_field(P), vec_field(N), vec_field(Vt), vec_field(Nt), T, K_t.as_tuple(), THR, THETA, passes)
    _, ref = icp_numpy.icp_pass(P, N, Vt, Nt, T, K_t.as_tuple(), THR, THETA, "huber", 0.05)
    n = int(ref[kicp.SUM_INLIERS])
    assert sums.shape == (kicp.n_sums(2),) and n > 50
    assert_sums_close(sums[:kicp.N_SUMS], ref)
    t, e = T[:3, 3], np.array([0.0, 1.0, 0.0])
    A = np.tile(np.concatenate([np.cross(t, e), e]), (n, 1))
    want = icp_numpy.term_sums(A, np.full(n, t[1] - target[1]), np.ones(n))
    got = sums[kicp.term_offset(1):]
    assert got[kicp.TERM_COUNT] == want[kicp.TERM_COUNT] == n
    if current_backend().has_f64:
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    else:  # (the prior's AᵀA is zero off its axis' entries, where the bound is 0 too)
        err = np.abs(got - want) / np.maximum(cs_scale(np.append(want, 0.0))[:kicp.TERM_SUMS], 1e-30)
        assert err.max() < 1e-4, f"float32 sums off by {err.max():.2e} of their scale"
    AtA, Atb = kicp.combined_system(sums, (1.0, 2.0))  # the solve's system: λ = 2 times the prior's
    np.testing.assert_allclose(AtA, kicp.unpack_sums(sums)["AtA"] + 2.0 * kicp.unpack_term_sums(sums, 1)["AtA"])
    np.testing.assert_allclose(Atb, kicp.unpack_sums(sums)["Atb"] + 2.0 * kicp.unpack_term_sums(sums, 1)["Atb"])


def test_three_terms_in_one_pass(cpu, rng):
    """Geometry, colour and the prior in one pass (88 sums): each term's sums where ``term_offset`` puts them."""
    from tests.tracking.test_photometric import random_intensities, scalar_field
    from ti_fusion.tracking.terms.photometric import photometric

    T = random_pose(rng, 0.1)
    K_t = Intrinsics(120.0, 110.0, 27.3, 20.6, 56, 40)
    P, N, Vt, Nt = random_pass_inputs(rng, T, K_t)
    P, src_i, tgt_ig = random_intensities(rng, P, T, K_t)
    kp = pass_for(P.shape[0] * P.shape[1])
    target = (0.01, 0.02, -0.03)
    passes = [point_to_plane("huber+depth", 0.05), photometric(scalar_field(src_i), vec_field(tgt_ig), 0.3, 0.2),
              kicp.TermPass(prior_row, 2, (), (), 5.0, target)]
    sums = kp.reduce(vec_field(P), vec_field(N), vec_field(Vt), vec_field(Nt), T, K_t.as_tuple(), THR, THETA, passes)
    assert sums.shape == (kicp.n_sums(3),) == (88,)
    joint = icp_numpy.joint_pass(P, N, Vt, Nt, src_i, tgt_ig, T, K_t.as_tuple(), THR, THETA, "huber+depth", 0.05, 0.2)
    np.testing.assert_allclose(sums[:kicp.n_sums(2)], joint, rtol=1e-5, atol=1e-12)
    n = int(joint[kicp.SUM_INLIERS])
    t, e = T[:3, 3], np.array([0.0, 0.0, 1.0])
    want = icp_numpy.term_sums(np.tile(np.concatenate([np.cross(t, e), e]), (n, 1)), np.full(n, t[2] - target[2]),
                               np.ones(n))
    np.testing.assert_allclose(sums[kicp.term_offset(2):], want, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_a_third_term_is_one_registration_line(cpu, rng, sequence, monkeypatch):
    """Registered by one line, the prior joins the pass where its weight is > 0: strong, it holds the pose's
    x translation at its target against the depth (which alone recovers the true motion); at weight 0 it is
    off and the alignment is the depth-only one, bit for bit."""
    monkeypatch.setattr(terms, "TERMS", terms.TERMS + ("tests.tracking.test_terms:TranslationPrior",))
    cfg = ICPConfig(iterations=[10, 5, 10])
    src, tgt, G = synthetic_pair(sequence, rng, noise=False)
    free = ICP(cfg).align(src, tgt)
    assert free.failure is None and abs(free.pose[0, 3] - G[0, 3]) < 1e-3
    monkeypatch.setattr(TranslationPrior, "target", (G[0, 3] + 0.02, 0.0, 0.0))
    monkeypatch.setattr(TranslationPrior, "strength", 0.0)
    off = ICP(cfg).align(src, tgt, terms=("prior",))
    np.testing.assert_array_equal(off.pose, free.pose)
    assert off.terms == {} and off.weights == (1.0,)
    monkeypatch.setattr(TranslationPrior, "strength", 1e4)
    held = ICP(cfg).align(src, tgt, terms=("prior",))
    assert held.failure is None and held.weights == (1.0, 1e4)
    assert held.terms["prior"]["count"] == held.inliers > 1000
    assert abs(held.pose[0, 3] - (G[0, 3] + 0.02)) < 1e-3  # the prior wins along x
    assert abs(held.pose[0, 3] - free.pose[0, 3]) > 0.015
