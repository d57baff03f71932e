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
    _installed = True
    return True


def _memoize_source_lines() -> None:
    """Keep ``getsourcelines``'s answer per function (the function itself is the key, so a function that
    is gone cannot hand its source to a new one at the same address); the caller copies the list."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return
    original = getattr(kernel_impl, "getsourcelines", None)
    if original is None:
        return
    cache: dict = {}

    def getsourcelines(func):
        lines = cache.get(func)
        if lines is None:
            lines = cache[func] = original(func)
        return lines

    getsourcelines.__wrapped__ = original
    kernel_impl.getsourcelines = getsourcelines


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
    launched: dict[int, object] = {}  # id → the instance, held: a freed instance's id may be a new one's
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


# --------------------------------------------------------------------------------------------------
# A shorter launch path for kernel instances already launched once
# --------------------------------------------------------------------------------------------------
_fast_installed = False
_TEMPLATE, _ARRAY, _FLOAT, _INT, _UINT, _MATRIX = range(6)
_MAX_PLANS = 256  # per kernel; more means objects made per call, which Taichi would compile anew anyway


class _Plan:
    """What a launch of one kernel instance needs, for arguments like the ones it was made from: Taichi's key
    of the instance, the instance, and weak references to the objects whose ids are in the plan's key."""

    __slots__ = ("key", "t_kernel", "refs")

    def __init__(self, key, t_kernel, refs):
        self.key, self.t_kernel, self.refs = key, t_kernel, refs


