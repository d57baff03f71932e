"""Feature-based RGB-D odometry: ORB keypoints, brute-force Hamming matching, 3D–2D PnP with RANSAC.

The classic RGB-D SLAM tutorial's front end, made robust:

1. ORB keypoints and descriptors on the grey colour image (``cv2.ORB_create(n_features)``);
2. brute-force Hamming matching; "good" matches are those with distance < max(factor · d_min, floor)
   (cross-checked matches) or that pass Lowe's ratio test (k = 2 nearest neighbours), per ``VOConfig.match``;
3. the reference frame's matched keypoints are lifted to 3D with ITS depth (depth at the rounded keypoint
   pixel; invalid depth skipped), and ``cv2.solvePnPRansac`` finds the pose of the other frame's camera
   from those 3D points and the matching 2D keypoints, with the depth camera's intrinsics;
4. Rodrigues vector → rotation matrix → 4×4 transform ``T`` with ``p_b = T p_a`` (frame a's camera
   coordinates to frame b's).

A frame is rejected when it has fewer good matches than ``min_good_match``, fewer RANSAC inliers than
``min_inliers``, or a motion norm ‖Δt‖ + min(2π − ‖r‖, ‖r‖) above ``max_norm`` (the tracker only: as an
ICP initialiser or for re-localisation a large motion is the point, and ICP checks the result).

Colour not registered to depth (7-Scenes): a keypoint is found in the colour image but lifted with the
depth at the same pixel of the depth image and back-projected with the depth camera's intrinsics (the
only intrinsics the set gives). Where the two cameras are not registered, that depth belongs to a
slightly different surface point (the cameras sit a few centimetres apart), so (a) at depth edges a
keypoint can take the background's or the foreground's depth: an outlier, which RANSAC mostly
rejects; (b) elsewhere every lifted point is displaced by a smooth, depth-dependent offset, which
RANSAC cannot reject and which biases each estimate. Both frames of a pair share the offset, so the
bias is second order, and neither shifting the depth lookup nor rescaling colour pixels to depth pixels
corrects it (docs/BENCHMARKS.md). The drift is dominated instead by keypoint noise (ORB keypoints on
coarser pyramid levels are localised to about a pixel) through PnP's rotation/translation ambiguity.
Dense ICP on depth alone suffers from neither, which is why the estimate initialises ICP rather
than replacing it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ti_fusion.config import VOConfig
from ti_fusion.frame import Frame
from ti_fusion.geometry import invert, make_pose, orthonormalize
from ti_fusion.timing import Stopwatch

# Why a frame (or a pair) was rejected; None means accepted.
NO_COLOR = "no_color"            # the frame has no colour image: nothing to detect features in
FEW_MATCHES = "few_matches"      # fewer good matches than min_good_match
NO_DEPTH = "no_depth"            # too few good matches with valid depth to solve PnP
FEW_INLIERS = "few_inliers"      # fewer RANSAC inliers than min_inliers (or no PnP solution)
LARGE_MOTION = "large_motion"    # motion norm above max_norm
REASONS = (NO_COLOR, FEW_MATCHES, NO_DEPTH, FEW_INLIERS, LARGE_MOTION)

_MIN_PNP_POINTS = 6  # solvePnPRansac needs at least 4 (P3P + 1); 6 leaves RANSAC something to vote on


# ----------------------------------------------------------------------------------------------------
# Keypoints of one frame
# ----------------------------------------------------------------------------------------------------
@dataclass
class FrameFeatures:
    """ORB keypoints of one frame, with their descriptors and 3D points lifted with the frame's depth.

    ``pixels``: N×2 keypoint positions in the DEPTH image's pixel grid (float64; equal to the colour
    positions when both images have the same size). ``points``: N×3 camera coordinates (metres) from the
    depth at the rounded pixel; rows of NaN where the depth is invalid.
    """

    keypoints: tuple
    descriptors: np.ndarray | None
    pixels: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def grey(color: np.ndarray) -> np.ndarray:
    """8-bit grey image of an RGB (H×W×3) or already grey (H×W) image."""
    color = np.asarray(color)
    if color.ndim == 2:
        return np.ascontiguousarray(color, dtype=np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(color, dtype=np.uint8), cv2.COLOR_RGB2GRAY)


def extract_features(frame: Frame, config: VOConfig | None = None, orb=None) -> FrameFeatures:
    """ORB keypoints and descriptors of ``frame``'s colour image, lifted to 3D with its depth."""
    config = config or VOConfig()
    if frame.color is None:
        return FrameFeatures((), None, np.zeros((0, 2)), np.zeros((0, 3)))
    orb = orb or cv2.ORB_create(config.n_features)
    image = grey(frame.color)
    keypoints, descriptors = orb.detectAndCompute(image, None)
    keypoints = tuple(keypoints)
    if not keypoints:
        return FrameFeatures((), None, np.zeros((0, 2)), np.zeros((0, 3)))
    h_c, w_c = image.shape
    h_d, w_d = frame.depth.shape
    pts = np.array([k.pt for k in keypoints], dtype=np.float64)
    # Colour pixel → depth pixel (pixel centres line up when one image is a rescaled copy of the other).
    pixels = np.column_stack([(pts[:, 0] + 0.5) * w_d / w_c - 0.5, (pts[:, 1] + 0.5) * h_d / h_c - 0.5])
    return FrameFeatures(keypoints, descriptors, pixels, lift(pixels, frame.depth, frame.intrinsics))


