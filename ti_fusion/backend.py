"""Choosing and starting the Taichi backend.

One process runs on one backend. ``init_backend("auto")`` tries cuda, then vulkan, then cpu. Taichi
itself silently falls back to the CPU when a GPU backend is missing; we check what actually started so
that asking for an absent backend fails at once with one line that says what is missing.
"""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass

from .errors import BackendUnavailable

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

    @property
    def has_f64(self) -> bool:
        """Whether kernels may accumulate in float64 (GPU backends do not promise 64-bit floats)."""
        return self.arch == "cpu"


_current: BackendInfo | None = None


def _started_arch() -> str:
    import taichi as ti

    arch = ti.lang.impl.current_cfg().arch
    if arch in (ti.x64, ti.arm64):
        return "cpu"
    return arch.name


def _try_start(arch: str, **kwargs) -> bool:
    """Start Taichi on ``arch``; False (and Taichi reset) when that backend is absent."""
    import taichi as ti

    ti.reset()
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
    kwargs.setdefault("default_fp", None)
    kwargs = {k: v for k, v in kwargs.items() if v is not None}
    if requested == "auto":
        missing = []
        for arch in ("cuda", "vulkan"):
            if _try_start(arch, **kwargs):
                reason = f"auto: picked {arch}" + (f" ({'; '.join(missing)})" if missing else "")
                _current = BackendInfo(arch, requested, reason)
                return _current
            missing.append(f"no {arch}")
        _try_start("cpu", **kwargs)
        _current = BackendInfo("cpu", requested, f"auto: picked cpu ({'; '.join(missing)})")
        return _current
    if requested == "cpu":
        _try_start("cpu", **kwargs)
        _current = BackendInfo("cpu", requested, "requested cpu")
        return _current
    if not _try_start(requested, **kwargs):
        import taichi as ti

        ti.reset()
        _current = None
        raise BackendUnavailable(f"backend {requested} unavailable: {_HOW_TO_GET[requested]}")
    _current = BackendInfo(requested, requested, f"requested {requested}")
    return _current


def current_backend() -> BackendInfo:
    """The running backend; starts the CPU backend (or $TI_FUSION_ARCH) if nothing was started yet."""
    if _current is None:
        return init_backend(os.environ.get("TI_FUSION_ARCH", "cpu"))
    return _current


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
