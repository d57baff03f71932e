"""Types, constants and small functions shared by the kernel files, and the sensor model on the Taichi side.

Poses travel to kernels as ``Rigid`` arguments: a flat float32 array of 12 numbers (R row-major, then t),
unpacked by ``rigid``; a small array is cheaper to pass than matrix and vector arguments. Depths are
compared as the int32 bit patterns of positive float32 values (``depth_bits``), which order exactly like
the values, so that 32-bit atomics can take a nearest depth on every backend.
"""

import numpy as np
import taichi as ti

from ti_fusion.backend import on_cpu
from ti_fusion.geometry import flatten_pose
from ti_fusion.sensor import SIGMA_1M, SIGMA_A, SIGMA_B, SIGMA_Z0

Vec3 = ti.types.vector(3, ti.f32)
Mat3 = ti.types.matrix(3, 3, ti.f32)
Rigid = ti.types.ndarray(dtype=ti.f32, ndim=1)  # R row-major, then t: see ``rigid`` and ``rigid_arg``

INT_MAX = 2147483647  # "no surfel" in index maps and "no depth" in depth keys
# Surfels per block of the per-block lists and scans. Small, so that a loop over the blocks of a map of
# a few hundred thousand surfels still has enough iterations to run on several threads (see
# docs/KERNELS.md).
BLOCK = 128
# Values per pack of the CPU's vectorised loops: Taichi's CPU backend does not vectorise a loop over pixels or
# surfels, but LLVM's SLP vectoriser turns one operation on a small vector's components into SIMD instructions,
# so the pyramid's loops take eight pixels of a row, the projections eight surfels, as one 8-vector
# (docs/KERNELS.md).
LANES = 8
Pack = ti.types.vector(LANES, ti.f32)


def data_oriented(cls):
    """``ti.data_oriented`` for a class whose objects kernels take as ``ti.template()`` arguments, without the
    ``__getattribute__`` hook Taichi installs to bind ``@ti.kernel`` methods: none of these classes has one,
    and the hook runs a Python function on every attribute read (hundreds per frame, ``isinstance`` checks
    of each launch's arguments included; docs/PERFORMANCE.md)."""
    cls = ti.data_oriented(cls)
    if any(getattr(v, "_is_wrapped_kernel", False) for v in vars(cls).values()):
        raise TypeError(f"{cls.__name__} has @ti.kernel methods: decorate it with ti.data_oriented")
    del cls.__getattribute__
    return cls


def given(x) -> bool:
    """Whether an optional template argument was given: ``ti.static(given(x))`` (``is not None`` is not
    allowed in Taichi scope, even inside ``ti.static``)."""
    return x is not None


@ti.func
def rigid(pose: ti.template()):
    """(R, t) of a ``Rigid`` argument."""
    R = Mat3([[pose[3 * i + j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    t = Vec3(pose[9], pose[10], pose[11])
    return R, t


def rigid_arg(T: np.ndarray) -> np.ndarray:
    """A 4×4 rigid transform as a ``Rigid`` kernel argument: R row-major, then t, float32."""
    return flatten_pose(T).astype(np.float32)


@ti.kernel
def _write_pose_pair(to_world: Rigid, to_camera: Rigid,
                     w0: ti.f32, w1: ti.f32, w2: ti.f32, w3: ti.f32, w4: ti.f32, w5: ti.f32,
                     w6: ti.f32, w7: ti.f32, w8: ti.f32, w9: ti.f32, w10: ti.f32, w11: ti.f32,
                     c0: ti.f32, c1: ti.f32, c2: ti.f32, c3: ti.f32, c4: ti.f32, c5: ti.f32,
                     c6: ti.f32, c7: ti.f32, c8: ti.f32, c9: ti.f32, c10: ti.f32, c11: ti.f32):
    for i in ti.static(range(12)):
        to_world[i] = ti.static((w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11))[i]
        to_camera[i] = ti.static((c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11))[i]


class PoseArgs:
    """A camera-to-world pose as the pair of ``Rigid`` arguments the map's kernels take: (to world, to camera).

    On the CPU these are NumPy arrays, which a launch passes by address. On a GPU backend a NumPy argument is
    copied to the device and back with a wait for the device at every launch, so there the pair is written
    into two device arrays by one launch with scalar arguments, which queues behind the frame's other work.
    The last pose is remembered: the stages of one frame convert it once.
    """

    def __init__(self):
        self.on_host = on_cpu()
        self._key = None
        self._pair = None
        if not self.on_host:
            self._device = (ti.ndarray(ti.f32, 12), ti.ndarray(ti.f32, 12))

    def __call__(self, pose: np.ndarray):
        pose = np.asarray(pose, dtype=np.float64)
        key = pose.tobytes()
        if key != self._key:
            to_world, to_camera = camera_to_world(pose), world_to_camera(pose)
            if self.on_host:
                self._pair = (to_world, to_camera)
            else:
                _write_pose_pair(*self._device, *to_world.tolist(), *to_camera.tolist())
                self._pair = self._device
            self._key = key
        return self._pair


def world_to_camera(pose: np.ndarray) -> np.ndarray:
    """The inverse of a 4×4 camera-to-world pose, as a ``Rigid`` argument."""
    return rigid_arg(np.linalg.inv(np.asarray(pose, dtype=np.float64)))


def camera_to_world(pose: np.ndarray) -> np.ndarray:
    """A 4×4 camera-to-world pose as a ``Rigid`` argument."""
    return rigid_arg(np.asarray(pose, dtype=np.float64))


@ti.func
def depth_bits(z):
    """int32 bit pattern of a positive float32: ordered exactly like the floats themselves."""
    return ti.bit_cast(ti.cast(z, ti.f32), ti.i32)


@ti.func
def bits_depth(k):
    return ti.bit_cast(k, ti.f32)


@ti.func
def is_valid(q, nq):
    """Whether a pixel of a vertex map ``q`` and normal map ``nq`` holds a measurement."""
    return q.z > 0 and nq.norm_sqr() > 0


# -- the sensor model (``ti_fusion.sensor``) --------------------------------------------------------------
# The constants are built as ``real`` values: a bare Python float in a kernel is a float32 constant, which
# would round them in the float64 kernels.


@ti.func
def depth_sigma(z, real: ti.template()):
    """Kinect's axial depth noise σ(z) = A + B (z − Z0)² at depth z, in arithmetic type ``real``."""
    dz = z - real(SIGMA_Z0)
    return real(SIGMA_A) + real(SIGMA_B) * dz * dz


@ti.func
def depth_noise_scale(z, real: ti.template()):
    """σ(1 m) / σ(z): 1 at 1 m, smaller farther away (a residual times this is in units of the noise at 1 m)."""
    return real(SIGMA_1M) / depth_sigma(z, real)
