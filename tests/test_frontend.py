"""The memo of Taichi's source-position text (ti_fusion/frontend.py): installed, and compile errors still
point at the right line, including when the same function is compiled again from another place."""

import pytest
import taichi as ti

from ti_fusion.frontend import memoize_source_positions


@ti.func
def _bad_index(x: ti.template(), i):
    return x[i, i, i]  # a 1-D field indexed with three indices: a compile error on this line


def test_memo_installed(cpu):
    """Fails loudly when a Taichi release no longer has what frontend.py patches (pyproject pins the range)."""
    assert ti.__version__[:2] == (1, 7), f"frontend.py was written for Taichi 1.7, found {ti.__version__}"
    assert memoize_source_positions()
    from taichi.lang.ast import ast_transformer_utils as utils

    assert hasattr(utils.ASTTransformerContext.get_pos_info, "__wrapped__")


def test_compile_errors_still_name_the_line(cpu):
    x = ti.field(ti.f32, shape=4)

    @ti.kernel
    def first():
        for i in range(4):
            x[i] = _bad_index(x, i)

    @ti.kernel
    def second():
        x[0] = 1.0
        x[1] = _bad_index(x, 1)

    for kernel in (first, second, first):  # the same failing function reached from two kernels, twice
        with pytest.raises(Exception) as info:
            kernel()
        text = str(info.value)
        assert "return x[i, i, i]" in text and "^" in text, text
        assert "_bad_index" in text, text


def test_memo_gives_the_original_text(cpu, monkeypatch):
    """Every position text the memo hands out while compiling a kernel with unrolled loops, an inlined
    function called twice and multi-line statements equals what Taichi itself would have built."""
    from taichi.lang.ast import ast_transformer_utils as utils

    memo = utils.ASTTransformerContext.get_pos_info
    compared = []

    def checked(self, node):
        text = memo(self, node)
        assert text == memo.__wrapped__(self, node)
        compared.append(text)
        return text

    monkeypatch.setattr(utils.ASTTransformerContext, "get_pos_info", checked)
    x = ti.field(ti.f32, shape=(4, 4))

    @ti.func
    def twice(a):
        return (a
                + a)

    @ti.kernel
    def kernel():
        for i, j in x:
            total = 0.0
            for k in ti.static(range(3)):
                if k > 0:
                    total += twice(x[i, j]) * k
            x[i, j] = twice(total)

    kernel()
    assert len(compared) > 50


def test_source_lines_are_kept_per_function(cpu):
    """Two kernels made by one factory share their source lines but not their captured values."""
    from taichi.lang import kernel_impl

    assert hasattr(kernel_impl.getsourcelines, "__wrapped__")
    x = ti.field(ti.f32, shape=2)

    def make(value):
        @ti.kernel
        def put(i: ti.i32):
            x[i] = value

        return put

    make(1.5)(0)
    make(2.5)(1)
    assert x.to_numpy().tolist() == [1.5, 2.5]


def test_the_wrapping_answers_as_textwrap():
    """MemoWrapper(width=80).wrap equals TextWrapper's on every line of this project's and Taichi's sources and
    on the caret lines the front end builds under them (every start and length, padded to the line), on blank,
    tabbed, non-ASCII and long texts, asked twice (the memo's answer too)."""
    import textwrap
    from pathlib import Path

    from ti_fusion.frontend import MemoWrapper

    root = Path(__file__).resolve().parents[1]
    files = [*root.glob("ti_fusion/**/*.py"), *root.glob("kernels/*.py"), *Path(ti.__file__).parent.glob("lang/**/*.py")]
    lines = {line for path in files for line in path.read_text().splitlines()}
    texts = set(lines) | {"", " ", " " * 81, "\t x", "a\tb", "é" * 10, "x" * 81, "a-b " * 30, "  ^", "^" * 90}
    for line in sorted(lines)[::7]:
        for start in range(0, len(line) + 1, 5):
            for n in (1, 3, 17, len(line) - start):
                texts.add((" " * start + "^" * n).ljust(len(line)))
    ours, theirs = MemoWrapper(width=80), textwrap.TextWrapper(width=80)
    for text in sorted(texts):
        want = theirs.wrap(text)
        assert ours.wrap(text) == want and ours.wrap(text) == want, repr(text)
    assert len(texts) > 10000


def test_the_front_ends_fill_and_dedent_are_textwraps(cpu):
    import textwrap

    from taichi.lang import kernel_impl

    assert memoize_source_positions()
    shim = kernel_impl.textwrap
    assert shim is not textwrap and shim.TextWrapper is textwrap.TextWrapper
    for text in ("  a\tb  ", "\t\tx = 1", "", "    def f():\n        return 1\n"):
        for _ in range(2):
            assert shim.fill(text, tabsize=4, width=9999) == textwrap.fill(text, tabsize=4, width=9999)
            assert shim.dedent(text) == textwrap.dedent(text)


