"""``TrackingTerm``: what one tracking term adds to ICP's normal equations, its weight, its stats and its checks.

Per correspondence of the projective association (ICP's: inside the image, distance and normal tests), a
term's per-pixel ``ti.func`` gives one row: (ok, A, r, w), A the 1×6 Jacobian of its residual r with respect
to the left update δξ = (ω, v) (rotation first), w the row's weight (a robust weight, say), ok whether the
pixel has a row. The fused pass (``ti_fusion.kernels.icp``) accumulates Σ w AᵀA (21), Σ w Aᵀr (6), Σ r² and
the row count of each term in registers per chunk, and the solve adds the terms' systems, each times its
weight λ: (Σ_k λ_k Σ w AᵀA) δξ = −Σ_k λ_k Σ w Aᵀr (the first term's λ is 1).
"""

from __future__ import annotations

import math

from ti_fusion.kernels.icp import TermPass


class TrackingTerm:
    """One term of ICP's cost. Subclasses set ``name`` and ``row`` and, as they need, the rest.

    ``row(real)``: a function that makes the term's per-pixel ``ti.func`` for the arithmetic type ``real``
    (ti.f64 on the CPU, ti.f32 elsewhere); the ``ti.func`` is called as ``f(c, mode, src, tgt, settings)``
    with ``c`` a ``ti_fusion.kernels.icp.Correspondence``, ``mode`` the compile-time int ``mode()`` gave,
    ``src`` and ``tgt`` the tuples of fields ``images`` gave (read at row ``c.s0 + v`` of the source, ``c.t0 +
    …`` of the target), ``settings`` a vector of the numbers ``settings()`` gave, and returns (ok, A, r, w).
    Keep it branch-light and in the arithmetic type: it runs for every correspondence of every iteration.
    """

    name: str = ""  # in stats, in ICPResult.terms and in align(terms=...)
    needs: frozenset = frozenset()  # the pyramids' images it reads besides depth's: {"intensity"}
    # its fields in each frame's /slam/stats "icp" object: key → (JSON type, description, the ``stats`` entry)
    stats_fields: dict = {}

    def __init__(self, config):
        self.config = config  # the ICPConfig
        self.check()

    # -- what a term says of itself ----------------------------------------------------------------
    @staticmethod
    def row(real):
        raise NotImplementedError

    def check(self) -> None:
        """Refuse settings the term cannot run with (ValueError, one line naming the key)."""

    def weight(self) -> float:
        """λ, the factor of its system in the sum solved; 0 turns the term off."""
        return 1.0

    def level_weight(self, level: int) -> float:
        """λ at pyramid ``level`` (0 the finest): ``weight()`` unless a term weighs its levels apart."""
        return self.weight()

    def mode(self) -> int:
        """A compile-time choice handed to its ``ti.func`` (e.g. which robust weight): one kernel instance each."""
        return 0

    def settings(self) -> tuple:
        """Up to ``ti_fusion.kernels.icp.TERM_SETTINGS`` numbers its ``ti.func`` reads (e.g. a robust scale)."""
        return ()

    def images(self, source, target, level: int) -> tuple[tuple, tuple]:
        """(source images, target images) its ``ti.func`` reads at ``level``: ``Level`` views (or fields) of the
        pyramids' layout, e.g. ``source.intensity[level]``."""
        return (), ()

    def enabled(self, frame) -> bool:
        """Whether ``frame`` can use the term (e.g. it has registered colour); a term that cannot says why,
        once a run."""
        return True

    def prepare(self, source, target) -> None:
        """Called by ``ICP.align`` with its pyramids before the first pass: a term whose weights depend on the
        frames (e.g. on how its images were made) sets them here."""

    def ready(self, source, target) -> bool:
        """Whether the pyramids hold the images it reads (``needs``)."""
        return True

    def stats(self, sums: dict | None) -> dict:
        """What a result reports of the term from its sums of the last iteration (``unpack_term_sums``: AtA,
        Atb, r2, count; None when it was off): its rows and their RMS residual."""
        if sums is None:
            return {"count": 0, "rms": float("nan")}
        count = sums["count"]
        return {"count": count, "rms": math.sqrt(sums["r2"] / count) if count else float("nan")}

    # -- for ICP -------------------------------------------------------------------------------------
    def kernel_pass(self, source, target, level: int) -> TermPass:
        """The term as the kernels take it at ``level``."""
        src, tgt = self.images(source, target, level)
        return TermPass(type(self).row, self.mode(), tuple(src), tuple(tgt), self.level_weight(level),
                        tuple(self.settings()))
