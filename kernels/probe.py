"""A kernel that only keeps the CPU busy: ``ti_fusion.backend.pin_cpu_workers`` runs it to find out
which threads are Taichi's workers (the ones that run it)."""

import taichi as ti


@ti.kernel
def busy(n: ti.i32, out: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    """About 20 ms on one core for n = 4096: 8 tasks of 512 iterations, so every worker takes some."""
    for i in range(n):
        x = ti.cast(i, ti.f32)
        for _ in range(600):
            x = ti.sqrt(x + 1.0)
        out[i] = x
