"""The geometric term: point-to-plane ICP's residual, always on and first in a pass.

r = n_qᵀ (p′ − q). With the update applied on the left, T ← exp(δξ) T, δξ = (ω, v) rotation first, to first
order exp(δξ) p′ ≈ p′ + ω × p′ + v, so r(δξ) ≈ r + (p′ × n_q)ᵀ ω + n_qᵀ v: the row A = [(p′ × n_q)ᵀ, n_qᵀ].
Its weight w: 1, Huber or Tukey on r (``icp.robust``, k = ``icp.robust_scale``), with ``icp.depth_weighting``
on r / σ(z) and times 1/σ(z)², σ the depth noise at the target point relative to 1 m (``ti_fusion.sensor``).
Its row count is the pass's inlier count. The robust weight is a compile-time choice (the term's ``mode``).
"""

import taichi as ti

from ti_fusion.kernels.common import depth_noise_scale
from ti_fusion.tracking.terms.base import TrackingTerm

ROBUST_CODES = {"none": 0, "huber": 1, "tukey": 2}
# Added to a robust code: residuals weighted by the depth noise σ(z) at the target point: a point at 3 m is ~10×
# noisier than one at 1 m, and weighting all alike lets the far, noisy ones pull the pose. Scaled so the
# weight is 1 at 1 m.
DEPTH_WEIGHTED = 4


def robust_code(robust: str) -> int:
    """"huber", or "huber+depth" for the depth-weighted variant (DEPTH_WEIGHTED): the term's mode."""
    name, _, depth = robust.partition("+")
    return ROBUST_CODES[name] + (DEPTH_WEIGHTED if depth == "depth" else 0)


def row(real):
    """The term's per-pixel ``ti.func`` in arithmetic type ``real`` (``TrackingTerm.row``)."""

    @ti.func
    def weight(r, robust: ti.template(), scale, z):
        """The robust weight of residual r at target depth z (robust: ROBUST_CODES, + DEPTH_WEIGHTED)."""
        s = ti.cast(1.0, real)
        if ti.static(robust >= DEPTH_WEIGHTED):  # r in units of the noise at 1 m, weight 1/σ(z)² likewise
            s = depth_noise_scale(z, real)
        rn = r * s
        w = ti.cast(1.0, real)
        if ti.static(robust % DEPTH_WEIGHTED == 1):  # Huber: quadratic up to k, linear beyond
            a = ti.abs(rn)
            if a > scale:
                w = scale / a
        elif ti.static(robust % DEPTH_WEIGHTED == 2):  # Tukey's biweight: zero beyond c
            w = 0.0
            if ti.abs(rn) < scale:
                u = 1.0 - (rn / scale) * (rn / scale)
                w = u * u
        return w * s * s

    @ti.func
    def point_to_plane(c: ti.template(), mode: ti.template(), src: ti.template(), tgt: ti.template(), settings):
        """(True, A, r, w): every correspondence has a row."""
        pn = c.pt.cross(c.nq)
        A = ti.Vector([pn.x, pn.y, pn.z, c.nq.x, c.nq.y, c.nq.z], dt=real)
        r = c.nq.dot(c.pt - c.q)
        return True, A, r, weight(r, mode, settings[0], c.q.z)

    return point_to_plane


class PointToPlaneTerm(TrackingTerm):
    name = "point_to_plane"
    row = staticmethod(row)

    def check(self) -> None:
        if self.config.robust not in ROBUST_CODES:
            raise ValueError(f"icp.robust {self.config.robust!r}: choose one of {', '.join(ROBUST_CODES)}")

    @property
    def robust(self) -> str:
        """``icp.robust``, with "+depth" when ``icp.depth_weighting`` is on."""
        return self.config.robust + ("+depth" if self.config.depth_weighting else "")

    def mode(self) -> int:
        return robust_code(self.robust)

    def settings(self) -> tuple:
        return (self.config.robust_scale,)


def point_to_plane(robust: str = "none", scale: float = 0.01):
    """The geometric term's ``TermPass`` with robust mode ``robust`` ("huber+depth", ...) and scale ``scale``:
    for passes run directly on ``PointToPlane`` (tests, benchmarks)."""
    from ti_fusion.kernels.icp import TermPass

    return TermPass(row, robust_code(robust), (), (), 1.0, (float(scale),))
