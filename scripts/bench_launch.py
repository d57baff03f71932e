#!/usr/bin/env python3
"""The host's cost of one Taichi kernel launch by the kind of its arguments, on any backend.

    python scripts/bench_launch.py [--arch cpu|cuda|vulkan] [--launches N]

Each row launches a kernel whose body writes one element (no loop: nothing for the device to do) N times
and prints the wall time per launch, with ``ti.sync()`` inside the timing, and the launching thread's CPU
time per launch (less moved by other work on the machine), through ti-fusion's shorter path for an
instance launched before (``launches.fast_launches``) and through Taichi's own ``Kernel.__call__``, the
two alternated in rounds of N/4. A frame's host overhead is about its launches times these figures
(``bench_host.py`` counts the launches). The two ``data_oriented`` rows
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

    @ti.kernel
    def icp_like(v: ti.template(), n: ti.template(), tv: ti.template(), tn: ti.template(), partials: ti.template(),
                 params: ti.types.ndarray(dtype=ti.f32, ndim=2), terms: ti.template(), row: ti.i32, it: ti.i32):
        v.f0[0] = n.f1[1] + tv[0] + tn[1] + partials[2] + params[row, it] + terms[0][1][0][3]

    h1, h2, p1, p2 = hooked(), hooked(), plain(), plain()
    params = np.zeros((4, 4), np.float32)
    terms = ((0, (a, b), (b, a)),)
    rows = [
        ("no arguments", lambda: no_args()),
        ("2 fields (template)", lambda: two_fields(a, b)),
        ("2 objects, ti.data_oriented", lambda: two_objects(h1, h2)),
        ("2 objects, common.data_oriented", lambda: two_objects(p1, p2)),
        ("10 scalars", lambda: scalars(1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7, 8, 9, 10)),
        ("a Taichi ndarray", lambda: array(nd)),
        ("a NumPy array", lambda: array(host)),
        ("as ICP's iterate: 5 templates, a nested tuple, an array, 2 ints",
         lambda: icp_like(p1, p2, a, b, a, params, terms, 1, 2)),
    ]
    from taichi.lang.kernel_impl import Kernel

    short = Kernel.__call__
    taichis = getattr(short, "__wrapped__", short)  # Taichi's own path (ti_fusion.launches.fast_launches)
    rounds = min(4, args.launches)
    print(f"bench_launch.py --arch {backend.arch} --launches {args.launches}")
    print("| launch | µs per launch | CPU µs per launch | Taichi's path: µs | CPU µs |")
    print("|---|---|---|---|---|")
    for name, launch in rows:
        launch()  # compiles
        ti.sync()
        spent = {short: [0.0, 0.0], taichis: [0.0, 0.0]}
        for _ in range(rounds):
            for path in (taichis, short):
                Kernel.__call__ = path
                try:
                    t0, c0 = time.perf_counter(), time.thread_time()
                    for _ in range(args.launches // rounds):
                        launch()
                    ti.sync()
                    spent[path][0] += time.perf_counter() - t0
                    spent[path][1] += time.thread_time() - c0
                finally:
                    Kernel.__call__ = short
        n = rounds * (args.launches // rounds) / 1e6
        print(f"| {name} | {spent[short][0] / n:.1f} | {spent[short][1] / n:.1f} | {spent[taichis][0] / n:.1f} "
              f"| {spent[taichis][1] / n:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
