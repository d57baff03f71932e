"""A shorter launch path for Taichi kernel instances launched before (``fast_launches``): Taichi 1.7's generic
``Kernel.__call__`` works out the instance and sets every argument anew on each launch, about half of a
launch's host time (docs/PERFORMANCE.md, "the loop's thread").
"""

from __future__ import annotations

_fast_installed = False
_TEMPLATE, _ARRAY, _FLOAT, _INT, _UINT, _MATRIX = range(6)
_MAX_PLANS = 256  # per kernel; more means objects made per call, which Taichi would compile anew anyway


class _Plan:
    """What a launch of one kernel instance needs, for arguments like the ones it was made from: Taichi's key
    of the instance, the instance, and weak references to the objects whose ids are in the plan's key."""

    __slots__ = ("key", "t_kernel", "refs", "compiled")

    def __init__(self, key, t_kernel, refs):
        self.key, self.t_kernel, self.refs = key, t_kernel, refs
        self.compiled = None  # (the program, its compiled kernel data of t_kernel), after the first launch here


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

    def materialized(runtime) -> bool:
        """Whether ``runtime.materialize()`` would do nothing: no field, gradient or matrix field made since its
        last call (it empties those lists), no fields builder left unfinalised but the root's, and the root
        finalised or still empty. Its checks then cost a launch a few microseconds for nothing."""
        try:
            fb = impl._root_fb
            return (runtime.materialized and (fb.finalized or fb.empty) and not runtime.global_vars
                    and not runtime.grad_vars and not runtime.dual_vars and not runtime.matrix_fields
                    and all(b is fb for b in runtime.unfinalized_fields_builder))
        except Exception:  # Taichi not initialised, or another layout: its own materialize decides
            return False

    def same_as_last(kernel, spec, args):
        """The last call's plan where this call's template arguments are the very objects it had (held by the
        kernel until its next call, so none of them can have died and left its id to another), its NumPy
        arrays have the same dtypes and shapes as the key reads them and its Taichi ndarrays are the same
        objects: the key and the plan it finds would be the same, so they are not worked out again (a launch
        with the same fields as the last, as most of a frame's are)."""
        last = kernel.__dict__.get("_fast_last")
        if last is None:
            return None
        plan, objects, arrays = last
        for i, o in zip(spec[1], objects):
            if args[i] is not o:
                return None
        for (i, element_dim), part in zip(spec[2], arrays):
            v = args[i]
            if type(v) is np.ndarray:
                if type(part) is not tuple or part != (v.dtype, v.ndim, v.shape[v.ndim - element_dim:]
                                                       if element_dim else ()):
                    return None
            elif v is not part:
                return None
        if kernel.compiled_kernels.get(plan.key) is not plan.t_kernel:
            return None
        return plan

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
        plan = same_as_last(self, spec, args)
        if plan is None:
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
            self._fast_last = (plan, tuple(args[i] for i in spec[1]),
                               tuple(args[i] if type(args[i]) is not np.ndarray else part
                                     for (i, _), part in zip(spec[2], key[len(spec[1]):])))
        if not materialized(runtime):
            runtime.materialize()  # as Taichi's path: fields made since the last launch get their tree now
        ctx = set_args(spec, plan.t_kernel, args)
        if ctx is None:
            return original(self, *args)
        try:
            prog = impl.get_runtime().prog
            known = plan.compiled
            if known is not None and known[0] is prog:
                compiled = known[1]
            else:
                # The program's compiled data of the instance: compile_kernel looks it up by a key it rebuilds
                # from the config each call (with config() and get_device_caps()); it stays in the
                # program's cache for the program's life, and a new program (ti.init) resets every instance,
                # so the plan with it.
                compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), plan.t_kernel)
                plan.compiled = (prog, compiled)
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
