"""The embedded synthetic RGB-D sequence: a scene of ``scenes.py`` (built from ``shapes.py``), its camera
path, a Taichi renderer.

``SyntheticSequence`` renders frame i of a catalogue scene (``scenes.get_scene``) or of any ``Scene`` with
its own noise seed; the primitives, the room and its path are in ``shapes.py`` (imported here too).
"""

from __future__ import annotations

import zlib

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import SynthConfig
from ti_fusion.synthetic.scenes import get_scene
from ti_fusion.synthetic.shapes import (  # noqa: F401 (callers import the scene from here too)
    FPS, T0, ROOM_MIN, ROOM_MAX, Material, Plane, Box, Sphere, Cylinder, Primitive, Scene, default_scene,
    look_at, camera_path, _signed_distance)


MIN_TRAJECTORY_POSES = 2


def read_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, camera-to-world poses) of a TUM trajectory file to render, one frame per pose.

    Refused with an ``InputError`` naming the file: missing or unreadable, a line that is not 8 numbers,
    a quaternion that is not a rotation, fewer than two poses, timestamps not increasing.
    """
    from pathlib import Path

    from ti_fusion.errors import InputError
    from ti_fusion.io.trajectory import read_tum

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trajectory file not found" if not path.exists() else "trajectory is not a file")
    stamps, poses = read_tum(path)
    if len(poses) < MIN_TRAJECTORY_POSES:
        raise InputError(path, f"trajectory has only {len(poses)} pose, need at least {MIN_TRAJECTORY_POSES}")
    if not np.all(np.isfinite(stamps)) or not np.all(np.isfinite(poses)):
        raise InputError(path, "trajectory holds NaN or infinite values")
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise InputError(path, f"timestamps must increase: pose {k + 1} ({stamps[k]:.6f}) is not after pose {k} "
                               f"({stamps[k - 1]:.6f})")
    return stamps, poses


# -- seeds ---------------------------------------------------------------------------------------------
def _mix(*values: int) -> int:
    """A 32-bit seed from integers (splitmix64 steps): stable across runs and platforms."""
    x = 0x9E3779B97F4A7C15
    for v in values:
        x = (x ^ (int(v) & 0xFFFFFFFFFFFFFFFF)) * 0xBF58476D1CE4E5B9 & 0xFFFFFFFFFFFFFFFF
        x = (x ^ (x >> 31)) * 0x94D049BB133111EB & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 29
    return x & 0xFFFFFFFF


def frame_seed(seed: int, index: int) -> int:
    """The noise seed of frame ``index`` of a sequence with ``seed``."""
    return _mix(seed, index)


# -- the sequence --------------------------------------------------------------------------------------
class SyntheticSequence:
    """The embedded RGB-D sequence: ``len(cfg.frames)`` poses at 30 Hz and a renderer for any pose.

    ``frame(i)`` renders frame i with its own noise seed (derived from ``cfg.seed`` and i); ``render``
    renders any pose. Rendering runs on the current Taichi backend (started on the CPU if none is).
    """

    def __init__(self, cfg: SynthConfig | None = None, scene: Scene | None = None):
        from ti_fusion.kernels.scene_render import SceneRenderer, SensorModel

        self.cfg = cfg or SynthConfig()
        c = self.cfg
        self.spec = get_scene(c.scene)
        self.scene = scene or self.spec.build()
        self.intrinsics = Intrinsics(fx=c.fx, fy=c.fx, cx=(c.width - 1) / 2.0, cy=(c.height - 1) / 2.0,
                                     width=c.width, height=c.height)
        if c.trajectory:
            stamps, poses = read_trajectory(c.trajectory)
            n = min(c.frames or len(poses), len(poses))
            self.timestamps, self.poses = stamps[:n], poses[:n]
        else:
            self.timestamps = T0 + self.spec.times(c.frames or self.spec.frames)
            self.poses = self.spec.path(self.timestamps - T0)
        self.sensor = SensorModel(min_range=c.min_range, max_range=c.max_range, grazing_deg=c.grazing_deg,
                                  baseline=c.baseline, subpixel=c.subpixel, sensor_width=c.sensor_width,
                                  color_sigma=c.color_noise, depth_noise_scale=c.depth_noise_scale)
        self._caster = SceneRenderer(self.scene.table())
        self.last_labels: np.ndarray | None = None  # primitive index per pixel of the last render, −1 = none

    def __len__(self) -> int:
        return len(self.poses)

    def render(self, pose: np.ndarray, noise: bool | None = None, seed: int | None = None,
               downsample: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(depth float32 H×W metres 0 = invalid, colour uint8 H×W×3 RGB) seen from camera-to-world ``pose``.

        ``noise`` None follows ``cfg.noise``. ``seed`` None derives the noise seed from ``cfg.seed`` and
        the pose, so two different poses get independent noise and the same pose the same frame.
        ``downsample`` f renders exactly ``full[::f, ::f]`` at a fraction of the cost.
        """
        from ti_fusion.backend import current_backend

        current_backend()
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"pose must be 4×4, got {pose.shape}")
        noise = self.cfg.noise if noise is None else noise
        if seed is None:
            seed = _mix(self.cfg.seed, zlib.crc32(pose.astype(np.float32).tobytes()))
        depth, color, labels = self._caster.render(pose, self.intrinsics, step=downsample,
                                                   sensor=self.sensor if noise else None, seed=seed)
        c = self.cfg
        if noise and (c.edge_shadow or c.edge_holes > 0):
            from ti_fusion.synthetic.edges import kinect_edges

            fx_baseline = self.intrinsics.fx * c.sensor_width / self.intrinsics.width * c.baseline
            depth = kinect_edges(depth, fx_baseline, downsample, c.edge_shadow, c.edge_holes, c.flying_pixels,
                                 _mix(seed, 0xED6E))
        if noise and c.exposure > 0:  # one gain per frame, as auto-exposure changes it
            gain = np.exp(c.exposure * np.random.default_rng(_mix(seed, 0xE4905E)).standard_normal())
            color = np.clip(np.round(color * gain), 0, 255).astype(np.uint8)
        if noise and c.jpeg_quality > 0:  # 8×8 blocks and chroma subsampling, at the rendered size
            import cv2

            ok, data = cv2.imencode(".jpg", color[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(c.jpeg_quality)])
            color = np.ascontiguousarray(cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1])
        self.last_labels = labels
        return depth, color

    def render_offset_color(self, pose: np.ndarray, T_color_depth: np.ndarray, intrinsics: Intrinsics,
                            noise: bool | None = None, seed: int | None = None) -> np.ndarray:
        """The colour image (uint8 H×W×3 RGB) of a second camera beside the depth camera, as on a RealSense
        or a Kinect: ``T_color_depth`` maps depth-camera points into it, ``intrinsics`` is its own camera;
        ``pose`` is the depth camera's camera-to-world. The target of colour registration."""
        from ti_fusion.backend import current_backend

        current_backend()
        pose_c = np.asarray(pose, dtype=np.float64) @ np.linalg.inv(np.asarray(T_color_depth, dtype=np.float64))
        noise = self.cfg.noise if noise is None else noise
        if seed is None:
            seed = _mix(self.cfg.seed, zlib.crc32(pose_c.astype(np.float32).tobytes()))
        _, color, _ = self._caster.render(pose_c, intrinsics, sensor=self.sensor if noise else None, seed=seed)
        return color

    def frame(self, index: int, downsample: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index`` of the sequence (noise per ``cfg.noise``, seed from ``cfg.seed`` and the index)."""
        seed = frame_seed(self.cfg.seed, index)
        depth, color = self.render(self.poses[index], seed=seed, downsample=downsample)
        if self.cfg.noise and self.cfg.color_offset_ms != 0 and len(self.poses) > 1:
            _, color = self.render(self.color_pose(index), seed=seed, downsample=downsample)
        return depth, color

    def color_pose(self, index: int) -> np.ndarray:
        """Camera-to-world pose of frame ``index``'s colour, ``synth.color_offset_ms`` after its depth: moved at
        constant velocity along the step to the next frame (the previous one for a negative offset or the last
        frame)."""
        from ti_fusion.geometry import invert, renormalize, se3_exp, se3_log

        dt = self.cfg.color_offset_ms / 1000.0
        other = index + 1 if (dt > 0 and index + 1 < len(self.poses)) or index == 0 else index - 1
        span = float(self.timestamps[other] - self.timestamps[index])
        step = se3_log(invert(self.poses[index]) @ self.poses[other])
        return renormalize(self.poses[index] @ se3_exp(step * (dt / span)))

    def surface_distance(self, points_world: np.ndarray) -> np.ndarray:
        """Distance (metres, float64) from each of N×3 world points to the nearest scene surface."""
        return self.scene.surface_distance(points_world)
