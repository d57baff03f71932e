"""The pose graph of the keyframes, optimised with GTSAM.

Nodes: keyframe poses (camera-to-world). Edges: odometry between consecutive keyframes (the tracked
relative pose, Gaussian with ``loop.odometry_sigma_*``, or with ``loop.odometry_from_icp`` a full covariance
shaped by the tracked frames' ICP AᵀA: ``frame_covariance``, ``edge_covariance``), with ``loop.keyframe_pnp``
a second relative pose of consecutive keyframes from PnP on their ORB features (``add_relative``), and
loops (the verified relative pose, with ``loop.loop_sigma_*`` under a robust kernel, ``loop.robust``). The
first keyframe is held by a tight prior (the map's frame).

The default kernel is Geman–McClure, minimised by graduated non-convexity (GTSAM's ``GncLMOptimizer``,
Yang et al. 2020) with the odometry edges and the prior known inliers: it starts from the convex (least
squares) problem and makes the kernel less convex step by step, so a true loop that starts tens of
standard deviations away (drift) is still pulled closed, while a loop that contradicts the odometry chain
ends with a weight near zero. Loops whose final weight is below ``GNC_MIN_WEIGHT`` are outliers;
the poses are then polished by Levenberg–Marquardt over the odometry and the inlier loops (Gaussian).
Plain LM with a Cauchy or Huber kernel (``loop.robust = "cauchy"`` / ``"huber"``) from the drifted
estimate leaves such a loop open: its residual starts where the kernel's weight is already tiny.

Why GTSAM: a maintained library made for exactly this (factor graphs on SE(3), robust noise models,
Levenberg–Marquardt / iSAM2), with Python wheels on PyPI for the Pythons we support; the graphs here (tens
to hundreds of keyframes) solve in milliseconds, so nothing incremental is needed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from ti_fusion.config import LoopConfig
from ti_fusion.geometry import hat, invert, renormalize, se3_log
from ti_fusion.timing import Stopwatch

PRIOR_SIGMA = 1e-6  # radians and metres: the first keyframe does not move
# With odometry_from_icp, a whitened direction weaker than the strongest gets variance × 1 / (λ/λmax): the inverse
# information, scaled so that the strongest keeps the constant sigma (the ratio 0.01 tried first did worse).
ODOMETRY_INFO_RATIO = 1.0
ODOMETRY_MAX_SCALE = 1e6  # that variance factor at most (the sigma × 1000); an untracked frame's in every direction
FREE_SIGMA = 1.0  # a loop edge's sigma along a direction its measurement does not fix (units of the unit twist: m, rad)
GNC_MIN_WEIGHT = 0.1  # a loop edge that GNC leaves with a weight below this is an outlier (GNC drives them to ~0)


@dataclass
class Edge:
    """A relative-pose measurement between keyframes ``i`` and ``j``: T = T_wi⁻¹ T_wj."""

    i: int
    j: int
    T: np.ndarray
    loop: bool
    covariance: np.ndarray | None = None  # 6×6 in GTSAM's Pose3 tangent order (ω, v); None: the constant sigmas
    robust: bool = False  # a non-loop edge under a Huber kernel (the keyframes' PnP edges)


@dataclass
class Optimised:
    """The outcome of ``PoseGraph.optimise``: the keyframes' poses, each loop edge's error afterwards (in
    its standard deviations, as a Mahalanobis norm over the six components), the total error before and
    after, LM's iterations and the milliseconds it took."""

    poses: np.ndarray  # (K, 4, 4)
    loop_errors: dict[tuple[int, int], float] = field(default_factory=dict)
    error_before: float = 0.0
    error_after: float = 0.0
    iterations: int = 0
    ms: float = 0.0
    outliers: list[tuple[int, int]] = field(default_factory=list)  # loop edges GNC gave a weight below the minimum


def _sigmas(rot_deg: float, trans_m: float) -> np.ndarray:
    """GTSAM's Pose3 tangent order: rotation first, then translation."""
    return np.array([np.radians(rot_deg)] * 3 + [trans_m] * 3)


