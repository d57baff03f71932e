"""Vectorised NumPy float64 version of one ICP pass: association, linearisation, reduction.

The same math as ``ti_fusion.kernels.icp`` (read its docstring for the conventions). ``icp_pass`` is the
reference the kernel tests compare against: it also returns every pixel's status code. ``LevelIteration``
is the baseline of ``scripts/bench_icp.py``: the same sums with nothing else, as a NumPy ICP would run
them (the source masked once per level, no status image). Inputs are H×W×3 vertex and normal maps (any
float dtype; computed in float64), a 4×4 pose mapping source points into the target camera and the target
level's (fx, fy, cx, cy).
"""

from __future__ import annotations

import numpy as np

from ti_fusion.kernels.icp import (N_SUMS, STATUS_BEHIND, STATUS_NORMAL_ANGLE, STATUS_OK, STATUS_OUT_OF_IMAGE,
                                   STATUS_SOURCE_INVALID, STATUS_TARGET_INVALID, STATUS_TOO_FAR, SUM_ATB,
                                   SUM_INLIERS, SUM_R2, SUM_SOURCE, TERM_COUNT, TERM_R2, UPPER, n_sums, term_offset)
from ti_fusion.sensor import SIGMA_1M, depth_sigma


def robust_weights(r: np.ndarray, robust: str, scale: float, z: np.ndarray | None = None) -> np.ndarray:
    """Huber: 1 up to k, k/|r| beyond; Tukey: (1 − (r/c)²)² up to c, 0 beyond; none: 1. With
    "+depth" (e.g. "huber+depth"), r is first divided by the depth noise σ(z) at the target depth z
    (relative to 1 m) and the weight multiplied by 1/σ(z)² (likewise)."""
    name, _, depth = robust.partition("+")
    s = np.ones_like(r)
    if depth == "depth":
        s = SIGMA_1M / depth_sigma(z)
    a = np.abs(r * s)
    if name == "huber":
        w = np.where(a > scale, scale / np.maximum(a, 1e-300), 1.0)
    elif name == "tukey":
        w = np.where(a < scale, (1.0 - (a / scale) ** 2) ** 2, 0.0)
    else:
        w = np.ones_like(r)
    return w * s * s


def associate(src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold: float, normal_threshold_deg: float):
    """Correspondences of one pass.

    Returns (status H×W int32 or None, rows) where rows holds, for the STATUS_OK pixels in pixel order,
    ``p`` (p′ = R p + t), ``q``, ``nq`` (float64 m×3) and ``sources`` (the count of valid source pixels).
    """
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    fx, fy, cx, cy = (float(k) for k in K)
    Ht, Wt = tgt_v.shape[:2]
    P = src_v.reshape(-1, 3)
    N = src_n.reshape(-1, 3)
    status = np.full(P.shape[0], STATUS_SOURCE_INVALID, dtype=np.int32)

    idx = np.flatnonzero((P[:, 2] > 0) & np.any(N != 0, axis=1))
    p = P[idx].astype(np.float64) @ R.T + t
    status[idx] = STATUS_BEHIND
    front = p[:, 2] > 0
    idx, p = idx[front], p[front]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u = np.floor(fx * p[:, 0] / p[:, 2] + cx + 0.5)
        v = np.floor(fy * p[:, 1] / p[:, 2] + cy + 0.5)
    status[idx] = STATUS_OUT_OF_IMAGE
    inside = (u >= 0) & (u < Wt) & (v >= 0) & (v < Ht)
    idx, p = idx[inside], p[inside]
    flat = v[inside].astype(np.int64) * Wt + u[inside].astype(np.int64)
    q = tgt_v.reshape(-1, 3)[flat].astype(np.float64)
    nq = tgt_n.reshape(-1, 3)[flat].astype(np.float64)
    status[idx] = STATUS_TARGET_INVALID
    ok = (q[:, 2] > 0) & np.any(nq != 0, axis=1)
    idx, p, q, nq = idx[ok], p[ok], q[ok], nq[ok]
    status[idx] = STATUS_TOO_FAR
    d = p - q
    ok = np.einsum("ij,ij->i", d, d) < float(dist_threshold) ** 2
    idx, p, q, nq = idx[ok], p[ok], q[ok], nq[ok]
    status[idx] = STATUS_NORMAL_ANGLE
    n_rot = N[idx].astype(np.float64) @ R.T
    ok = np.einsum("ij,ij->i", n_rot, nq) > np.cos(np.radians(normal_threshold_deg))
    idx, p, q, nq = idx[ok], p[ok], q[ok], nq[ok]
    status[idx] = STATUS_OK
    sources = int(np.count_nonzero(status != STATUS_SOURCE_INVALID))
    return status.reshape(src_v.shape[:2]), {"p": p, "q": q, "nq": nq, "sources": sources}


