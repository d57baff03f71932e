"""Choosing and starting the Taichi backend.

One process runs on one backend. ``init_backend("auto")`` tries cuda, then vulkan, then cpu. Taichi
itself silently falls back to the CPU when a GPU backend is missing; we check what actually started so
that asking for an absent backend fails at once with one line that says what is missing.

On the CPU (Linux), Taichi's worker threads are pinned one per logical CPU once it has started
(``pin_cpu_workers``; ``TI_FUSION_PIN_THREADS=0`` turns it off): left to the scheduler, both workers can
be woken on the same core, so a kernel of a few milliseconds runs on one core while the other idles
(docs/PERFORMANCE.md has the measurements).
"""

from __future__ import annotations

import contextlib
import io
import os
import threading
import weakref
from dataclasses import dataclass, field

from ti_fusion.errors import BackendUnavailable, TiFusionError

ARCH_CHOICES = ("cpu", "cuda", "vulkan", "auto")

_HOW_TO_GET = {
    "cuda": "no CUDA driver found (libcuda.so): install the NVIDIA driver on a machine with an NVIDIA GPU, "
    "or use --arch vulkan / --arch cpu",
    "vulkan": "no Vulkan device found: install a Vulkan driver (without a GPU, Mesa's software driver: "
    "apt-get install mesa-vulkan-drivers), or use --arch cpu",
}


@dataclass(frozen=True)
class BackendInfo:
    """The backend a process runs on, and why it was picked."""

    arch: str  # "cpu", "cuda" or "vulkan"
    requested: str
    reason: str
    # Which start of Taichi this is (every init_backend resets Taichi and frees what was made before), and the
    # thread that started it: Taichi 1.7 allocates fields only on that thread.
    generation: int = field(default=0, compare=False)
    thread: int = field(default_factory=threading.get_ident, compare=False)
    thread_name: str = field(default_factory=lambda: threading.current_thread().name, compare=False)

    @property
    def has_f64(self) -> bool:
        """Whether kernels may accumulate in float64 (GPU backends do not promise 64-bit floats)."""
        return self.arch == "cpu"


_current: BackendInfo | None = None
_generation = 0  # starts of Taichi so far in this process


class BackendMisuse(TiFusionError):
    """Taichi objects used where they cannot work: after Taichi was started again, or from another thread."""


# Environment variables Taichi reads in ti.init that abort the process (no exception) when their value is
# not a backend's name.
_TAICHI_ARCH_VARS = ("TI_ARCH",)
_TAICHI_ARCH_NAMES = ("cpu", "x64", "arm64", "cuda", "vulkan", "metal", "opengl", "gles", "dx11", "dx12", "amdgpu")


def check_environment() -> None:
    """BackendUnavailable for an environment that would make Taichi abort the process without a word: an
    unknown backend name in $TI_ARCH (an unset $HOME is filled in when ti_fusion is imported)."""
    for name in _TAICHI_ARCH_VARS:
        value = os.environ.get(name)
        if value is not None and value.strip().lower() not in _TAICHI_ARCH_NAMES:
            raise BackendUnavailable(f"environment variable {name}={value!r} is not a Taichi backend (Taichi reads it "
                                     f"instead of --arch): unset it, or set one of cpu, cuda, vulkan")


def check_started(generation: int, what: str) -> None:
    """BackendMisuse when an object made on start ``generation`` of Taichi (``current_backend().generation``)
    is used after another start (its fields are freed: a kernel or read-back on them crashes the process)."""
    if _current is None or _current.generation != generation:
        raise BackendMisuse(f"{what}: made before Taichi was started again (init_backend resets Taichi and frees "
                            "every field made before): make a new one after the last init_backend")


def check_usable(generation: int, what: str) -> None:
    """``check_started``, and BackendMisuse when used on another thread than the one that started Taichi."""
    check_started(generation, what)
    if threading.get_ident() != _current.thread:
        raise BackendMisuse(f"{what} called on thread {threading.current_thread().name!r}, but Taichi allocates its "
                            f"fields only on the thread that started it ({_current.thread_name!r}, in init_backend): "
                            "call init_backend, make the DenseSLAM and call register_frame all on one thread, e.g. "
                            "one worker thread that takes frames from a queue.Queue (docs/DATA.md, 'Threads')")


def _started_arch() -> str:
    import taichi as ti

    arch = ti.lang.impl.current_cfg().arch
    if arch in (ti.x64, ti.arm64):
        return "cpu"
    return arch.name


def _try_start(arch: str, **kwargs) -> bool:
    """Start Taichi on ``arch``; False (and Taichi reset) when that backend is absent."""
    import taichi as ti

    from ti_fusion.frontend import clock_first_launches, fast_class_check, memoize_source_positions
    from ti_fusion.launches import fast_launches

    memoize_source_positions()
    fast_class_check()
    clock_first_launches()
    fast_launches()
    global _threads_before_init, _generation
    _generation += 1
    ti.reset()
    _threads_before_init = _thread_ids()
    try:
        # Taichi prints "[Taichi] Starting on arch=..." itself; we report the backend our own way.
        with contextlib.redirect_stdout(io.StringIO()):
            ti.init(arch=getattr(ti, arch), log_level=ti.ERROR, enable_fallback=False, **kwargs)
    except RuntimeError:
        ti.reset()
        return False
    return _started_arch() == arch


