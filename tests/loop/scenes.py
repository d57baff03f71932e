"""Small synthetic views for the loop-closure tests: the room rendered at 320×240 at chosen poses, and
keyframes made from them as the loop closer makes its own (ORB features, depth summary, grid points)."""

import numpy as np

from ti_fusion.config import SynthConfig, VOConfig
from ti_fusion.geometry import make_pose, se3_exp
from ti_fusion.io.datasets.arrays import rgbd_frame
from ti_fusion.loop.keyframes import Keyframe, grid_points
from ti_fusion.tracking.features import extract_features

WIDTH, HEIGHT = 320, 240


def sequence():
    from ti_fusion.synthetic.scene import SyntheticSequence

    return SyntheticSequence(SynthConfig(width=WIDTH, height=HEIGHT, fx=262.5))


def moved(pose: np.ndarray, yaw_deg: float = 0.0, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``pose`` turned by ``yaw_deg`` about its camera's y axis (down) and shifted along its own axes."""
    return pose @ make_pose(se3_exp(np.r_[0.0, np.radians(yaw_deg), 0.0, 0.0, 0.0, 0.0])[:3, :3], np.asarray(shift))


def view(seq, pose: np.ndarray, index: int, seed: int):
    depth, color = seq.render(pose, seed=seed)
    return rgbd_frame(depth, seq.intrinsics, color=color, index=index, timestamp=float(index), gt_pose=pose)


def keyframe(id_: int, frame, pose: np.ndarray, n_features: int = 500) -> Keyframe:
    import cv2

    vo = VOConfig(n_features=n_features)
    features = extract_features(frame, vo, cv2.ORB_create(n_features))
    depth = np.ascontiguousarray(frame.depth, dtype=np.float32)
    return Keyframe(id_, frame.index, frame.timestamp, np.array(pose, dtype=np.float64), features,
                    frame.intrinsics, depth, frame.intrinsics, grid_points(depth, frame.intrinsics))
