"""Memos for Taichi's compiler front end: the source it reads and the position text it builds.

Taichi 1.7's front end (Python AST → Taichi IR, run for every kernel instance in every process, with a
warm kernel cache too) formats a "File ..., line ..." message with the offending source line wrapped
by ``textwrap`` for every node it visits, to have it ready should that node fail to compile. The same
nodes are visited again and again (every unrolled ``ti.static`` iteration, every inlined ``ti.func``,
every instance of a kernel), and the text only depends on where the node is in its file, so
``memoize_source_positions`` caches it by that position: the front end gets the same strings, sooner
(docs/PERFORMANCE.md, "Cold start": about a quarter of a warm run's time to its first tracked frame).
It also reads a function's source lines from its file (``inspect.getsourcelines``, which tokenizes the
file's text) again for every instance; ``memoize_source_positions`` keeps them per function.
"""

from __future__ import annotations

import textwrap as _textwrap

_installed = False


def memoize_source_positions() -> bool:
    """Cache ``ASTTransformerContext.get_pos_info`` by node position; True when installed (once per process).
    Does nothing on a Taichi whose front end does not look the way this was written for."""
    global _installed
    if _installed:
        return True
    try:
        from taichi.lang.ast import ast_transformer_utils as utils
    except ImportError:
        return False
    context = getattr(utils, "ASTTransformerContext", None)
    original = getattr(context, "get_pos_info", None)
    if original is None:
        return False
    cache: dict = {}

    def get_pos_info(self, node):
        # Everything the original reads: the function's place in its file (its source is that file's),
        # and the node's kind and span (a For/While/If/FunctionDef span ends where its body starts).
        body = getattr(node, "body", None)
        key = (self.file, self.lineno_offset, self.indent, self.func.func.__name__, type(node), node.lineno,
               node.end_lineno, node.col_offset, node.end_col_offset, body[0].lineno if isinstance(body, list) and body else None)
        text = cache.get(key)
        if text is None:
            text = cache[key] = original(self, node)
        return text

    get_pos_info.__wrapped__ = original
    context.get_pos_info = get_pos_info
    _memoize_source_lines()
    _memoize_wrapping(utils)
    _installed = True
    return True


def _memoize_wrapping(utils) -> None:
    """The position text's ``TextWrapper(width=80).wrap`` of a source line and of its caret line (called again and
    again for the same few texts; most lines of this project are longer than 80 columns), and
    the front end's ``textwrap.fill`` and ``dedent`` of each function's source lines for every instance, answered
    from memos of those pure functions of their text: the same strings, once each."""
    import types

    textwrap = _textwrap
    if getattr(utils, "TextWrapper", None) is textwrap.TextWrapper:
        utils.TextWrapper = MemoWrapper
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return
    if getattr(kernel_impl, "textwrap", None) is textwrap:
        fills: dict = {}

        def fill(text, **options):
            key = (text, tuple(options.items()))
            out = fills.get(key)
            if out is None:
                out = fills[key] = textwrap.fill(text, **options)
            return out

        shim = types.ModuleType("textwrap")  # textwrap itself, but for these two
        shim.__dict__.update(textwrap.__dict__)
        shim.fill, shim.dedent = fill, _memo(textwrap.dedent)
        kernel_impl.textwrap = shim


_PRINTABLE_ASCII = frozenset(map(chr, range(0x20, 0x7F)))


class MemoWrapper(_textwrap.TextWrapper):
    """``TextWrapper`` whose ``wrap`` keeps its answer per (width, text) when made with the width alone (as the
    front end makes it). A printable ASCII text no longer than the width is not split: its lines are the text
    without its trailing spaces, or none when it is blank (``TextWrapper``'s rule there, checked in the tests
    against it on every line of the sources)."""

    _memo: dict = {}

    def __init__(self, width: int = 70, **options):
        super().__init__(width, **options)
        self._plain = not options

    def wrap(self, text):
        if not self._plain:
            return super().wrap(text)
        if len(text) <= self.width and _PRINTABLE_ASCII.issuperset(text):
            text = text.rstrip(" ")
            return [text] if text.strip(" ") else []
        key = (self.width, text)
        lines = self._memo.get(key)
        if lines is None:
            lines = self._memo[key] = tuple(super().wrap(text))
        return list(lines)