def init_backend(requested: str = "cpu", **kwargs) -> BackendInfo:
    """Start Taichi on ``requested`` (cpu, cuda, vulkan or auto); raise BackendUnavailable if absent."""
    global _current
    requested = requested.lower()
    if requested not in ARCH_CHOICES:
        raise BackendUnavailable(f"unknown backend {requested!r}: choose one of {', '.join(ARCH_CHOICES)}")
    check_environment()
    kwargs.setdefault("default_fp", None)
    kwargs = {k: v for k, v in kwargs.items() if v is not None}
    if requested == "auto":
        missing = []
        for arch in ("cuda", "vulkan"):
            if _try_start(arch, **kwargs):
                reason = f"auto: picked {arch}" + (f" ({'; '.join(missing)})" if missing else "")
                _current = BackendInfo(arch, requested, reason, _generation)
                return _current
            missing.append(f"no {arch}")
        _try_start("cpu", **kwargs)
        _current = BackendInfo("cpu", requested, f"auto: picked cpu ({'; '.join(missing)})" + pin_cpu_workers(),
                               _generation)
        return _current
    if requested == "cpu":
        _try_start("cpu", **kwargs)
        _current = BackendInfo("cpu", requested, "requested cpu" + pin_cpu_workers(), _generation)
        return _current
    if not _try_start(requested, **kwargs):
        import taichi as ti

        ti.reset()
        _current = None
        raise BackendUnavailable(f"backend {requested} unavailable: {_HOW_TO_GET[requested]}")
    _current = BackendInfo(requested, requested, f"requested {requested}", _generation)
    return _current


# Below this many pixels (or surfels) a loop runs on the calling thread (CPU only): handing a loop to
# Taichi's thread pool and waiting for it costs more than the other threads save on so few items.
SERIAL_BELOW = 16384


def serial_for(n_items: int) -> bool:
    """Whether a loop over ``n_items`` should run on the calling thread (see SERIAL_BELOW)."""
    return n_items < SERIAL_BELOW and on_cpu()


_threads_before_init: set[int] = set()  # this process's threads before the last ti.init (Linux)


def _thread_ids() -> set[int]:
    try:
        return {int(tid) for tid in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def _thread_run_ns() -> dict[int, int]:
    """CPU time (ns) each thread of this process has run so far (Linux)."""
    out = {}
    for tid in _thread_ids():
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as f:
                out[tid] = int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            pass
    return out


def pin_cpu_workers() -> str:
    """Pin the running CPU backend's worker threads one per logical CPU; returns a note for the backend's
    reason ("" when nothing was pinned). Taichi does not name its workers: they are the threads that
    ``ti.init`` started and that run a short parallel kernel (``kernels.probe.busy``, run up to three
    times until every worker has taken part). Threads that were there before, such as a busy
    Python thread or OpenBLAS's, are left alone."""
    import threading

    import numpy as np
    import taichi as ti

    from ti_fusion.kernels.probe import busy

    if os.environ.get("TI_FUSION_PIN_THREADS", "1") == "0" or not hasattr(os, "sched_setaffinity") \
            or not os.path.isdir("/proc/self/task"):
        return ""
    cpus = sorted(os.sched_getaffinity(0))
    expected = min(ti.lang.impl.current_cfg().cpu_max_num_threads, len(cpus))
    if len(cpus) < 2 or expected < 2:
        return ""
    out = np.zeros(4096, dtype=np.float32)
    busy(out.shape[0], out)  # compiles
    new = _thread_ids() - _threads_before_init - {threading.get_native_id()}
    ran: dict[int, int] = {}
    for _ in range(3):
        before = _thread_run_ns()
        busy(out.shape[0], out)
        ti.sync()
        for tid, ns in _thread_run_ns().items():
            if tid in new:
                ran[tid] = ran.get(tid, 0) + ns - before.get(tid, ns)
        workers = sorted(tid for tid, ns in ran.items() if ns > 1_000_000)
        if len(workers) >= expected:
            break
    pinned = []
    for k, tid in enumerate(workers):
        cpu = cpus[k % len(cpus)]
        try:
            os.sched_setaffinity(tid, {cpu})
            pinned.append(cpu)
        except OSError:
            pass
    if not pinned:
        return ""
    return f"; {len(pinned)} worker threads pinned to CPUs {', '.join(map(str, pinned))}"


def current_backend() -> BackendInfo:
    """The running backend; starts the CPU backend (or $TI_FUSION_ARCH) if nothing was started yet."""
    if _current is None:
        return init_backend(os.environ.get("TI_FUSION_ARCH", "cpu"))
    return _current


_on_cpu_asked: tuple | None = None  # (weak reference to the Taichi runtime asked, its answer)


def on_cpu() -> bool:
    """Whether the kernels run on the CPU: what every CPU-only kernel variant and host-memory shortcut asks, in
    Python or at compile time (``if ti.static(on_cpu()):``). The running Taichi program answers, not what
    init_backend recorded, so that asking never restarts Taichi (started by ``ti.init`` itself, or a kernel
    compiled inside init_backend) nor answers for a backend no longer running; with none started, it starts
    one as ``current_backend`` does."""
    global _on_cpu_asked
    from taichi.lang import impl

    runtime = impl.get_runtime()  # a new one at every ti.init and ti.reset
    if runtime.prog is None:
        return current_backend().arch == "cpu"
    asked = _on_cpu_asked
    if asked is None or asked[0]() is not runtime:  # the program's config is read once: a read takes microseconds
        asked = _on_cpu_asked = (weakref.ref(runtime), _started_arch() == "cpu")
    return asked[1]


def vulkan_available() -> bool:
    """Whether a Vulkan device is present (leaves Taichi reset: call init_backend afterwards)."""
    import taichi as ti

    global _current
    try:
        ok = _try_start("vulkan")
    finally:
        ti.reset()
        _current = None
    return ok
