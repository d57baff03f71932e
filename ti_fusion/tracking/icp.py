"""Projective point-to-plane ICP, coarse to fine: ``ICP(config).align(source, target, init)``.

``source`` and ``target`` are ``FramePyramid`` (or anything with per-level ``vertex``, ``normal`` images, as
``Level`` views or plain fields, and ``intrinsics``) of two depth frames; the result's ``pose`` maps source-camera points into the target
camera, p_target = T p_source. Each iteration is one Taichi pass (association + linearisation +
reduction, ``ti_fusion.kernels.icp``), the 6×6 system is checked and solved and the pose updated on the
left with the exact exponential, T ← exp(δξ) · T, the twist δξ = (ω, v) rotation first.

Where the solve runs: inside the same kernel launch (``PointToPlane.iterate``: a Cholesky solve, float64 on
the CPU, Jacobi-scaled float32 elsewhere), and the records of the iterations are replayed here afterwards
through the same checks (too few inliers, rank, condition number) and bookkeeping, so the result is the
same as solving in NumPy: a failure found on replay rewinds to the pose before that iteration, and a system
the kernel refused but NumPy accepts goes on in NumPy (the sums cross every iteration, Cholesky in float64).

Tracking terms (``ti_fusion.tracking.terms``): the geometric one (point to plane) is always on; the others
``align(..., terms=(name, ...))`` names (each with weight λ > 0; e.g. "photometric", docs/PHOTOMETRIC.md) join it
in the same pass (``ti_fusion.kernels.icp``: each term's sums beside the geometric ones) and the system solved is
AᵀA + Σ λ_k A_kᵀA_k, Aᵀb + Σ λ_k A_kᵀr_k; the checks (condition number) are those of that system.
``ICPResult.degeneracy`` reports the weak eigen-directions of the geometric AᵀA of the last iteration and
whether the other terms constrained them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ti_fusion.backend import current_backend
from ti_fusion.config import ICPConfig
from ti_fusion.geometry import rigidity_error, se3_exp, unflatten_pose
from ti_fusion.kernels.icp import (FAILED, R_ITERATION, R_LEVEL, R_OUTCOME, R_POSE, R_UPDATE, SUM_INLIERS, SUM_R2,
                                   SUM_SOURCE, UPDATED, PointToPlane, combined_system, combined_systems, n_terms_of,
                                   record_sums, unpack_sums, unpack_term_sums)
from ti_fusion.tracking.solve import check_system, condition_numbers, solve_normal_equations, weak_directions
from ti_fusion.tracking.terms import make_terms


@dataclass
class IterationRecord:
    """One ICP iteration: pyramid level (0 = finest), iteration within the level, the mean squared
    point-to-plane residual and the correspondence count at the pose before the update, and ‖δξ‖."""

    level: int
    iteration: int
    loss: float
    inliers: int
    update_norm: float = float("nan")


@dataclass
class ICPResult:
    """Outcome of ``ICP.align``.

    pose: 4×4 float64, source camera → target camera (p_target = T p_source). On a failure, the last
    good estimate (the pose before the degenerate iteration).
    converged: no failure and the last update ‖δξ‖ passed its level's stop test (``ICP.stop_update``).
    failure: None, or a short reason ("too few inliers (12 < 100)", "ill-conditioned AᵀA (cond ...)").
    inliers, inlier_ratio (inliers / valid source pixels), residual_rms (metres), condition (cond AᵀA),
    update_norm: of the last iteration that ran.
    """

    pose: np.ndarray
    converged: bool = False
    failure: str | None = None
    iterations: list[IterationRecord] = field(default_factory=list)
    inliers: int = 0
    inlier_ratio: float = 0.0
    residual_rms: float = float("nan")
    condition: float = float("nan")
    update_norm: float = float("nan")
    terms: dict = field(default_factory=dict)  # each term but the first that ran: name → its stats of the last
                                               # iteration (``TrackingTerm.stats``: rows and RMS residual)
    weights: tuple = (1.0,)  # λ of each term of the last iteration's pass (at its level), in the order of their sums
    degeneracy: dict | None = None  # weak geometric directions (``ti_fusion.tracking.solve.weak_directions``)
    sums: np.ndarray | None = field(default=None, repr=False)  # the last iteration's sums (``n_sums``)

    @property
    def color_inliers(self) -> int:
        """The photometric term's rows in the last iteration (0: the term was off)."""
        return int(self.terms.get("photometric", {}).get("count", 0))

    @property
    def color_rms(self) -> float:
        """The RMS intensity residual of those, in [0, 1] units."""
        return float(self.terms.get("photometric", {}).get("rms", float("nan")))

    def table(self) -> list[dict]:
        """The per-iteration records as plain dicts (for summary.json)."""
        return [{"level": r.level, "iteration": r.iteration, "loss": r.loss, "inliers": r.inliers,
                 "update_norm": r.update_norm} for r in self.iterations]