def fast_launches() -> bool:
    """Launch a kernel instance that has run before without Taichi 1.7's generic Python path; True when
    installed (once per process). Taichi's ``Kernel.__call__`` works out the instance from every argument
    (``TaichiCallableTemplateMapper.extract``: a weak reference per data-oriented object, the dtype and
    shape of every array) and then sets each argument through nested closures and type dispatch; that is
    about half of a launch's host time, and a frame launches about twenty kernels (docs/PERFORMANCE.md).
    Here each kernel keeps, per kind of call (its template arguments' identities, its arrays' dtypes and
    dimensions), the instance Taichi chose for it, and sets the arguments from a list made once from the
    annotations: the same instance, the same argument values, the same launch. Anything else (keyword
    arguments, autodiff, a tape, a struct or argument-pack argument, a non-contiguous array, an argument
    of another type than last time, a first launch) takes Taichi's own path, which also raises its errors."""
    global _fast_installed
    if _fast_installed:
        return True
    try:
        import weakref

        import numpy as np
        from taichi.lang import impl, kernel_impl, runtime_ops
        from taichi.lang._ndarray import Ndarray
        from taichi.lang.enums import AutodiffMode, Layout
        from taichi.lang.exception import handle_exception_from_cpp
        from taichi.lang.matrix import MatrixType
        from taichi.lang.util import cook_dtype
        from taichi.types import ndarray_type, primitive_types, template
        from taichi.types.utils import is_signed
    except ImportError:
        return False
    Kernel = kernel_impl.Kernel
    original = Kernel.__call__
    if not all(hasattr(Kernel, name) for name in ("ensure_compiled", "construct_kernel_ret")):
        return False
    none_mode = AutodiffMode.NONE
    primitives = (int, float, bool)
    int32_max = np.iinfo(np.int32).max

    def spec_of(kernel):
        """(the arguments' setters, the template positions, the array positions) from the annotations, or
        None where an argument is of a kind this path does not set."""
        setters, templates, arrays = [], [], []
        slot = 0
        for i, argument in enumerate(kernel.arguments):
            anno = argument.annotation
            if isinstance(anno, template):
                templates.append(i)
                continue
            index = (slot,)
            slot += 1
            if isinstance(anno, ndarray_type.NdarrayType):
                if anno.dtype is None or id(anno.dtype) in primitive_types.type_ids:
                    element_dim = 0
                else:
                    element_dim = anno.dtype.ndim
                setters.append((_ARRAY, i, index, (element_dim, anno.layout == Layout.SOA)))
                arrays.append((i, element_dim))
            elif id(anno) in primitive_types.real_type_ids:
                setters.append((_FLOAT, i, index, None))
            elif id(anno) in primitive_types.integer_type_ids:
                setters.append((_INT if is_signed(cook_dtype(anno)) else _UINT, i, index, None))
            elif isinstance(anno, MatrixType) and anno.ndim in (1, 2) and (
                    anno.dtype in primitive_types.real_types or anno.dtype in primitive_types.integer_types):
                setters.append((_MATRIX, i, index, anno))
            else:
                return None
        return tuple(setters), tuple(templates), tuple(arrays)

    def key_of(spec, args):
        """The call's key (None: take Taichi's path) and the objects whose identity it holds."""
        parts, held = [], []
        for i in spec[1]:
            parts.append(template_key(args[i], held))
        for i, element_dim in spec[2]:
            v = args[i]
            if type(v) is np.ndarray:
                parts.append((v.dtype, v.ndim, v.shape[v.ndim - element_dim:] if element_dim else ()))
            elif isinstance(v, Ndarray):
                parts.append(id(v))
                held.append(v)
            else:
                return None, None
        return tuple(parts), held

    def template_key(v, held):
        """A template argument's part of the key: a number by value and a tuple by its items, as Taichi
        keys them; any other object by its id, held (weakly, by the plan) so the id cannot be another's."""
        kind = type(v)
        if kind in primitives:
            return (v,)
        if kind is tuple:
            return ("tuple",) + tuple(template_key(x, held) for x in v)
        held.append(v)
        return id(v)

    def set_args(spec, t_kernel, args):
        """A launch context with the call's arguments set as Taichi sets them; None where one of them is
        not what this path sets (Taichi's path then decides, and raises its own error if it is wrong)."""
        ctx = t_kernel.make_launch_context()
        for kind, i, index, extra in spec[0]:
            v = args[i]
            if kind == _ARRAY:
                element_dim, soa = extra
                if type(v) is np.ndarray:
                    if not v.flags.c_contiguous or v.size > int32_max:
                        return None
                    shape = v.shape
                    if element_dim:
                        shape = shape[element_dim:] if soa else shape[:-element_dim]
                    ctx.set_arg_external_array_with_shape(index, int(v.ctypes.data), v.nbytes, shape, 0)
                else:  # a Taichi ndarray (key_of let nothing else through)
                    if v.grad is not None:
                        return None
                    ctx.set_arg_ndarray(index, v.arr)
            elif kind == _FLOAT:
                if not isinstance(v, (float, int, np.floating, np.integer)):
                    return None
                ctx.set_arg_float(index, float(v))
            elif kind == _INT or kind == _UINT:
                if not isinstance(v, (int, np.integer)):
                    return None
                (ctx.set_arg_int if kind == _INT else ctx.set_arg_uint)(index, int(v))
            else:  # _MATRIX
                real = extra.dtype in primitive_types.real_types
                if real:
                    setter, types, cast = ctx.set_struct_arg_float, (int, float, np.integer, np.floating), float
                else:
                    setter = ctx.set_struct_arg_int if is_signed(cook_dtype(extra.dtype)) else ctx.set_struct_arg_uint
                    types, cast = (int, np.integer), int
                try:
                    if extra.ndim == 2:
                        values = [v[r, c] for r in range(extra.n) for c in range(extra.m)]
                    else:
                        values = [v[r] for r in range(extra.n)]
                except Exception:
                    return None
                for k, x in enumerate(values):
                    if not isinstance(x, types):
                        return None
                    setter(index + (k,), cast(x))
        return ctx

    def __call__(self, *args, **kwargs):
        runtime = self.runtime
        if (kwargs or self.autodiff_mode != none_mode or runtime.fwd_mode_manager or runtime.target_tape
                or len(args) != len(self.arguments)):
            return original(self, *args, **kwargs)
        spec = self.__dict__.get("_fast_spec", False)
        if spec is False:
            spec = self._fast_spec = spec_of(self)
            self._fast_plans = {}
        if spec is None:
            return original(self, *args)
        key, held = key_of(spec, args)
        if key is None:
            return original(self, *args)
        plans = self._fast_plans
        plan = plans.get(key)
        # a plan's ids are its objects' while they live (a dead one's id may be another's now)
        if plan is None or any(ref() is None for ref in plan.refs) or \
                self.compiled_kernels.get(plan.key) is not plan.t_kernel:
            result = original(self, *args)  # compiles (or loads) and launches as Taichi does
            try:
                refs = tuple(weakref.ref(v) for v in held)
            except TypeError:  # an object without weak references: its id alone cannot be trusted
                return result
            instance_key = (self.func, self.mapper.lookup(args)[0], self.autodiff_mode)
            t_kernel = self.compiled_kernels.get(instance_key)
            if t_kernel is not None:
                if len(plans) >= _MAX_PLANS:
                    plans.clear()
                plans[key] = _Plan(instance_key, t_kernel, refs)
            return result
        runtime.materialize()  # as Taichi's path: fields made since the last launch get their tree now
        ctx = set_args(spec, plan.t_kernel, args)
        if ctx is None:
            return original(self, *args)
        try:
            prog = impl.get_runtime().prog
            compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), plan.t_kernel)
            prog.launch_kernel(compiled, ctx)
        except Exception as e:
            e = handle_exception_from_cpp(e)
            if impl.get_runtime().print_full_traceback:
                raise e
            raise e from None
        returns = self.return_type
        if returns is not None or self.has_print:
            runtime_ops.sync()
        if returns is None:
            return None
        values = [self.construct_kernel_ret(ctx, t, (i,)) for i, t in enumerate(returns)]
        return values[0] if len(returns) == 1 else values

    __call__.__wrapped__ = original
    Kernel.__call__ = __call__
    _fast_installed = True
    return True
