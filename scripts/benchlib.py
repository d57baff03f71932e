"""What the benchmarks share: NumPy at its best (``keep_freed_memory``), the conditions it ran under for
their headers (``numpy_conditions``), the pause that keeps OpenBLAS's threads out of the kernels' timings
(``BLAS_SETTLE_S``), and OpenCV's RGB-D odometry as a peer (``OpenCVOdometry``, in bench_icp.py and
bench_slam.py).

The benchmarks import it as a sibling (``python scripts/bench_x.py`` has scripts/ on its path); it imports
nothing from scripts/, so that a test can load it from its file.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

import numpy as np

# NumPy's matrix products wake OpenBLAS's worker threads, which spin for tens of ms afterwards: a benchmark
# waits this long after a NumPy call before timing the kernels, so that they do not share the cores
BLAS_SETTLE_S = 0.2

# glibc's mallopt parameters
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # the ceiling of glibc's own adaptive threshold on 64-bit


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed blocks of up to 32 MiB for reuse instead of returning them to the system
    (benchmarks call this before timing the NumPy references). By default blocks above a threshold that
    glibc adapts at run time are mmap-ed and unmapped on free, so NumPy's large temporaries page-fault
    afresh on every call, in some processes and not in others (docs/BENCHMARKS.md says by how much). Kept,
    NumPy is timed at its best, every run alike. Returns whether it took effect (False off glibc)."""
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)) and \
            bool(libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30))
    except (OSError, AttributeError):
        return False


# Environment settings that change how fast NumPy's BLAS runs. Some machines set OPENBLAS_CORETYPE (to an
# older core's kernels, as a guard against OpenBLAS bugs on newer CPUs); a benchmark names them beside
# its ratios.
BLAS_SETTINGS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def numpy_conditions(kept_freed_memory: bool) -> str:
    """How NumPy runs in a benchmark, for its header: freed memory kept or not (``keep_freed_memory``) and
    the BLAS settings in the environment."""
    text = ("freed memory kept (glibc): NumPy timed at its best" if kept_freed_memory
            else "freed memory returned to the system (not glibc)")
    blas = [f"{k}={os.environ[k]}" for k in BLAS_SETTINGS if k in os.environ]
    return text + (f"; NumPy's BLAS under {', '.join(blas)}" if blas else "")


class OpenCVOdometry:
    """OpenCV's RGB-D odometry between two frames, whichever API this cv2 has: OpenCV 5's ``cv2.Odometry``
    or OpenCV 4 contrib's ``cv2.rgbd``. ``prepare(depth_m, grey)`` → a frame; ``compute(src, dst)`` → (ok,
    4×4 Rt with Rt · p_src = p_dst). Depth in metres (float32, 0 = none), grey uint8 or None."""

    KINDS = ("depth", "depth-fast", "rgbd", "rgb")

    def __init__(self, kind: str, K, depth_max: float):
        import cv2

        self.cv2, self.kind = cv2, kind
        camera = np.array([[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]], np.float32)
        if hasattr(cv2, "Odometry"):  # OpenCV 5: the 3d module
            settings = cv2.OdometrySettings()
            settings.setCameraMatrix(camera)
            settings.setMaxDepth(float(depth_max))
            kind_type = {"depth": cv2.OdometryType_DEPTH, "depth-fast": cv2.OdometryType_DEPTH,
                         "rgbd": cv2.OdometryType_RGB_DEPTH, "rgb": cv2.OdometryType_RGB}[kind]
            algo = cv2.OdometryAlgoType_FAST if kind == "depth-fast" else cv2.OdometryAlgoType_COMMON
            self.odometry = cv2.Odometry(kind_type, settings, algo)
            self.api = "cv2.Odometry"
        elif hasattr(cv2, "rgbd"):  # OpenCV 4 contrib
            rgbd = cv2.rgbd
            if kind == "depth":
                self.odometry = rgbd.ICPOdometry_create(camera, 0.0, float(depth_max))
            elif kind == "depth-fast":
                self.odometry = rgbd.FastICPOdometry_create(camera)
            elif kind == "rgbd":
                self.odometry = rgbd.RgbdICPOdometry_create(camera, 0.0, float(depth_max))
            else:
                self.odometry = rgbd.RgbdOdometry_create(camera, 0.0, float(depth_max))
            self.api = "cv2.rgbd (contrib)"
        else:
            raise ImportError(f"OpenCV {cv2.__version__} has neither cv2.Odometry (OpenCV 5) nor cv2.rgbd "
                              "(OpenCV 4 contrib)")
        self.name = f"OpenCV {cv2.__version__} {kind} odometry"
        self.uses_grey = kind in ("rgbd", "rgb")

    def prepare(self, depth_m: np.ndarray, grey: np.ndarray | None):
        cv2 = self.cv2
        depth = np.ascontiguousarray(depth_m, dtype=np.float32)
        if grey is None:
            grey = np.zeros(depth.shape, np.uint8)
        if hasattr(cv2, "Odometry"):
            frame = cv2.OdometryFrame(image=grey, depth=depth) if self.uses_grey else cv2.OdometryFrame(depth=depth)
            self.odometry.prepareFrame(frame)
            return frame
        frame = cv2.rgbd.OdometryFrame_create(grey, depth, np.ones(depth.shape, np.uint8), None, -1)
        self.odometry.prepareFrameCache(frame, cv2.rgbd.OdometryFrame_CACHE_ALL)
        return frame

    def compute(self, src, dst) -> tuple[bool, np.ndarray]:
        if hasattr(self.cv2, "Odometry"):
            ok, Rt = self.odometry.compute(src, dst)
        else:
            ok, Rt = self.odometry.compute2(src, dst)
        return bool(ok), (np.asarray(Rt, dtype=np.float64) if ok else np.eye(4))


def grey_of(color: np.ndarray | None) -> np.ndarray | None:
    if color is None:
        return None
    c = color.astype(np.float32)
    return np.clip(0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2] + 0.5, 0, 255).astype(np.uint8)