# --------------------------------------------------------------------------------------------------
# The kernels' first launches timed, and the terminal told when kernels compile
# --------------------------------------------------------------------------------------------------
def test_the_clock_counts_each_instance_once_and_says_once_that_kernels_compile():
    from ti_fusion.frontend import COMPILING_S, KernelClock

    clock, said = KernelClock(), []
    clock.notice = said.append
    clock.add(0.05, "loaded")
    clock.add(COMPILING_S + 1.0, "slow")
    clock.add(COMPILING_S + 2.0, "slow")
    assert (clock.instances, clock.compiled, said) == (3, 2, [COMPILING_S + 1.0])
    assert clock.by_kernel == {"slow": 2 * COMPILING_S + 3.0}
    assert clock.seconds == pytest.approx(0.05 + 2 * COMPILING_S + 3.0)


def test_first_launches_are_clocked(cpu):
    from ti_fusion.frontend import CLOCK, clock_first_launches

    assert clock_first_launches()
    x = ti.field(ti.f32, shape=8)
    y = ti.field(ti.f32, shape=8)

    @ti.kernel
    def fill(f: ti.template(), v: ti.f32):
        for i in f:
            f[i] = v

    before = CLOCK.instances
    fill(x, 1.0)
    fill(x, 2.0)  # the same instance: not a first launch
    assert CLOCK.instances == before + 1
    fill(y, 3.0)  # another field, another instance
    assert CLOCK.instances == before + 2 and x[0] == 2.0 and y[7] == 3.0


def test_an_instance_given_a_freed_instances_wrapper_is_a_first_launch(cpu, monkeypatch):
    """After a reset frees the program's instances, a new one can be allocated at a freed one's address, and
    pybind then hands back the wrapper still registered there (and held by the clock): it is clocked anyway."""
    from taichi._lib import core as _ti_core

    from ti_fusion.frontend import CLOCK, clock_first_launches

    assert clock_first_launches()
    x = ti.field(ti.f32, shape=8)

    @ti.kernel
    def fill(f: ti.template(), v: ti.f32):
        for i in f:
            f[i] = v

    fill(x, 1.0)
    (old,) = fill._primal.compiled_kernels.values()
    fill._primal.compiled_kernels.clear()  # as a reset does
    monkeypatch.setattr(_ti_core.Program, "create_kernel", lambda self, *args: old)  # the reused address's wrapper
    before = CLOCK.instances
    fill(x, 2.0)
    assert CLOCK.instances == before + 1 and x[0] == 2.0


def test_a_first_launch_counts_as_compiled_by_the_cpu_time_of_its_compile_step(cpu, monkeypatch):
    """Whether a first launch compiled is judged by the CPU time of Taichi's compile step (a load from the
    cache takes milliseconds of it), not by the launch's wall time, which a loaded machine stretches; the
    step is timed on first launches only."""
    from taichi._lib import core as _ti_core

    from ti_fusion import frontend

    assert frontend.clock_first_launches()
    original = _ti_core.Program.compile_kernel
    x = ti.field(ti.f32, shape=8)

    @ti.kernel
    def fill(f: ti.template(), v: ti.f32):
        for i in f:
            f[i] = v

    monkeypatch.setattr(frontend, "COMPILING_S", 0.0)  # (by wall time every launch would count as compiled)
    monkeypatch.setattr(frontend, "COMPILING_CPU_S", 1e9)
    compiled = frontend.CLOCK.compiled
    fill(x, 1.0)
    assert frontend.CLOCK.compiled == compiled
    # below any step's CPU time, which is 0.0 where the thread's clock did not tick during a load from the cache
    monkeypatch.setattr(frontend, "COMPILING_CPU_S", -1.0)
    fill(ti.field(ti.f32, shape=8), 2.0)  # another instance
    assert frontend.CLOCK.compiled == compiled + 1
    assert _ti_core.Program.compile_kernel is original  # later launches call Taichi's own