def lift(pixels: np.ndarray, depth: np.ndarray, intrinsics) -> np.ndarray:
    """N×3 camera coordinates of ``pixels`` (N×2, u v) with the depth read at the rounded pixel; NaN where invalid."""
    h, w = depth.shape
    u = np.clip(np.rint(pixels[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(pixels[:, 1]).astype(np.int64), 0, h - 1)
    z = depth[v, u].astype(np.float64)
    z[~(np.isfinite(z) & (z > 0))] = np.nan
    K = intrinsics
    # Depth from the rounded pixel, direction from the sub-pixel keypoint (the surface is locally smooth,
    # and b's keypoints, which these points must project onto, are sub-pixel too).
    return np.column_stack([(pixels[:, 0] - K.cx) * z / K.fx, (pixels[:, 1] - K.cy) * z / K.fy, z])


# ----------------------------------------------------------------------------------------------------
# Matching and PnP between two frames
# ----------------------------------------------------------------------------------------------------
def match_features(a: FrameFeatures, b: FrameFeatures, config: VOConfig) -> tuple[list, list]:
    """(all matches, good matches) from ``a`` (query) to ``b`` (train), per ``config.match``."""
    if a.descriptors is None or b.descriptors is None:
        return [], []
    if config.match == "ratio":
        if len(b) < 2:
            return [], []
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False).knnMatch(a.descriptors, b.descriptors, k=2)
        matches = [p[0] for p in pairs if len(p) > 0]
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < config.ratio * p[1].distance]
        return matches, good
    if config.match != "min_distance":
        raise ValueError(f"vo.match must be 'min_distance' or 'ratio', not {config.match!r}")
    matches = list(cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a.descriptors, b.descriptors))
    if not matches:
        return [], []
    d_min = min(m.distance for m in matches)
    threshold = max(config.min_distance_factor * d_min, config.min_distance_floor)
    return matches, [m for m in matches if m.distance < threshold]


def motion_norm(T: np.ndarray) -> float:
    """‖Δt‖ + min(2π − ‖r‖, ‖r‖): the tutorial's size of a motion (metres + radians)."""
    rvec, _ = cv2.Rodrigues(np.asarray(T[:3, :3], dtype=np.float64))
    r = float(np.linalg.norm(rvec))
    return float(np.linalg.norm(T[:3, 3])) + min(2.0 * np.pi - r, r)


