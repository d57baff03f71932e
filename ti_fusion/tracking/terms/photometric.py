"""The photometric term (``icp.color_weight`` λ > 0, docs/PHOTOMETRIC.md): the live frame's intensity against
the model's, at each correspondence.

The model's intensity I_m at the source pixel (``source.intensity``, −1 = none) is compared with the live
frame's at the projection of p′, bilinearly interpolated at x = fx x′/z′ + cx, y = fy y′/z′ + cy (no rounding)
from ``target.intensity_grad`` = (I, ∂I/∂x, ∂I/∂y) per pixel (I < 0 at any of the four taps: no row).
r_c = I(x, y) − I_m; with g = ∂I/∂p′ = (g_x fx/z′, g_y fy/z′, −(g_x fx x′ + g_y fy y′)/z′²) and δp′ = ω × p′ +
v, the row is A_c = [(p′ × g)ᵀ, gᵀ] (the point-to-plane row with the normal replaced by the intensity
gradient in 3-D). Huber weights on r_c (k = ``icp.color_robust_scale``). λ is ``icp.color_weight`` at the
coarse levels and at the finest level too on clean colour; on JPEG-compressed colour (the live frame's
``FramePyramid.blockiness``) the finest level's is ``icp.color_weight`` × ``icp.color_finest_scale``
(``level_weight``, ``finest_scale``). Only where colour is registered to depth (``Frame.color_registered``):
elsewhere the term is off for the frame, said once a run.
"""

import logging
import math

import taichi as ti

from ti_fusion.tracking.terms.base import TrackingTerm

log = logging.getLogger(__name__)


# The live frame's JPEG blockiness (kernels/pyramid.py, ``jpeg_blockiness``) at and below which its colour counts as
# clean (the finest level keeps the whole colour weight) and at and above which as compressed (the finest level's
# weight × icp.color_finest_scale), linear between: the gap between clean and JPEG colour's measured values
# (docs/PHOTOMETRIC.md, "Which colour is real: the frame's JPEG blocks").
CLEAN_BLOCKINESS = 1.4
JPEG_BLOCKINESS = 2.0


def finest_scale(scale: float, blockiness: float) -> float:
    """The finest level's factor on the colour weight for a live frame of ``blockiness``: 1 on clean colour,
    ``scale`` (``icp.color_finest_scale``) on compressed colour, linear between; ``scale`` where the frame's
    blockiness is unknown (NaN)."""
    if math.isnan(blockiness) or blockiness >= JPEG_BLOCKINESS:
        return scale
    if blockiness <= CLEAN_BLOCKINESS:
        return 1.0
    return 1.0 - (1.0 - scale) * (blockiness - CLEAN_BLOCKINESS) / (JPEG_BLOCKINESS - CLEAN_BLOCKINESS)