_SHARED: dict = {}  # the PointToPlane pass of the running backend


class ICP:
    """Coarse-to-fine projective point-to-plane ICP with the kernels of the running Taichi backend."""

    def __init__(self, config: ICPConfig | None = None):
        self.config = config or ICPConfig()
        self.terms = make_terms(self.config)  # every registered term, the geometric one first
        self._terms = self.terms[:1]  # this align call's (``align``)

    def term(self, name: str):
        """The registered term called ``name`` (ValueError naming the registered ones for another)."""
        for term in self.terms:
            if term.name == name:
                return term
        raise ValueError(f"no tracking term {name!r} (terms: {', '.join(t.name for t in self.terms)})")

    def terms_for(self, frame) -> tuple[str, ...]:
        """The terms after the geometric one that ``frame`` can use: weight > 0 and ``enabled(frame)`` (a term
        that cannot says why, once)."""
        return tuple(t.name for t in self.terms[1:] if t.weight() > 0 and t.enabled(frame))

    def needs(self, names) -> frozenset:
        """The pyramids' images the named terms read (``TrackingTerm.needs``)."""
        return frozenset().union(*(self.term(n).needs for n in names))

    def ready(self, names, source, target) -> tuple[str, ...]:
        """Those of the named terms whose images the pyramids hold."""
        return tuple(n for n in names if self.term(n).ready(source, target))

    def _kernels(self, n_pixels: int) -> PointToPlane:
        """The pass of the current backend, sized for ``n_pixels``, shared by every ICP object: Taichi
        compiles a kernel once per set of fields it is given, so a shared pass compiles once per pair of
        maps rather than once per ICP object (rebuilt after a backend change)."""
        backend = current_backend()
        shared = _SHARED.get("pass")
        if shared is None or _SHARED.get("backend") is not backend or shared.max_pixels < n_pixels:
            shared = PointToPlane(n_pixels, backend.has_f64)
            _SHARED.update({"pass": shared, "backend": backend})
        return shared

    def dist_threshold(self, level: int) -> float:
        """d_thr at a pyramid level: coarse levels start further from the solution, so they may accept
        correspondences further apart (``level_dist_scale`` ** level)."""
        return self.config.dist_threshold * self.config.level_dist_scale ** level

    def stop_update(self, level: int) -> float:
        """The update ‖δξ‖ below which a level stops: ``icp.stop_update`` at the finest, doubled per coarser
        level, whose pixels are twice as large as the next finer's (the pyramid halves the image per level; a
        coarse level need not converge finer than it can see)."""
        return self.config.stop_update * 2 ** level

    def _converged(self, result: ICPResult) -> bool:
        """Whether the last iteration's update passed its level's stop test."""
        level = result.iterations[-1].level if result.iterations else 0
        return bool(result.update_norm < self.stop_update(level))

    def align(self, source, target, init: np.ndarray | None = None, terms=()) -> ICPResult:
        """Align ``source`` to ``target`` starting from ``init`` (identity when None), with the geometric term
        and the registered terms named in ``terms`` whose weight is > 0 (in the registry's order; their images,
        e.g. the photometric term's ``source.intensity`` and ``target.intensity_grad``, must be computed)."""
        cfg = self.config
        for name in terms:
            self.term(name)  # an unknown name: ValueError
        self._terms = [self.terms[0]] + [t for t in self.terms[1:] if t.name in terms and t.weight() > 0]
        for term in self._terms:
            term.prepare(source, target)
        n_levels = len(cfg.iterations)
        if source.levels < n_levels or target.levels < n_levels:
            raise ValueError(f"icp.iterations has {n_levels} levels but the maps have "
                             f"{min(source.levels, target.levels)}")
        T = np.eye(4) if init is None else np.array(init, dtype=np.float64)
        problem = rigidity_error(T)
        if problem:
            raise ValueError(f"initial pose: {problem}")
        kernels = self._kernels(source.shapes[0][0] * source.shapes[0][1])
        result = ICPResult(pose=T)
        schedule = list(zip(reversed(range(n_levels)), cfg.iterations))  # (level, iterations), coarse → fine
        resume = (0, 0)
        if kernels.solves_in_kernel:
            resume = self._align_in_kernel(kernels, source, target, schedule, result)
        if resume is not None:
            self._align_in_python(kernels, source, target, schedule, result, resume)
        if result.sums is not None:
            others = None  # Σ λ_k AᵀA_k of the other terms: what they add along the geometry's weak directions
            # each term's lift at its own weight(), not its last level's: whether it holds a direction, as the slide
            # starts ask, not how much a lighter finest level pulls on it
            for k in range(1, n_terms_of(result.sums)):
                part = self._terms[k].weight() * unpack_term_sums(result.sums, k)["AtA"]
                others = part if others is None else others + part
            result.degeneracy = weak_directions(unpack_sums(result.sums)["AtA"], others, 1.0, cfg.weak_ratio)
        return result

    def _passes(self, source, target, level: int) -> list:
        """This align's terms as the kernels take them at ``level``."""
        return [t.kernel_pass(source, target, level) for t in self._terms]

    def _align_in_kernel(self, kernels: PointToPlane, source, target, schedule, result: ICPResult):
        """Every iteration one launch of the ``iterate`` kernel, which solves and updates the pose itself
        (float64, Cholesky); then its records are replayed here through the same checks and bookkeeping as
        ``_align_in_python``. Per iteration that saves the round trip through NumPy (the sums out, the
        check, the solve, the SE(3) update, the pose back in), which takes as long as a small pass itself.
        Returns None when done, or the (stage, iteration) to go on from in Python, with
        ``result.pose`` set, if the kernel refused a system that NumPy's checks accept."""
        cfg = self.config
        kernels.begin_iterations(result.pose, sum(n for _, n in schedule))
        for level, n_iter in schedule:  # every level's settings first: they cross to a GPU in one copy
            if n_iter:
                kernels.begin_level(source.vertex[level], source.normal[level], target.vertex[level],
                                    target.normal[level], target.intrinsics[level].as_tuple(),
                                    self.dist_threshold(level), cfg.normal_threshold_deg, level, cfg.min_inliers,
                                    self.stop_update(level), self._passes(source, target, level))
        for level, n_iter in schedule:
            done = 0
            for it in range(n_iter):
                done = kernels.iterate(it, level)  # on a GPU always 0: the device skips what follows a stop
                if done:
                    break
            if done == FAILED:
                break
        n_levels = len(schedule)
        records = kernels.iteration_records()
        sums = record_sums(records, len(self._terms))
        # every record's system and condition number at once: one eigenvalue call rather than one per record
        levels = records[:, R_LEVEL].astype(int)
        systems = combined_systems(sums, [np.array([t.level_weight(level) for level in levels])[:, None]
                                          for t in self._terms])
        conds = condition_numbers(systems[0])
        for k, record in enumerate(records):
            level, it = int(record[R_LEVEL]), int(record[R_ITERATION])
            if self._record(result, level, it, sums[k], (systems[0][k], systems[1][k]), conds[k]) is None:
                result.pose = unflatten_pose(record[R_POSE:R_POSE + 12])
                return None  # a failure, reported as the NumPy path reports it
            if record[R_OUTCOME] != UPDATED:
                result.pose = unflatten_pose(record[R_POSE:R_POSE + 12])
                result.iterations.pop()  # recorded again by the NumPy path
                return n_levels - 1 - level, it
            result.iterations[-1].update_norm = result.update_norm = float(record[R_UPDATE])
        result.pose = kernels.pose()
        result.converged = self._converged(result)
        return None

    def _align_in_python(self, kernels: PointToPlane, source, target, schedule, result: ICPResult,
                         start: tuple[int, int] = (0, 0)) -> None:
        """The sums of each iteration to NumPy, checked, solved (Cholesky) and applied there; from
        ``start`` = (stage of ``schedule``, iteration) at ``result.pose``."""
        for stage, (level, n_iter) in enumerate(schedule):
            if stage < start[0]:
                continue
            for it in range(start[1] if stage == start[0] else 0, n_iter):
                delta = self._iteration(kernels, source, target, level, it, result)
                if delta is None:  # degenerate: keep the last good pose
                    return
                result.pose = se3_exp(delta) @ result.pose
                result.iterations[-1].update_norm = result.update_norm = float(np.linalg.norm(delta))
                if result.update_norm < self.stop_update(level):
                    break
        result.converged = self._converged(result)

    def _record(self, result: ICPResult, level: int, it: int, sums: np.ndarray,
                system: tuple[np.ndarray, np.ndarray] | None = None, cond: float | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
        """Record an iteration's sums in ``result`` and check its system (AᵀA, Aᵀb; ``system`` and its
        ``cond`` where the caller has them): the system, or None (with ``result.failure`` set) when it is
        degenerate."""
        cfg = self.config
        sums = np.asarray(sums, dtype=np.float64)
        n, sources = int(round(sums[SUM_INLIERS])), int(round(sums[SUM_SOURCE]))
        loss = float(sums[SUM_R2]) / n if n else float("nan")
        result.iterations.append(IterationRecord(level, it, loss, n))
        result.inliers = n
        result.inlier_ratio = n / sources if sources else 0.0
        result.residual_rms = math.sqrt(loss) if n else float("nan")
        result.sums = sums
        for k, term in enumerate(self._terms[1:], start=1):
            s = unpack_term_sums(sums, k)
            s["count"] = int(round(s["count"]))
            result.terms[term.name] = term.stats(s)
        result.weights = tuple(t.level_weight(level) for t in self._terms)
        AtA, Atb = combined_system(sums, result.weights) if system is None else system
        failure, result.condition = check_system(AtA, n, cfg.min_inliers, cfg.max_condition, cond)
        if failure is not None:
            result.failure = f"level {level} iteration {it}: {failure}"
            return None
        return AtA, Atb

    def _iteration(self, kernels: PointToPlane, source, target, level: int, it: int,
                   result: ICPResult) -> np.ndarray | None:
        """One associate + linearise + solve at ``result.pose``: records it in ``result`` and returns δξ,
        or None after setting ``result.failure`` when the system is degenerate."""
        cfg = self.config
        args = (source.vertex[level], source.normal[level], target.vertex[level], target.normal[level],
                result.pose, target.intrinsics[level].as_tuple(), self.dist_threshold(level),
                cfg.normal_threshold_deg)
        sums = kernels.reduce(*args, self._passes(source, target, level))
        system = self._record(result, level, it, sums)
        if system is None:
            return None
        failure = delta = None
        try:
            delta = solve_normal_equations(*system)
            if not np.all(np.isfinite(delta)):
                failure, delta = "non-finite update", None
        except np.linalg.LinAlgError as exc:
            failure = f"solver failed ({exc})"
        if failure is not None:
            result.failure = f"level {level} iteration {it}: {failure}"
        return delta