@dataclass
class PnPEstimate:
    """Result of matching frame a to frame b and solving PnP.

    ``T``: 4×4 float64 with p_b = T p_a (frame a's camera coordinates → frame b's), or None when no pose
    was found; ``reason``: None when the estimate passes every check, else one of ``REASONS`` (``T`` may
    still be set, e.g. for a motion judged too large). The match lists are kept for visualisation.
    """

    T: np.ndarray | None
    reason: str | None
    keypoints: tuple[int, int] = (0, 0)
    matches: int = 0
    good: int = 0
    lifted: int = 0                  # good matches whose frame-a keypoint has valid depth
    inliers: int = 0
    motion_norm: float = float("nan")
    all_matches: list = field(default_factory=list, repr=False)
    good_matches: list = field(default_factory=list, repr=False)
    inlier_matches: list = field(default_factory=list, repr=False)

    @property
    def ok(self) -> bool:
        return self.reason is None and self.T is not None

    @property
    def pose(self) -> np.ndarray | None:
        """``T`` when the estimate passed its checks, else None: what an initialiser should use."""
        return self.T if self.ok else None


def solve_pnp(a: FrameFeatures, b: FrameFeatures, intrinsics, config: VOConfig,
              check_motion: bool = True) -> PnPEstimate:
    """Pose of frame b's camera relative to frame a's from their features (a lifted with a's depth).

    ``intrinsics``: the depth camera's (the lifted points and b's pixels are in the depth pixel grid).
    """
    all_m, good = match_features(a, b, config)
    est = PnPEstimate(None, None, (len(a), len(b)), len(all_m), len(good), all_matches=all_m, good_matches=good)
    if len(good) < config.min_good_match:
        est.reason = FEW_MATCHES
        return est
    ia = np.array([m.queryIdx for m in good])
    ib = np.array([m.trainIdx for m in good])
    valid = np.isfinite(a.points[ia, 2])
    est.lifted = int(valid.sum())
    if est.lifted < _MIN_PNP_POINTS:
        est.reason = NO_DEPTH
        return est
    lifted_matches = [m for m, v in zip(good, valid) if v]
    object_points = np.ascontiguousarray(a.points[ia[valid]], dtype=np.float64)
    image_points = np.ascontiguousarray(b.pixels[ib[valid]], dtype=np.float64)
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            object_points, image_points, intrinsics.K, None,
            iterationsCount=config.ransac_iterations,
            reprojectionError=config.ransac_reprojection_px,
            confidence=0.99,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
    except cv2.error:  # degenerate configurations (e.g. all points collinear)
        ok, inliers = False, None
    if not ok or inliers is None:
        est.reason = FEW_INLIERS
        return est
    inliers = inliers.ravel()
    est.inliers = int(len(inliers))
    est.inlier_matches = [lifted_matches[i] for i in inliers]
    R, _ = cv2.Rodrigues(rvec)
    est.T = make_pose(orthonormalize(R), tvec.ravel())
    est.motion_norm = motion_norm(est.T)
    if est.inliers < config.min_inliers:
        est.reason = FEW_INLIERS
    elif check_motion and est.motion_norm > config.max_norm:
        est.reason = LARGE_MOTION
    return est


def estimate_relative_pose(frame_a: Frame, frame_b: Frame, config: VOConfig | None = None,
                           check_motion: bool = False) -> PnPEstimate:
    """Relative pose of two frames from ORB + PnP: ``T`` maps frame_a's camera coordinates to frame_b's.

    Stateless (features are computed for both frames on each call). Used to initialise ICP
    (``ICP.align(source=a, target=b, init=est.T)``) and by the SLAM loop to re-localise after a
    tracking failure. ``est.ok`` tells whether the estimate passed the match and inlier checks (at least
    ``config.min_inliers_init`` inliers, stricter than the tracker's ``min_inliers``);
    the motion-size check (``max_norm``) applies only with ``check_motion=True``, because a large
    motion is exactly what an initialiser is for. When ``frame_a`` has no colour, ``reason`` is NO_COLOR.
    """
    config = config or VOConfig()
    if frame_a.color is None or frame_b.color is None:
        return PnPEstimate(None, NO_COLOR)
    orb = cv2.ORB_create(config.n_features)
    fa = extract_features(frame_a, config, orb)
    fb = extract_features(frame_b, config, orb)
    est = solve_pnp(fa, fb, frame_b.intrinsics, config, check_motion=check_motion)
    # Without the motion check a wrong pose is not caught by its size: ask for more inliers instead.
    if est.reason is None and est.inliers < config.min_inliers_init:
        est.reason = FEW_INLIERS
    return est


