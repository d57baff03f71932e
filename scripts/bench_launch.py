#!/usr/bin/env python3
"""The host's cost of one Taichi kernel launch by the kind of its arguments, on any backend.

    python scripts/bench_launch.py [--arch cpu|cuda|vulkan] [--launches N]

Each row launches a kernel whose body writes one element (no loop: nothing for the device to do) N times
and prints the wall time per launch, with ``ti.sync()`` inside the timing. A frame's host overhead is about
its launches times these figures (``bench_host.py`` counts the launches). The two ``data_oriented`` rows
compare an object passed as a template argument under Taichi's own decorator, which hooks every attribute
read of the object, and under ``kernels/common.data_oriented``, which drops the hook.
"""

import argparse
import sys
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "vulkan", "auto"])
    parser.add_argument("--launches", type=int, default=5000)
    args = parser.parse_args()
    if args.launches < 1:
        parser.error("--launches must be at least 1")

    import taichi as ti

    from ti_fusion.backend import init_backend
    from ti_fusion.kernels.common import data_oriented

    backend = init_backend(args.arch)

    class Fields:
        def __init__(self):
            for i in range(8):
                setattr(self, f"f{i}", ti.field(ti.f32, shape=16))

    hooked, plain = ti.data_oriented(type("Hooked", (Fields,), {})), data_oriented(type("Plain", (Fields,), {}))
    a, b = ti.field(ti.f32, shape=16), ti.field(ti.f32, shape=16)
    nd = ti.ndarray(ti.f32, shape=16)
    host = np.zeros(16, np.float32)

    @ti.kernel
    def no_args():
        a[0] = 1.0

    @ti.kernel
    def two_fields(x: ti.template(), y: ti.template()):
        x[0] = y[1]

    @ti.kernel
    def two_objects(x: ti.template(), y: ti.template()):
        x.f0[0] = y.f1[1]

    @ti.kernel
    def scalars(s0: ti.f32, s1: ti.f32, s2: ti.f32, s3: ti.f32, s4: ti.f32, s5: ti.f32, s6: ti.i32,
                s7: ti.i32, s8: ti.i32, s9: ti.i32):
        a[0] = s0 + s1 + s2 + s3 + s4 + s5 + s6 + s7 + s8 + s9

    @ti.kernel
    def array(x: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        a[0] = x[1]

    h1, h2, p1, p2 = hooked(), hooked(), plain(), plain()
    rows = [
        ("no arguments", lambda: no_args()),
        ("2 fields (template)", lambda: two_fields(a, b)),
        ("2 objects, ti.data_oriented", lambda: two_objects(h1, h2)),
        ("2 objects, common.data_oriented", lambda: two_objects(p1, p2)),
        ("10 scalars", lambda: scalars(1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7, 8, 9, 10)),
        ("a Taichi ndarray", lambda: array(nd)),
        ("a NumPy array", lambda: array(host)),
    ]
    print(f"bench_launch.py --arch {backend.arch} --launches {args.launches}")
    print("| launch | µs per launch |")
    print("|---|---|")
    for name, launch in rows:
        launch()  # compiles
        ti.sync()
        t0 = time.perf_counter()
        for _ in range(args.launches):
            launch()
        ti.sync()
        print(f"| {name} | {(time.perf_counter() - t0) / args.launches * 1e6:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