def linearise(p: np.ndarray, q: np.ndarray, nq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (m×6) = [(p′ × n_q)ᵀ, n_qᵀ] and r (m) = n_qᵀ (p′ − q)."""
    A = np.concatenate([np.cross(p, nq), nq], axis=1)
    r = np.einsum("ij,ij->i", nq, p - q)
    return A, r


def reduce_sums(A: np.ndarray, r: np.ndarray, w: np.ndarray, sources: int) -> np.ndarray:
    """The 30 sums in the kernel's order (21 upper AᵀA, 6 Aᵀb, Σr², inliers, sources)."""
    wA = A * w[:, None]
    AtA = wA.T @ A
    sums = np.zeros(N_SUMS)
    sums[:21] = [AtA[i, j] for i, j in UPPER]
    sums[SUM_ATB:SUM_ATB + 6] = wA.T @ r
    sums[SUM_R2] = r @ r
    sums[SUM_INLIERS] = r.shape[0]
    sums[SUM_SOURCE] = sources
    return sums


def icp_pass(src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold: float, normal_threshold_deg: float,
             robust: str = "none", robust_scale: float = 0.01):
    """(status H×W, sums[30]) of one pass: the float64 reference of ``PointToPlane.reduce``/``status``."""
    status, c = associate(src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold, normal_threshold_deg)
    A, r = linearise(c["p"], c["q"], c["nq"])
    return status, reduce_sums(A, r, robust_weights(r, robust, robust_scale, c["q"][:, 2]), c["sources"])


def bilinear(ig: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m×3 values, valid) of the H×W×3 image ``ig`` = (I, ∂I/∂x, ∂I/∂y) at continuous pixels (x, y) inside
    [0, W − 1) × [0, H − 1); valid where all four taps have I ≥ 0."""
    ig = np.asarray(ig, dtype=np.float64)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    a, b, c, d = ig[y0, x0], ig[y0, x0 + 1], ig[y0 + 1, x0], ig[y0 + 1, x0 + 1]
    valid = np.minimum(np.minimum(a[:, 0], b[:, 0]), np.minimum(c[:, 0], d[:, 0])) >= 0
    return (1 - ay) * ((1 - ax) * a + ax * b) + ay * ((1 - ax) * c + ax * d), valid


def photometric_rows(p: np.ndarray, pixels: np.ndarray, src_i: np.ndarray, tgt_ig: np.ndarray, K):
    """The colour term at the correspondences p′ (m×3) of the flat source pixels ``pixels``: (A_c k×6,
    r_c k) for those with a model intensity whose projection's four taps lie in the target with one
    (``ti_fusion.tracking.terms.photometric``'s docstring has the math)."""
    fx, fy, cx, cy = (float(k) for k in K)
    Ht, Wt = tgt_ig.shape[:2]
    Im = np.asarray(src_i, dtype=np.float64).reshape(-1)[pixels]
    x = fx * p[:, 0] / p[:, 2] + cx
    y = fy * p[:, 1] / p[:, 2] + cy
    inside = (Im >= 0) & (x >= 0) & (x < Wt - 1) & (y >= 0) & (y < Ht - 1)
    p, Im, x, y = p[inside], Im[inside], x[inside], y[inside]
    s, valid = bilinear(tgt_ig, x, y)
    p, Im, s = p[valid], Im[valid], s[valid]
    z = p[:, 2]
    gu, gv = s[:, 1] * fx / z, s[:, 2] * fy / z
    g = np.stack([gu, gv, -(gu * p[:, 0] + gv * p[:, 1]) / z], axis=1)
    return np.concatenate([np.cross(p, g), g], axis=1), s[:, 0] - Im


def joint_pass(src_v, src_n, tgt_v, tgt_n, src_i, tgt_ig, T, K, dist_threshold: float, normal_threshold_deg: float,
               robust: str = "none", robust_scale: float = 0.01, color_scale: float = 0.05) -> np.ndarray:
    """The 59 sums of a pass with the point-to-plane and the photometric term: the reference of
    ``PointToPlane.reduce`` with those two terms: the 30 of ``icp_pass``, then the colour term's 21 AᵀA, 6 Aᵀb,
    Σr_c² and count (Huber weights, k = ``color_scale``)."""
    status, c = associate(src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold, normal_threshold_deg)
    A, r = linearise(c["p"], c["q"], c["nq"])
    sums = np.zeros(n_sums(2))
    sums[:N_SUMS] = reduce_sums(A, r, robust_weights(r, robust, robust_scale, c["q"][:, 2]), c["sources"])
    Ac, rc = photometric_rows(c["p"], np.flatnonzero(status.reshape(-1) == STATUS_OK), src_i, tgt_ig, K)
    sums[term_offset(1):] = term_sums(Ac, rc, robust_weights(rc, "huber", color_scale))
    return sums


def term_sums(A: np.ndarray, r: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A tracking term's 29 sums from its rows (k×6), residuals and weights: 21 AᵀA, 6 Aᵀb, Σr², count."""
    s = reduce_sums(A, r, w, 0)
    out = np.zeros(TERM_COUNT + 1)
    out[:27], out[TERM_R2], out[TERM_COUNT] = s[:27], s[SUM_R2], s[SUM_INLIERS]
    return out


class LevelIteration:
    """One ICP iteration at one pyramid level as a lean NumPy ICP runs it: the valid source points are
    gathered once per level (they do not change between its iterations), and each call transforms them,
    associates, linearises and reduces, with no per-pixel status. ``sums(T)`` equals ``icp_pass``'s sums.
    """

    def __init__(self, src_v, src_n, tgt_v, tgt_n, K, dist_threshold: float, normal_threshold_deg: float,
                 robust: str = "none", robust_scale: float = 0.01):
        P = src_v.reshape(-1, 3)
        N = src_n.reshape(-1, 3)
        valid = (P[:, 2] > 0) & np.any(N != 0, axis=1)
        self.p = P[valid].astype(np.float64)
        self.n = N[valid].astype(np.float64)
        self.tgt_v = tgt_v.reshape(-1, 3)
        self.tgt_n = tgt_n.reshape(-1, 3)
        self.Ht, self.Wt = tgt_v.shape[:2]
        self.K = tuple(float(k) for k in K)
        self.dist2 = float(dist_threshold) ** 2
        self.cos = float(np.cos(np.radians(normal_threshold_deg)))
        self.robust, self.robust_scale = robust, robust_scale

    def sums(self, T) -> np.ndarray:
        T = np.asarray(T, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        fx, fy, cx, cy = self.K
        p = self.p @ R.T + t
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            u = np.floor(fx * p[:, 0] / z + cx + 0.5)
            v = np.floor(fy * p[:, 1] / z + cy + 0.5)
        sel = np.flatnonzero((z > 0) & (u >= 0) & (u < self.Wt) & (v >= 0) & (v < self.Ht))
        p = p[sel]
        flat = v[sel].astype(np.int64) * self.Wt + u[sel].astype(np.int64)
        q = self.tgt_v[flat].astype(np.float64)
        nq = self.tgt_n[flat].astype(np.float64)
        d = p - q
        ok = (q[:, 2] > 0) & np.any(nq != 0, axis=1) & (np.einsum("ij,ij->i", d, d) < self.dist2)
        ok &= np.einsum("ij,ij->i", self.n[sel] @ R.T, nq) > self.cos
        p, q, nq = p[ok], q[ok], nq[ok]
        A, r = linearise(p, q, nq)
        w = robust_weights(r, self.robust, self.robust_scale, q[:, 2])
        return reduce_sums(A, r, w, self.p.shape[0])