def relocalise(reference: Frame, reference_pose: np.ndarray, frame: Frame,
               config: VOConfig | None = None) -> np.ndarray | None:
    """Camera-to-world pose guess for ``frame`` from a frame with a known pose, or None when PnP fails.

    For the SLAM loop after a tracking failure: initialise ICP with the returned pose.
    """
    est = estimate_relative_pose(reference, frame, config)
    if not est.ok:
        return None
    return np.asarray(reference_pose, dtype=np.float64) @ invert(est.T)


# ----------------------------------------------------------------------------------------------------
# The tracker
# ----------------------------------------------------------------------------------------------------
@dataclass
class VOResult:
    """What ``FeatureOdometry.register_frame`` reports for one frame.

    ``relative``: p_frame = relative · p_keyframe (keyframe camera → this camera), None when no pose was
    found; ``pose``: camera-to-world of this frame when accepted, else None.
    """

    index: int
    timestamp: float
    accepted: bool
    reason: str | None
    pose: np.ndarray | None
    relative: np.ndarray | None
    keyframe_index: int | None
    keypoints: int = 0
    matches: int = 0
    good: int = 0
    inliers: int = 0
    motion_norm: float = float("nan")
    ms: float = 0.0
    estimate: PnPEstimate | None = field(default=None, repr=False)

    @property
    def status(self) -> str:
        return "accepted" if self.accepted else f"rejected: {self.reason}"

    def stats(self) -> dict:
        """Per-frame numbers for the log (/vo/stats)."""
        return {
            "frame": int(self.index),
            "keyframe": -1 if self.keyframe_index is None else int(self.keyframe_index),
            "keypoints": int(self.keypoints),
            "matches": int(self.matches),
            "good": int(self.good),
            "inliers": int(self.inliers),
            "motion_norm": float(self.motion_norm) if np.isfinite(self.motion_norm) else -1.0,
            "accepted": bool(self.accepted),
            "status": self.status,
            "reason": self.reason or "",
            "ms": round(float(self.ms), 3),
        }