def adjoint(T: np.ndarray) -> np.ndarray:
    """The 6×6 adjoint of T in the (ω, v) order: T exp(ξ) T⁻¹ = exp(Ad(T) ξ)."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = hat(t) @ R
    return Ad


def frame_covariance(AtA: np.ndarray | None, config: LoopConfig) -> np.ndarray:
    """One tracked frame's share of an odometry edge's covariance, in its camera's frame ((ω, v), right
    perturbation of its camera-to-world pose), before the 1/frames scaling: the constant sigmas' diagonal D², reshaped
    by ICP's geometric AᵀA. Whitened by D, the eigen-directions whose eigenvalue is at least
    ``ODOMETRY_INFO_RATIO`` of the largest keep variance 1 (the constant sigma); weaker ones get
    ``ODOMETRY_INFO_RATIO / (λ/λmax)``, at most ``ODOMETRY_MAX_SCALE``. No (or a non-finite, or zero) AᵀA: the
    maximum in every direction (a frame that was not tracked)."""
    D = np.diag(_sigmas(config.odometry_sigma_deg, config.odometry_sigma_m))
    scale = np.full(6, ODOMETRY_MAX_SCALE)
    vec = np.eye(6)
    if AtA is not None and np.all(np.isfinite(AtA)):
        Hw = D @ np.asarray(AtA, dtype=np.float64) @ D
        lam, vec = np.linalg.eigh(0.5 * (Hw + Hw.T))
        if lam[-1] > 0:
            ratio = np.maximum(lam, 0.0) / lam[-1]
            with np.errstate(divide="ignore"):
                scale = np.clip(ODOMETRY_INFO_RATIO / ratio, 1.0, ODOMETRY_MAX_SCALE)
        else:
            vec = np.eye(6)
    return D @ (vec * scale) @ vec.T @ D


def edge_covariance(frames: list[tuple[np.ndarray, np.ndarray]], pose_j: np.ndarray) -> np.ndarray:
    """An odometry edge's covariance (keyframe j's frame, GTSAM's BetweenFactor convention) from the frames
    tracked since keyframe i, keyframe j included: each (camera-to-world pose, ``frame_covariance``) moved into
    j's frame with the adjoint of T_j⁻¹ T_f and summed (first order, independent frames), divided by their
    number so that an edge whose frames all observed every direction keeps the constant sigmas."""
    inv_j = invert(pose_j)
    total = np.zeros((6, 6))
    for pose, cov in frames:
        Ad = adjoint(inv_j @ pose)
        total += Ad @ cov @ Ad.T
    total /= max(len(frames), 1)
    return 0.5 * (total + total.T)


class PoseGraph:
    """Keyframe poses, odometry and loop edges; ``optimise`` returns corrected poses."""

    def __init__(self, config: LoopConfig):
        self.config = config
        self.poses: list[np.ndarray] = []  # the current estimate of each keyframe's pose
        self.edges: list[Edge] = []
        self._odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(_sigmas(config.odometry_sigma_deg,
                                                                         config.odometry_sigma_m))
        self._loop_sigmas = _sigmas(config.loop_sigma_deg, config.loop_sigma_m)
        self._loop_gaussian = gtsam.noiseModel.Diagonal.Sigmas(self._loop_sigmas)
        self._loop_noise = self._loop_kernel(self._loop_gaussian)

    def _loop_kernel(self, gaussian):
        """A loop edge's noise model: ``gaussian`` under the robust kernel of ``loop.robust`` (cauchy, huber),
        or as it is (none; gnc, which weighs the loops itself)."""
        if self.config.robust in ("none", "gnc"):
            return gaussian
        kernels = {"cauchy": gtsam.noiseModel.mEstimator.Cauchy, "huber": gtsam.noiseModel.mEstimator.Huber}
        return gtsam.noiseModel.Robust.Create(kernels[self.config.robust].Create(self.config.robust_scale), gaussian)

    def __len__(self) -> int:
        return len(self.poses)

    def add_keyframe(self, pose: np.ndarray, covariance: np.ndarray | None = None, chained: bool = True) -> int:
        """A new keyframe at ``pose``; from the second on, an odometry edge from the previous one (the
        relative pose of the two current estimates) with ``covariance`` (6×6, (ω, v), ``edge_covariance``),
        or the constant sigmas when None; none when not ``chained`` (a new session's first keyframe: the
        caller ties it to the map with ``add_relative``). Returns its id."""
        pose = np.asarray(pose, dtype=np.float64)
        if self.poses and chained:
            i = len(self.poses) - 1
            self.edges.append(Edge(i, i + 1, renormalize(invert(self.poses[i]) @ pose), loop=False,
                                   covariance=covariance))
        self.poses.append(pose.copy())
        return len(self.poses) - 1

    def add_relative(self, i: int, j: int, T_ij: np.ndarray) -> None:
        """A relative-pose edge that does not come from tracking (``loop.keyframe_pnp``: PnP between consecutive
        keyframes), T_ij = T_wi⁻¹ T_wj, with the loop sigmas under a Huber kernel; like odometry, a known
        inlier of GNC."""
        self.edges.append(Edge(i, j, np.asarray(T_ij, dtype=np.float64), loop=False,
                               covariance=np.diag(self._loop_sigmas ** 2), robust=True))

    def add_loop(self, i: int, j: int, T_ij: np.ndarray, free=()) -> None:
        """A loop edge: T_ij = T_wi⁻¹ T_wj measured (keyframe j's camera in keyframe i's). ``free``: unit twists
        ((ω, v), keyframe j's frame) along which the measurement says nothing (the weak directions of
        verification's depth-only ICP, e.g. a slide along a plain wall): the edge's sigma there is
        ``FREE_SIGMA``, so the graph keeps that component from odometry instead of from the loop."""
        covariance = None
        if len(free):
            covariance = np.diag(self._loop_sigmas ** 2)
            for e in free:
                e = np.asarray(e, dtype=np.float64)
                e = e / np.linalg.norm(e)
                covariance += FREE_SIGMA ** 2 * np.outer(e, e)
        self.edges.append(Edge(i, j, np.asarray(T_ij, dtype=np.float64), loop=True, covariance=covariance))

    def remove_loop(self, i: int, j: int) -> None:
        self.edges = [e for e in self.edges if not (e.loop and (e.i, e.j) == (i, j))]

    def loop_error(self, edge: Edge, poses) -> float:
        """The loop edge's error at ``poses``, in its standard deviations (Mahalanobis norm)."""
        E = invert(edge.T) @ invert(poses[edge.i]) @ poses[edge.j]
        xi = se3_log(E)  # (ω, v): the same order as the sigmas
        if edge.covariance is not None:
            return float(np.sqrt(xi @ np.linalg.solve(edge.covariance, xi)))
        return float(np.linalg.norm(xi / self._loop_sigmas))

    def optimise(self) -> Optimised:
        """Optimise every keyframe pose from the current estimates (GNC, then LM over the inliers; or LM
        with the configured kernel). ``loop_errors`` covers every loop edge, outliers included."""
        watch = Stopwatch()
        initial = gtsam.Values()
        for k, pose in enumerate(self.poses):
            initial.insert(k, gtsam.Pose3(pose))
        gnc = self.config.robust == "gnc"
        loops = [e for e in self.edges if e.loop]
        inliers = loops
        iterations = 0
        if gnc and loops:
            graph = self._graph(loops, self._loop_gaussian)
            params = gtsam.GncLMParams()
            params.setKnownInliers(list(range(1 + len(self.edges) - len(loops))))  # the prior and odometry
            params.setLossType(gtsam.GncLossType.GM)
            optimizer = gtsam.GncLMOptimizer(graph, initial, params)
            initial = optimizer.optimize()
            weights = np.asarray(optimizer.getWeights())[-len(loops):]
            inliers = [e for e, w in zip(loops, weights) if w >= GNC_MIN_WEIGHT]
        graph = self._graph(inliers, self._loop_gaussian if gnc else self._loop_noise)
        start = gtsam.Values()
        for k, pose in enumerate(self.poses):
            start.insert(k, gtsam.Pose3(pose))
        error_before = float(graph.error(start))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-9)
        params.setAbsoluteErrorTol(1e-12)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = optimizer.optimize()
        iterations += int(optimizer.iterations())
        poses = np.stack([renormalize(result.atPose3(k).matrix()) for k in range(len(self.poses))])
        out = Optimised(poses, error_before=error_before, error_after=float(graph.error(result)),
                        iterations=iterations)
        out.loop_errors = {(e.i, e.j): self.loop_error(e, poses) for e in loops}
        out.outliers = [(e.i, e.j) for e in loops if e not in inliers]
        out.ms = watch.ms
        return out

    def _graph(self, loops: list[Edge], loop_noise) -> gtsam.NonlinearFactorGraph:
        """The prior, the odometry edges (in that order: GNC's known inliers are their indices), then ``loops``."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(self.poses[0]),
                                         gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)))
        for e in self.edges:
            if not e.loop:
                noise = self._odometry_noise if e.covariance is None else \
                    gtsam.noiseModel.Gaussian.Covariance(e.covariance)
                if e.robust:
                    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), noise)
                graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T), noise))
        for e in loops:
            noise = loop_noise
            if e.covariance is not None:
                noise = gtsam.noiseModel.Gaussian.Covariance(e.covariance)
                if loop_noise is not self._loop_gaussian:  # the robust kernel over this covariance too
                    noise = self._loop_kernel(noise)
            graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T), noise))
        return graph

    def set_poses(self, poses: np.ndarray) -> None:
        """Take optimised poses as the current estimates."""
        self.poses = [p.copy() for p in poses]