def row(real):
    """The term's per-pixel ``ti.func`` in arithmetic type ``real`` (``TrackingTerm.row``)."""
    vec3 = ti.types.vector(3, real)

    @ti.func
    def bilinear(ig: ti.template(), t0, x, y):
        """(I, ∂I/∂x, ∂I/∂y) of ``ig`` at the continuous pixel (x, y), 0 ≤ x < W − 1, 0 ≤ y < H − 1, and
        whether all four taps hold an intensity (I ≥ 0)."""
        x0 = ti.cast(x, ti.i32)  # truncation is the floor for x ≥ 0
        y0 = ti.cast(y, ti.i32)
        ax = x - x0
        ay = y - y0
        a = ti.cast(ig[t0 + y0, x0], real)
        b = ti.cast(ig[t0 + y0, x0 + 1], real)
        c = ti.cast(ig[t0 + y0 + 1, x0], real)
        d = ti.cast(ig[t0 + y0 + 1, x0 + 1], real)
        valid = ti.min(ti.min(a[0], b[0]), ti.min(c[0], d[0])) >= 0
        return (1.0 - ay) * ((1.0 - ax) * a + ax * b) + ay * ((1.0 - ax) * c + ax * d), valid

    @ti.func
    def photometric(c: ti.template(), mode: ti.template(), src: ti.template(), tgt: ti.template(), settings):
        """(ok, A_c, r_c, w_c): ok is False where the model has no intensity or the projection's four taps are
        not all inside the target image with an intensity."""
        ok = False
        A = ti.Vector.zero(real, 6)
        r = ti.cast(0.0, real)
        w = ti.cast(0.0, real)
        cscale = settings[0]
        Im = ti.cast(src[0][c.s0 + c.v, c.u], real)
        inv_z = 1.0 / c.pt.z
        x = c.K[0] * c.pt.x * inv_z + c.K[2]
        y = c.K[1] * c.pt.y * inv_z + c.K[3]
        if Im >= 0 and 0 <= x and x < c.Wt - 1 and 0 <= y and y < c.Ht - 1:
            s, valid = bilinear(tgt[0], c.t0, x, y)
            if valid:
                ok = True
                r = s[0] - Im
                gu = s[1] * c.K[0] * inv_z
                gv = s[2] * c.K[1] * inv_z
                g = vec3(gu, gv, -(gu * c.pt.x + gv * c.pt.y) * inv_z)
                pg = c.pt.cross(g)
                A = ti.Vector([pg.x, pg.y, pg.z, g.x, g.y, g.z], dt=real)
                w = 1.0
                a = ti.abs(r)
                if a > cscale:  # Huber
                    w = cscale / a
        return ok, A, r, w

    return photometric


class PhotometricTerm(TrackingTerm):
    name = "photometric"
    needs = frozenset({"intensity"})
    stats_fields = {"color_residuals": ("integer", "photometric residuals of the last iteration (0: the term is off, "
                                                   "icp.color_weight = 0 or colour not registered)", "count")}
    row = staticmethod(row)

    def __init__(self, config):
        super().__init__(config)
        self._warned = False  # the line saying the term is off for frames without registered colour
        self._finest = self.config.color_finest_scale  # the finest level's factor for this alignment (``prepare``)

    def weight(self) -> float:
        return self.config.color_weight

    def level_weight(self, level: int) -> float:
        # on real (JPEG) colour the finest level's intensity gradients pulled pairs off the truth, the coarser levels
        # held them; on clean colour they are information (docs/PHOTOMETRIC.md, real colour)
        return self.config.color_weight * (self._finest if level == 0 else 1.0)

    def prepare(self, source, target) -> None:
        """The finest level's factor from the live frame's (``target``'s) JPEG blockiness."""
        self._finest = finest_scale(self.config.color_finest_scale, getattr(target, "blockiness", float("nan")))

    def settings(self) -> tuple:
        return (self.config.color_robust_scale,)

    def images(self, source, target, level: int) -> tuple[tuple, tuple]:
        return (source.intensity[level],), (target.intensity_grad[level],)

    def ready(self, source, target) -> bool:
        return source.intensity is not None and target.intensity_grad is not None

    def enabled(self, frame) -> bool:
        """Registered colour only; once a run, says that a frame without it is tracked with depth only."""
        if frame.color is not None and frame.color_registered:
            return True
        if not self._warned:
            self._warned = True
            from ti_fusion.config import ICPConfig

            why = "has no colour" if frame.color is None else "has colour that is not registered to depth"
            weight = self.weight()
            # the default weight asks for colour only where it can be used: elsewhere its absence is no news
            say = log.info if weight == ICPConfig.color_weight else log.warning
            say(f"icp.color_weight = {weight:g}, but frame {frame.index} {why}: the photometric tracking "
                "term is off for such frames (depth only); see docs/PHOTOMETRIC.md")
        return False


def photometric(source, target, weight: float, scale: float):
    """The photometric term's ``TermPass`` with images ``source`` (the model's intensity) and ``target`` (the live
    frame's (I, ∂I/∂x, ∂I/∂y)), λ ``weight`` and Huber's k ``scale``: for passes run directly on
    ``PointToPlane`` (tests, benchmarks)."""
    from ti_fusion.kernels.icp import TermPass

    return TermPass(row, 0, (source,), (target,), float(weight), (float(scale),))