class FeatureOdometry:
    """Frame-to-keyframe ORB + PnP odometry with the tutorial's three rejection rules.

    Each frame is matched against the keyframe, the last ACCEPTED frame; a rejected frame is skipped
    (no pose) and the next one is matched against the same keyframe. The first accepted frame's pose is
    ``initial_pose`` if given, else its ground-truth pose when the dataset has one (so the trajectory is
    directly comparable with ground truth), else the identity.
    """

    def __init__(self, config: VOConfig | None = None, initial_pose: np.ndarray | None = None):
        self.config = config or VOConfig()
        self.initial_pose = initial_pose
        self._orb = cv2.ORB_create(self.config.n_features)
        self.keyframe: FrameFeatures | None = None
        self.keyframe_index: int | None = None
        self.keyframe_pose: np.ndarray | None = None
        self.first_pose_source: str | None = None  # "given" | "ground truth" | "identity"

    def register_frame(self, frame: Frame) -> VOResult:
        watch = Stopwatch()
        result = self._register(frame)
        result.ms = watch.ms
        return result

    def _register(self, frame: Frame) -> VOResult:
        cfg = self.config
        base = dict(index=frame.index, timestamp=frame.timestamp, keyframe_index=self.keyframe_index)
        if frame.color is None:
            return VOResult(accepted=False, reason=NO_COLOR, pose=None, relative=None, **base)
        features = extract_features(frame, cfg, self._orb)
        if self.keyframe is None:
            # The first keyframe needs enough keypoints to be matched against at all.
            if len(features) < cfg.min_good_match:
                return VOResult(accepted=False, reason=FEW_MATCHES, pose=None, relative=None,
                                keypoints=len(features), **base)
            pose = self._first_pose(frame)
            self._make_keyframe(frame, features, pose)
            return VOResult(accepted=True, reason=None, pose=pose.copy(), relative=np.eye(4),
                            keypoints=len(features), motion_norm=0.0, **base)
        est = solve_pnp(self.keyframe, features, frame.intrinsics, cfg, check_motion=True)
        counts = dict(keypoints=len(features), matches=est.matches, good=est.good, inliers=est.inliers,
                      motion_norm=est.motion_norm, estimate=est)
        if not est.ok:
            return VOResult(accepted=False, reason=est.reason, pose=None, relative=est.T, **counts, **base)
        pose = self.keyframe_pose @ invert(est.T)  # T_w,frame = T_w,key · T_key,frame
        self._make_keyframe(frame, features, pose)
        return VOResult(accepted=True, reason=None, pose=pose.copy(), relative=est.T, **counts, **base)

    def _first_pose(self, frame: Frame) -> np.ndarray:
        if self.initial_pose is not None:
            self.first_pose_source = "given"
            return np.asarray(self.initial_pose, dtype=np.float64).copy()
        if frame.gt_pose is not None and np.all(np.isfinite(frame.gt_pose)):
            self.first_pose_source = "ground truth"
            return make_pose(orthonormalize(frame.gt_pose[:3, :3]), frame.gt_pose[:3, 3])
        self.first_pose_source = "identity"
        return np.eye(4)

    def _make_keyframe(self, frame: Frame, features: FrameFeatures, pose: np.ndarray) -> None:
        self.keyframe = features
        self.keyframe_index = frame.index
        self.keyframe_pose = pose


# ----------------------------------------------------------------------------------------------------
# Visualisation
# ----------------------------------------------------------------------------------------------------
def draw_match_panels(frame_a: Frame, frame_b: Frame, config: VOConfig | None = None) -> tuple[np.ndarray, PnPEstimate]:
    """RGB image of three panels stacked vertically: all matches, good matches, RANSAC inliers (a → b)."""
    config = config or VOConfig()
    if frame_a.color is None or frame_b.color is None:
        raise ValueError("both frames need a colour image to draw matches")
    orb = cv2.ORB_create(config.n_features)
    fa = extract_features(frame_a, config, orb)
    fb = extract_features(frame_b, config, orb)
    est = solve_pnp(fa, fb, frame_b.intrinsics, config, check_motion=False)
    img_a = cv2.cvtColor(np.ascontiguousarray(frame_a.color, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    img_b = cv2.cvtColor(np.ascontiguousarray(frame_b.color, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    panels = []
    titles = (f"all matches: {est.matches}", f"good matches: {est.good}",
              f"RANSAC inliers: {est.inliers}" + (f"  ({est.reason})" if est.reason else ""))
    for title, matches in zip(titles, (est.all_matches, est.good_matches, est.inlier_matches)):
        panel = cv2.drawMatches(img_a, list(fa.keypoints), img_b, list(fb.keypoints), matches, None,
                                flags=cv2.DrawMatchesFlags_NOT_DRAW_SINGLE_POINTS)
        scale = max(panel.shape[0] / 480.0, 0.5)
        cv2.putText(panel, title, (10, int(30 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale,
                    (0, 0, 0), int(4 * scale), cv2.LINE_AA)
        cv2.putText(panel, title, (10, int(30 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale,
                    (255, 255, 255), max(int(2 * scale), 1), cv2.LINE_AA)
        panels.append(panel)
    return cv2.cvtColor(np.vstack(panels), cv2.COLOR_BGR2RGB), est
