"""kernels/common.py's ``data_oriented``: objects kernels take as template arguments, without Taichi's
attribute hook."""

import numpy as np
import pytest


def test_data_oriented_objects_reach_kernels_without_the_attribute_hook(arch):
    import taichi as ti

    from ti_fusion.kernels.common import data_oriented

    @data_oriented
    class Pair:
        def __init__(self):
            self.a = ti.field(ti.f32, shape=4)
            self.b = ti.field(ti.f32, shape=4)

    @ti.kernel
    def add(p: ti.template()):
        for i in p.a:
            p.b[i] = p.a[i] + 1.0

    pair = Pair()
    assert type(pair).__getattribute__ is object.__getattribute__
    pair.a.from_numpy(np.arange(4, dtype=np.float32))
    add(pair)
    np.testing.assert_array_equal(pair.b.to_numpy(), np.arange(1, 5, dtype=np.float32))


def test_data_oriented_refuses_a_class_with_kernel_methods(cpu):
    import taichi as ti

    from ti_fusion.kernels.common import data_oriented

    with pytest.raises(TypeError, match="WithKernel has @ti.kernel methods"):
        @data_oriented
        class WithKernel:
            @ti.kernel
            def run(self):
                pass