def test_the_terminal_is_told_that_kernels_compile(monkeypatch, capsys):
    import importlib

    from ti_fusion import frontend

    main = importlib.import_module("ti_fusion.cli.main")  # (the package's ``main`` attribute is the function)

    monkeypatch.setattr(frontend, "offline_cache_files", lambda: ("/tmp/empty-cache", 0))
    main._announce_compiling(quiet=False)
    assert "compiling kernels: the kernel cache (/tmp/empty-cache) is empty" in capsys.readouterr().out
    frontend.CLOCK.add(frontend.COMPILING_S + 0.5, "big")
    fields = main._kernel_times(quiet=False)
    assert f"kernels: 1 compiled in {frontend.COMPILING_S + 0.5:.1f} s" in capsys.readouterr().out
    assert fields["kernels_compiled"] == 1 and fields["kernels_compiled_s"] == {"big": frontend.COMPILING_S + 0.5}

    main._announce_compiling(quiet=True)
    frontend.CLOCK.add(0.02, "loaded")
    frontend.CLOCK.add(3.0, "render_kernel", True, elsewhere=True)  # a frame reader process's, beside the loop
    fields = main._kernel_times(quiet=False)
    assert "kernels: 1 compiled in 3.0 s, 3.0 s of it in the frame reader process (and 1 loaded from the cache " \
           "or compiled quickly, 0.0 s)" in capsys.readouterr().out
    assert fields["kernel_first_launch_s"] == 0.02 and fields["kernel_compile_elsewhere_s"] == 3.0
    assert fields["kernels_compiled_s"] == {"render_kernel": 3.0} and fields["kernel_instances"] == 2

    monkeypatch.setattr(frontend, "offline_cache_files", lambda: ("/tmp/full-cache", 40))
    main._announce_compiling(quiet=False)  # a cache with kernels: said when the first one compiles
    assert capsys.readouterr().out == ""
    frontend.CLOCK.add(frontend.COMPILING_S + 0.5, "new")
    assert "compiling kernels that are not in the kernel cache" in capsys.readouterr().out
    main._kernel_times(quiet=True)


def test_a_failed_run_leaves_no_notice_behind(cpu, tmp_path, monkeypatch):
    """A ti-fusion run that stops with an error resets the clock's notice: later kernels of the process (a
    user's own code after main()) print nothing."""
    import importlib

    from ti_fusion import frontend
    from ti_fusion.cli.main import main

    monkeypatch.setattr(frontend, "offline_cache_files", lambda: ("/tmp/full-cache", 40))
    announced = []
    real = importlib.import_module("ti_fusion.cli.main")._announce_compiling

    def announce(quiet):
        real(quiet)
        announced.append(frontend.CLOCK.notice)

    monkeypatch.setattr(importlib.import_module("ti_fusion.cli.main"), "_announce_compiling", announce)
    assert main(["slam", str(tmp_path / "no-such-folder"), "--out", str(tmp_path / "run")]) == 2
    assert announced and announced[0] is not None  # the notice was set for the run (Taichi had started)
    assert frontend.CLOCK.notice is None


def test_the_class_check_answers_as_taichis(monkeypatch):
    """``fast_class_check``'s replacement of Taichi's in-class test gives the original's answer for every
    ``ti.kernel`` and ``ti.func`` defined while the kernels are imported and below: in a ``data_oriented``
    class body (True), in a function and at module level (False)."""
    from taichi.lang import kernel_impl

    from ti_fusion.frontend import fast_class_check

    assert fast_class_check()
    fast = kernel_impl._inside_class
    assert hasattr(fast, "__wrapped__")
    answers = []

    def both(level_of_class_stackframe):
        mine = fast(level_of_class_stackframe + 1)
        theirs = fast.__wrapped__(level_of_class_stackframe + 1)
        answers.append((mine, theirs))
        return mine

    monkeypatch.setattr(kernel_impl, "_inside_class", both)

    @ti.data_oriented
    class Owner:
        @ti.kernel
        def method(self):
            pass

        @ti.func
        def helper(self):
            pass

    @ti.kernel
    def plain():
        pass

    @ti.func
    def plain_func():
        pass

    import types
    from pathlib import Path

    import ti_fusion.kernels.pyramid as module

    # every decorator of a kernels module, run again in a copy of it (the module itself stays as it is, and
    # whether an earlier test imported it already does not matter)
    copy = types.ModuleType("pyramid_copy")
    copy.__file__ = module.__file__
    exec(compile(Path(module.__file__).read_text(), module.__file__, "exec"), copy.__dict__)
    assert answers[:4] == [(True, True), (True, True), (False, False), (False, False)]
    assert len(answers) > 10 and all(mine == theirs for mine, theirs in answers)
    assert Owner.method._is_classkernel and not plain._is_classkernel


def test_the_class_check_is_in_place_while_taichi_is_imported(tmp_path):
    """Importing ti_fusion before Taichi installs the cheap check as Taichi's kernel_impl is loaded, so that
    Taichi's own decorators use it, and the finder that did it is gone afterwards."""
    import subprocess
    import sys

    code = ("import sys, ti_fusion\n"
            "assert 'taichi' not in sys.modules\n"
            "from taichi.lang import kernel_impl\n"
            "assert hasattr(kernel_impl._inside_class, '__wrapped__')\n"
            "from ti_fusion.frontend import _ClassCheckFinder\n"
            "assert not any(isinstance(f, _ClassCheckFinder) for f in sys.meta_path)\n"
            "import taichi as ti\n"
            "@ti.data_oriented\n"
            "class A:\n"
            "    @ti.kernel\n"
            "    def k(self):\n"
            "        pass\n"
            "assert A.k._is_classkernel\n")
    script = tmp_path / "script.py"  # (the class check reads the decorator's line from its file)
    script.write_text(code)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
