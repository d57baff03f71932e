"""The 6×6 Gauss–Newton step of point-to-plane ICP, and the checks that refuse a degenerate system.

The step minimises ‖A δ + b‖² over the twist δ = (ω, v) (rotation first) by a Cholesky solve of the normal
equations AᵀA δ = −Aᵀb from the reduced 6×6 sums. Forming AᵀA squares the condition number, but
``check_system`` refuses cond(AᵀA) above ``icp.max_condition`` (1e7), so float64 keeps about nine digits of δ:
a QR factorisation of the stacked rows, which avoids the squaring, gave the same steps.
"""

from __future__ import annotations

import numpy as np

def condition_number(AtA: np.ndarray) -> float:
    """cond(AᵀA) = λmax / λmin of the symmetric matrix; inf when it is singular or not positive."""
    return float(condition_numbers(np.asarray(AtA, dtype=np.float64)[None])[0])


def condition_numbers(AtA: np.ndarray) -> np.ndarray:
    """``condition_number`` of each of a stack of matrices (n × 6 × 6), in one eigenvalue call."""
    if np.isfinite(AtA).all():  # (every tracked frame's: no selection, no copy)
        return _eigenvalue_ratios(AtA)
    cond = np.full(AtA.shape[0], np.inf)
    finite = np.all(np.isfinite(AtA), axis=(1, 2))
    if finite.any():
        cond[finite] = _eigenvalue_ratios(AtA[finite])
    return cond


def _eigenvalue_ratios(AtA: np.ndarray) -> np.ndarray:
    """λmax / λmin of each finite symmetric matrix of the stack; inf where it is singular or not positive."""
    lam = np.linalg.eigvalsh(AtA)
    ok = (lam[:, -1] > 0) & (lam[:, 0] > lam[:, -1] * 1e-15)
    cond = np.full(AtA.shape[0], np.inf)
    cond[ok] = lam[ok, -1] / lam[ok, 0]
    return cond


def check_system(AtA: np.ndarray, inliers: int, min_inliers: int, max_condition: float,
                 cond: float | None = None) -> tuple[str | None, float]:
    """(failure reason or None, cond(AᵀA)): too few correspondences, rank deficiency, ill-conditioning.
    ``cond``: cond(AᵀA) where the caller has it already (``condition_numbers``)."""
    if inliers < min_inliers:
        return f"too few inliers ({inliers} < {min_inliers})", float("inf")
    cond = condition_number(AtA) if cond is None else float(cond)
    if not np.isfinite(cond):
        rank = int(np.linalg.matrix_rank(AtA)) if np.all(np.isfinite(AtA)) else 0
        return f"rank-deficient AᵀA (rank {rank} < 6)", cond
    if cond > max_condition:
        return f"ill-conditioned AᵀA (cond {cond:.1e} > {max_condition:.0e})", cond
    return None, cond


def solve_normal_equations(AtA: np.ndarray, Atb: np.ndarray) -> np.ndarray:
    """δ with AᵀA δ = −Aᵀb, by Cholesky (AᵀA = L Lᵀ)."""
    AtA = np.asarray(AtA, dtype=np.float64)
    rhs = -np.asarray(Atb, dtype=np.float64)
    L = np.linalg.cholesky(AtA)  # LinAlgError when AᵀA is not positive definite
    return np.linalg.solve(L.T, np.linalg.solve(L, rhs))  # two triangular solves


def weak_directions(AtA: np.ndarray, color_AtA: np.ndarray | None, color_weight: float,
                    weak_ratio: float) -> dict:
    """The eigen-directions of the geometric AᵀA whose eigenvalue is below ``weak_ratio`` × the largest
    (what depth alone leaves unconstrained: two translations and a rotation facing a plane), and whether
    the other tracking terms (``color_weight`` × ``color_AtA``: ICP passes Σ λ_k AᵀA_k of the terms after the
    geometry, with weight 1; the keys keep the photometric term's name, "color", the log's stats read them)
    lift each above that line.

    Returns {"weak": count, "constrained_by_color": count, "directions": [{"twist": unit 6-vector (ω, v),
    largest component positive, "ratio": λ / λmax of the geometry, "joint_ratio": eᵀ(AᵀA + λ_c A_cᵀA_c)e /
    λmax, "color": bool}, ...] (weakest first), "weakest": {"twist", "ratio", "joint_ratio"} of the weakest
    direction whether weak or not (None for a system without a positive eigenvalue)}."""
    AtA = np.asarray(AtA, dtype=np.float64)
    out = {"weak": 0, "constrained_by_color": 0, "directions": [], "weakest": None}
    if not np.all(np.isfinite(AtA)):
        return out
    lam, vec = np.linalg.eigh(AtA)
    top = lam[-1]
    if not top > 0:
        return out
    e0 = vec[:, 0] * np.sign(vec[np.argmax(np.abs(vec[:, 0])), 0])
    joint0 = float(lam[0]) if color_AtA is None else float(e0 @ (AtA + color_weight * color_AtA) @ e0)
    out["weakest"] = {"twist": [float(x) for x in e0], "ratio": float(max(lam[0], 0.0) / top),
                      "joint_ratio": float(max(joint0, 0.0) / top)}
    for i in range(6):
        if lam[i] >= weak_ratio * top:
            break
        e = vec[:, i] * np.sign(vec[np.argmax(np.abs(vec[:, i])), i])
        joint = float(lam[i]) if color_AtA is None else float(e @ (AtA + color_weight * color_AtA) @ e)
        lifted = color_AtA is not None and joint >= weak_ratio * top
        out["directions"].append({"twist": [round(float(x), 3) for x in e], "ratio": float(max(lam[i], 0.0) / top),
                                  "joint_ratio": float(max(joint, 0.0) / top), "color": bool(lifted)})
        out["weak"] += 1
        out["constrained_by_color"] += int(lifted)
    return out