def _memoize_source_lines() -> None:
    """Keep ``getsourcelines``'s (and ``getsourcefile``'s) answer per function (the function itself is the key, so
    a function that is gone cannot hand its source to a new one at the same address); the caller copies the
    list."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return
    for name in ("getsourcelines", "getsourcefile"):
        original = getattr(kernel_impl, name, None)
        if original is not None:
            setattr(kernel_impl, name, _memo(original))


def _memo(function):
    """``function`` of one hashable argument answered from a memo of its answers (None is asked again)."""
    answers: dict = {}

    def memo(key):
        answer = answers.get(key)
        if answer is None:
            answer = answers[key] = function(key)
        return answer

    memo.__wrapped__ = function
    return memo


def fast_class_check() -> bool:
    """Make Taichi's check of whether a ``ti.kernel`` / ``ti.func`` is defined in a class body cheap; True
    when installed (once per process). Taichi 1.7's decorators read the source line the defining frame is
    at with ``inspect.getframeinfo``, which finds the frame's module by scanning every loaded module's
    file (``inspect.getmodule``) and reads the whole file, for every kernel and function defined at import
    and for ICP's kernels built per set of terms (docs/PERFORMANCE.md). This reads the same line through
    ``linecache`` and matches it against the same patterns."""
    global _class_check_installed
    if _class_check_installed:
        return True
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return False
    original = getattr(kernel_impl, "_inside_class", None)
    patterns = getattr(kernel_impl, "_KERNEL_CLASS_STACKFRAME_STMT_RES", None)
    if original is None or patterns is None:
        return False
    import linecache
    import sys

    def _inside_class(level_of_class_stackframe):
        try:
            frame = sys._getframe(level_of_class_stackframe)
            line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals).strip()
        except Exception:
            return False
        return any(pattern.match(line) for pattern in patterns)

    _inside_class.__wrapped__ = original
    kernel_impl._inside_class = _inside_class
    _class_check_installed = True
    return True


_class_check_installed = False


def class_check_on_import() -> None:
    """Have ``fast_class_check`` installed as soon as Taichi's ``kernel_impl`` is imported, where Taichi is not
    imported yet: Taichi's own ~90 kernels and functions, decorated while ``import taichi`` runs, then take the
    cheap check too (the expensive one scans every loaded module: docs/PERFORMANCE.md). A finder on
    ``sys.meta_path`` for that one module, gone once used; any surprise leaves the import as it was."""
    import sys

    if "taichi.lang.kernel_impl" in sys.modules or any(isinstance(f, _ClassCheckFinder) for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _ClassCheckFinder())


class _ClassCheckFinder:
    """The finder of ``class_check_on_import``: finds nothing itself, but wraps the loader the other finders
    give for ``taichi.lang.kernel_impl`` so that ``fast_class_check`` runs right after the module's code."""

    def find_spec(self, name, path=None, target=None):
        if name != "taichi.lang.kernel_impl":
            return None
        import sys

        if self in sys.meta_path:
            sys.meta_path.remove(self)
        try:
            for finder in sys.meta_path:
                spec = getattr(finder, "find_spec", lambda *a: None)(name, path, target)
                if spec is not None:
                    break
            else:
                return None
            loader = spec.loader
            run = loader.exec_module

            def exec_module(module):
                run(module)
                fast_class_check()

            loader.exec_module = exec_module
            return spec
        except Exception:
            return None


# --------------------------------------------------------------------------------------------------
# How long the kernels' first launches take: compiling (or loading from the offline cache)
# --------------------------------------------------------------------------------------------------
# A kernel instance's first launch that takes longer than this compiled it (a load from the offline cache
# takes tens of milliseconds); the first such launch of a process says so on the terminal. Where Taichi's
# compile step itself is timed (``clock_first_launches``), its CPU time on the launching thread decides
# instead: a load from the cache takes milliseconds of it, a compile a tenth of a second or more, however
# loaded the machine (where a load's wall time can pass COMPILING_S; docs/PERFORMANCE.md).
COMPILING_S = 1.0
COMPILING_CPU_S = 0.1


