"""Shared fixtures.

Taichi runs one backend per process, so the backend fixtures are session-scoped: pytest groups the
tests by backend and Taichi is re-initialised only when the backend changes.
- ``arch``: parametrised over cpu, vulkan (skipped with a reason where no device is present) and cuda
  (only where the CUDA driver finds a device; TI_FUSION_NO_CUDA=1 leaves it out);
  use it for kernel tests, which compare every backend against the same NumPy float64 reference.
- ``cpu``: the CPU backend only, for pipeline and end-to-end tests.
"""

from __future__ import annotations

import importlib.util
import os
import zlib
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.backend import init_backend, vulkan_available

# Matplotlib imported once per test process: the runs' trajectory.png is then drawn in-process, not by a
# plot process per run that imports it again (ti_fusion/evaluation/plot_process.py; tested there).
import matplotlib.figure  # noqa: F401

REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"
SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"

_vulkan_ok: bool | None = None


def _has_vulkan() -> bool:
    global _vulkan_ok
    if _vulkan_ok is None:
        _vulkan_ok = os.environ.get("TI_FUSION_NO_VULKAN") is None and vulkan_available()
    return _vulkan_ok


def _use(arch: str) -> str:
    from ti_fusion import backend

    if backend._current is None or backend._current.arch != arch:
        init_backend(arch)
    return arch


def _has_cuda() -> bool:
    """Whether the CUDA driver finds a device (asked through libcuda itself, without starting Taichi)."""
    if os.environ.get("TI_FUSION_NO_CUDA") is not None:
        return False
    import ctypes

    try:
        lib = ctypes.CDLL("libcuda.so.1")
        count = ctypes.c_int(0)
        return lib.cuInit(0) == 0 and lib.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0
    except (OSError, AttributeError):
        return False


# cuda is a parameter only where a CUDA device is found, so machines without one list no skipped cuda tests
ARCHES = ["cpu", "vulkan"] + (["cuda"] if _has_cuda() else [])


def use_arch(arch: str) -> str:
    """Start ``arch`` for a kernel test, or skip the test where it has no device."""
    if arch == "vulkan" and not _has_vulkan():
        pytest.skip("no Vulkan device (apt-get install mesa-vulkan-drivers for lavapipe)")
    return _use(arch)


@pytest.fixture(params=ARCHES)
def arch(request):
    return use_arch(request.param)


@pytest.fixture
def cpu():
    return _use("cpu")


@pytest.fixture
def rng(request):
    """A fresh random generator per test, seeded from the test's name so failures reproduce."""
    seed = zlib.crc32(request.node.nodeid.encode())  # stable across processes, unlike hash()
    return np.random.default_rng(seed)


@pytest.fixture
def redkitchen():
    if not (REDKITCHEN / "frame-000000.depth.png").is_file():
        pytest.skip(f"real data not found at {REDKITCHEN}")
    return REDKITCHEN


@pytest.fixture(scope="session")
def script():
    """``script("bench_icp_ceiling")``: a script of scripts/ loaded from its file (scripts/ stays off the
    path), for the tests that check that a benchmark times the computation it claims. A script loaded
    this way imports its sibling scripts only inside the functions that use them."""
    loaded = {}

    def load(name: str):
        if name not in loaded:
            spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            loaded[name] = module
        return loaded[name]

    return load


def pytest_collection_modifyitems(config, items):
    """The fast tier (``scripts/test.sh --fast``: every test not marked ``slow``) must still launch every
    kernel, so every kernel test (one on the ``arch`` fixture or an ``arch_...`` one) keeps a case unmarked:
    a parametrised one may mark its other cases slow, never all of them."""
    cases: dict[str, list[bool]] = {}
    for item in items:
        if any(name == "arch" or name.startswith("arch_") for name in getattr(item, "fixturenames", ())):
            cases.setdefault(item.nodeid.split("[")[0], []).append(item.get_closest_marker("slow") is not None)
    marked = [test for test, slow in cases.items() if all(slow)]
    if marked:
        raise pytest.UsageError(f"every case of these kernel tests (on the arch fixture) is marked slow, which "
                                f"takes them out of the fast tier: {', '.join(marked)}")


@pytest.fixture
def terminal_ctrl_c():
    """Ctrl-C as in a terminal for a run in this process: Python's own handler, which the run takes over, whatever
    this process inherited (pytest-xdist's workers ignore SIGINT, and a run leaves an ignored Ctrl-C ignored)."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    if previous is not None:  # (None: a handler not set from Python)
        signal.signal(signal.SIGINT, previous)


def terminal_signals() -> None:
    """``preexec_fn`` of a child process that a test stops as a terminal would: Ctrl-C and hang-up act as in a
    terminal, whatever the test process inherited (pytest-xdist's workers ignore SIGINT, nohup ignores
    SIGHUP, and an ignored signal stays ignored across exec)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
