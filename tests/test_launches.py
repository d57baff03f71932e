"""The shorter launch path of an instance launched before (ti_fusion/launches.py): the same instance, the same
arguments and results as Taichi's own path, which every unusual call still takes."""

import numpy as np
import pytest
import taichi as ti

@pytest.fixture
def taichi_launches(monkeypatch):
    """How many launches took Taichi's own path (``Kernel.launch_kernel``) rather than the shorter one."""
    from taichi.lang.kernel_impl import Kernel

    from ti_fusion.launches import fast_launches

    assert fast_launches()
    calls = []
    launch = Kernel.launch_kernel

    def counted(self, *args):
        calls.append(self.func.__name__)
        return launch(self, *args)

    monkeypatch.setattr(Kernel, "launch_kernel", counted)
    return calls


@ti.data_oriented
class _Holder:
    def __init__(self, n):
        self.out = ti.field(ti.f32, shape=n)


def test_a_launch_again_sets_every_kind_of_argument_as_taichi_does(cpu, taichi_launches):
    """Template objects (a data-oriented object, a field, a tuple of a number and fields), NumPy arrays of
    scalars and of vectors, signed, unsigned and float scalars, a vector and a matrix: the second and later
    launches take the shorter path and compute what NumPy does with the same values."""
    holder, extra = _Holder(4), ti.field(ti.i32, shape=4)
    scale = ti.field(ti.f32, shape=())

    @ti.kernel
    def combine(h: ti.template(), e: ti.template(), pair: ti.template(), a: ti.types.ndarray(dtype=ti.f32, ndim=1),
                v: ti.types.ndarray(dtype=ti.math.vec3, ndim=1), k: ti.i32, u: ti.u32, x: ti.f32,
                w: ti.types.vector(3, ti.f32), m: ti.types.matrix(2, 2, ti.f32)):
        for i in range(4):
            h.out[i] = a[i] * x + v[i].dot(w) + m[0, 1] * pair[1][None] + ti.cast(k + ti.cast(u, ti.i32), ti.f32) + pair[0]
            e[i] = k * i

    rng = np.random.default_rng(5)
    for n in range(4):
        a = rng.standard_normal(4).astype(np.float32)
        v = rng.standard_normal((4, 3)).astype(np.float32)
        w, m = rng.standard_normal(3), rng.standard_normal((2, 2))
        scale[None] = n + 0.5
        k, u, x = n - 2, np.uint32(n), float(n) * 0.25
        combine(holder, extra, (2, scale), a, v, k, u, x, w, m)
        expected = (a.astype(np.float64) * np.float32(x) + v.astype(np.float64) @ w.astype(np.float32)
                    + np.float32(m[0, 1]) * np.float32(n + 0.5) + k + n + 2)
        np.testing.assert_allclose(holder.out.to_numpy(), expected, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(extra.to_numpy(), k * np.arange(4))
    assert taichi_launches.count("combine") == 1  # only the first launch took Taichi's path


def test_a_launch_again_is_the_same_instance_and_values_as_taichis_path(cpu, taichi_launches):
    """The same calls through the shorter path and through Taichi's own leave the same bits."""
    from taichi.lang.kernel_impl import Kernel

    out = ti.field(ti.f32, shape=64)

    @ti.kernel
    def fused(out: ti.template(), a: ti.types.ndarray(dtype=ti.f32, ndim=1), s: ti.f32, t: ti.f32):
        for i in out:
            out[i] = ti.sqrt(a[i] * s + t) / (a[i] + 3.0) + ti.sin(a[i] * t)

    a = np.linspace(0.0, 5.0, 64, dtype=np.float32)
    fused(out, a, 1.7, 0.3)
    fused(out, a, 1.3, 0.9)
    short = out.to_numpy()
    Kernel.__call__.__wrapped__(fused._primal, out, a, 1.3, 0.9)  # Taichi's own path
    np.testing.assert_array_equal(out.to_numpy(), short)
    assert taichi_launches.count("fused") == 2


def test_a_launch_again_returns_what_the_kernel_returns(cpu):
    @ti.kernel
    def one(a: ti.types.ndarray(dtype=ti.i32, ndim=1)) -> ti.i32:
        return a[0] + a[1]

    @ti.kernel
    def two(x: ti.f32) -> (ti.f32, ti.i32):
        return x * 2.0, 7

    for n in range(3):
        assert one(np.array([n, 40], np.int32)) == n + 40
        assert two(n + 0.5) == [2 * n + 1.0, 7]


def test_what_the_shorter_path_does_not_set_takes_taichis_path_and_errors(cpu, taichi_launches):
    """A value of another type, a strided array, a different array dtype, a keyword argument: Taichi's path,
    with its errors, after the shorter one has been used."""
    out = ti.field(ti.f32, shape=4)

    @ti.kernel
    def put(out: ti.template(), a: ti.types.ndarray(), k: ti.i32):
        for i in range(4):
            out[i] = a[i] + k

    a = np.arange(8, dtype=np.float32)
    put(out, a[:4], 1)
    put(out, a[:4], 2)
    assert taichi_launches.count("put") == 1
    with pytest.raises(Exception, match="i32"):
        put(out, a[:4], 2.5)  # a float for an i32: Taichi's error
    with pytest.raises(ValueError, match="contiguous"):
        put(out, a[::2], 1)  # strided: Taichi refuses it
    put(out, np.arange(4, dtype=np.float64), 1)  # another dtype: another instance, Taichi's path
    np.testing.assert_array_equal(out.to_numpy(), np.arange(4) + 1.0)
    put(out, a=a[4:], k=3)  # keywords: Taichi's path
    np.testing.assert_array_equal(out.to_numpy(), np.arange(4, 8) + 3.0)
    assert taichi_launches.count("put") == 5


def test_an_object_gone_is_not_mistaken_for_a_new_one_at_its_address(cpu, taichi_launches):
    """A template object's id is only its own while it lives: a new object (possibly at the same address)
    gets its own instance, writing its own fields."""
    import gc

    @ti.kernel
    def mark(h: ti.template(), v: ti.f32):
        for i in range(2):
            h.out[i] = v

    for n in range(4):
        holder = _Holder(2)
        mark(holder, n)
        mark(holder, n + 0.5)
        np.testing.assert_array_equal(holder.out.to_numpy(), [n + 0.5, n + 0.5])
        del holder
        gc.collect()
    assert taichi_launches.count("mark") == 4  # each object's first launch


def test_fields_made_between_launches_are_materialised_first(cpu, taichi_launches, monkeypatch):
    """Taichi's ``materialize`` runs before a shorter-path launch only where it would do something (a field made
    since the last launch): a field made between two launches of the same instance is placed and readable by
    the next, as on Taichi's path; with nothing new, the launch skips the call."""
    from taichi.lang import impl

    runtime = impl.get_runtime()
    calls = []
    materialize = type(runtime).materialize
    monkeypatch.setattr(type(runtime), "materialize", lambda self: (calls.append(1), materialize(self))[1])
    total = ti.field(ti.f32, shape=())

    @ti.kernel
    def add(v: ti.f32):
        total[None] += v

    add(1.0)
    add(2.0)
    calls.clear()
    add(3.0)  # nothing made since the last launch
    assert calls == []
    later = ti.field(ti.f32, shape=3)  # a field made between two launches: materialised before the next
    add(4.0)
    assert calls == [1]
    later.fill(5.0)
    np.testing.assert_array_equal(later.to_numpy(), [5.0, 5.0, 5.0])
    assert total[None] == 10.0
    assert taichi_launches.count("add") == 1


def test_the_last_calls_plan_is_taken_only_for_the_same_objects(cpu, taichi_launches):
    """A launch with the very template objects and array kinds of the kernel's last launch reuses its plan;
    another object, another array dtype or a Taichi ndarray in turn takes its own instance."""
    a, b = _Holder(3), _Holder(3)

    @ti.kernel
    def put(h: ti.template(), x: ti.types.ndarray(), v: ti.f32):
        for i in range(3):
            h.out[i] = x[i] + v

    for round in range(3):
        for holder, offset in ((a, 1.0), (a, 2.0), (b, 3.0), (a, 4.0), (b, 5.0)):
            put(holder, np.arange(3, dtype=np.float32), offset + round)
            np.testing.assert_array_equal(holder.out.to_numpy(), np.arange(3) + offset + round)
        put(a, np.arange(3, dtype=np.float64), 0.5)  # another dtype: another instance
        np.testing.assert_array_equal(a.out.to_numpy(), np.arange(3) + 0.5)
        nd = ti.ndarray(ti.f32, shape=3)
        nd.from_numpy(np.full(3, 7.0, np.float32))
        put(a, nd, 0.0)
        put(a, nd, 1.0)
        np.testing.assert_array_equal(a.out.to_numpy(), [8.0, 8.0, 8.0])
    assert taichi_launches.count("put") <= 2 + 3 + 3  # each kind's first launch, and each new ndarray's