class KernelClock:
    """Seconds spent in each kernel instance's first launch (Taichi's front end, then compiling the
    instance or loading it from the offline cache, then its first run), summed over the process;
    ``compiled`` counts the launches that took longer than ``COMPILING_S``. ``notice`` (set by the CLI) is
    called once, when the first such launch ends."""

    def __init__(self):
        self.seconds = 0.0
        self.instances = 0
        self.compiled = 0
        self.compile_s = 0.0
        self.by_kernel: dict[str, float] = {}  # kernel name → seconds of its instances' first launches that compiled
        self.launches: list[tuple[str, float, bool]] = []  # (name, seconds, compiled) of each first launch, in order
        self.elsewhere_s = 0.0  # of compile_s, the seconds compiled in other processes (``add(..., elsewhere=True)``)
        self.notice = None

    def add(self, seconds: float, name: str = "?", compiled: bool | None = None, elsewhere: bool = False) -> None:
        """One first launch of ``seconds``; ``compiled``: whether it compiled the instance (None: judged by
        ``seconds`` against ``COMPILING_S``); ``elsewhere``: launched in another process (a frame reader's
        renderer), so its seconds are not this process's (``seconds`` leaves them out)."""
        if compiled is None:
            compiled = seconds > COMPILING_S
        self.launches.append((name, seconds, bool(compiled)))
        if not elsewhere:
            self.seconds += seconds
        self.instances += 1
        if compiled:
            if elsewhere:
                self.elsewhere_s += seconds
            self.compiled += 1
            self.compile_s += seconds
            self.by_kernel[name] = self.by_kernel.get(name, 0.0) + seconds
            if self.compiled == 1 and self.notice is not None:
                self.notice(seconds)


CLOCK = KernelClock()
_clocked = False


def clock_first_launches() -> bool:
    """Time every kernel instance's first launch into ``CLOCK`` (once per process); True when installed."""
    global _clocked
    if _clocked:
        return True
    try:
        from taichi.lang.kernel_impl import Kernel
    except ImportError:
        return False
    import time

    materialize, launch = Kernel.materialize, Kernel.launch_kernel
    pending: dict = {}  # the instance being materialised → the front end's seconds, until its first launch
    launched: dict[int, object] = {}  # id → the instance launched (held, so its wrapper's id stays its own)
    compile_cpu: dict = {}  # the instance being launched first → CPU seconds of its compile step (or load)
    try:
        from taichi._lib import core as _ti_core

        program = _ti_core.Program
        compile_kernel = program.compile_kernel
    except (ImportError, AttributeError):
        program = None

    def timed_compile(self, config, caps, kernel, *rest):
        start = time.thread_time()
        try:
            return compile_kernel(self, config, caps, kernel, *rest)
        finally:
            compile_cpu[id(kernel)] = time.thread_time() - start

    def timed_materialize(self, key=None, args=None, arg_features=None):
        if key is None or key in self.compiled_kernels:
            return materialize(self, key, args, arg_features)
        start = time.perf_counter()
        try:
            return materialize(self, key, args, arg_features)
        finally:
            kernel = self.compiled_kernels.get(key)
            if kernel is not None:
                pending[id(kernel)] = time.perf_counter() - start
                # a new instance has not been launched, even where it got a freed one's wrapper: after a reset,
                # pybind hands back the wrapper still registered at a reused address
                launched.pop(id(kernel), None)

    def timed_launch(self, t_kernel, *args):
        if id(t_kernel) in launched:
            return launch(self, t_kernel, *args)
        launched[id(t_kernel)] = t_kernel
        if program is not None:  # its compile step timed on this launch only: later launches pay nothing
            program.compile_kernel = timed_compile
        start = time.perf_counter()
        try:
            return launch(self, t_kernel, *args)
        finally:
            if program is not None:
                program.compile_kernel = compile_kernel
            cpu = compile_cpu.pop(id(t_kernel), None)
            CLOCK.add(pending.pop(id(t_kernel), 0.0) + time.perf_counter() - start, getattr(self.func, "__name__", "?"),
                      None if cpu is None else cpu > COMPILING_CPU_S)

    Kernel.materialize, Kernel.launch_kernel = timed_materialize, timed_launch
    _clocked = True
    return True


def offline_cache_files() -> tuple[str, int] | None:
    """(the folder of Taichi's offline kernel cache, how many cached kernels it holds), or None where the
    cache is off or this Taichi does not say where it is."""
    try:
        from taichi.lang import impl

        cfg = impl.current_cfg()
        if not cfg.offline_cache:
            return None
        folder = cfg.offline_cache_file_path
    except Exception:
        return None
    import os

    try:
        return folder, sum(1 for name in os.listdir(folder) if name.endswith(".tic"))
    except OSError:
        return folder, 0
