"""Backend selection: what starts, and the one-line message when a backend is absent."""

import os
import subprocess
import sys
import threading

import pytest

from ti_fusion import backend
from ti_fusion.backend import init_backend
from ti_fusion.errors import BackendUnavailable


def _has_cuda() -> bool:
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


@pytest.mark.skipif(_has_cuda(), reason="this machine has CUDA")
def test_missing_cuda_is_one_clear_line():
    with pytest.raises(BackendUnavailable) as info:
        init_backend("cuda")
    message = str(info.value)
    assert "\n" not in message
    assert "CUDA" in message and "--arch" in message
    assert backend._current is None  # nothing half-started is left behind


def test_unknown_backend():
    with pytest.raises(BackendUnavailable, match="unknown backend"):
        init_backend("metal-ish")


def test_auto_picks_and_says_why():
    info = init_backend("auto")
    assert info.arch in ("cuda", "vulkan", "cpu")
    assert info.reason.startswith(f"auto: picked {info.arch}")
    assert info.has_f64 == (info.arch == "cpu")
    init_backend("cpu")


def test_cli_missing_backend_exits_with_one_line(tmp_path):
    if _has_cuda():
        pytest.skip("this machine has CUDA")
    proc = subprocess.run(
        [sys.executable, "-m", "ti_fusion", "icp", "--arch", "cuda", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )
    if "invalid choice" in proc.stderr:
        pytest.skip("icp command not available yet")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "cuda" in lines[0].lower() and "--arch" in lines[0]


def _single_cpu_threads() -> list[int]:
    """CPU of every thread of this process whose affinity is one CPU."""
    out = []
    for tid in os.listdir("/proc/self/task"):
        try:
            cpus = os.sched_getaffinity(int(tid))
        except ProcessLookupError:  # a thread that has just ended
            continue
        if len(cpus) == 1:
            out.extend(cpus)
    return out


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux and at least 2 CPUs")
def test_cpu_workers_are_pinned_one_per_cpu(monkeypatch):
    """Taichi's workers are pinned, each to its own CPU; a thread that was busy before Taichi started (a
    Python thread here, OpenBLAS's elsewhere) is not, though it also runs during the probe kernel."""
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            sum(range(1000))

    busy = threading.Thread(target=spin, daemon=True)
    busy.start()
    try:
        info = init_backend("cpu")
        assert "worker threads pinned to CPUs" in info.reason
        assert os.sched_getaffinity(busy.native_id) == os.sched_getaffinity(0)
    finally:
        stop.set()
        busy.join()
    cpus = _single_cpu_threads()
    assert len(set(cpus)) >= 2, cpus  # at least two workers, on different CPUs
    monkeypatch.setenv("TI_FUSION_PIN_THREADS", "0")
    assert backend.pin_cpu_workers() == ""  # the opt-out


def _run_fresh(tmp_path, code: str) -> str:
    script = tmp_path / "script.py"  # (Taichi reads a kernel's source from its file)
    script.write_text(code)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


_ASK_IN_A_KERNEL = """
x = ti.field(ti.i32, shape=4)

@ti.kernel
def fill():
    for i in x:
        if ti.static(backend.on_cpu()):
            x[i] = 1
        else:
            x[i] = 2
"""


def test_on_cpu_restarts_no_taichi_started_by_hand(tmp_path):
    """In a process that ran ti.init itself, asking on_cpu (while a kernel compiles, or as an index map is made)
    answers from that program: it neither starts Taichi again (which would free its fields and drop its
    settings) nor breaks the kernel's compilation."""
    out = _run_fresh(tmp_path, """
import taichi as ti
from taichi.lang import impl
from ti_fusion import backend
from ti_fusion.kernels.index_map import IndexMap
ti.init(arch=ti.cpu, log_level=ti.ERROR, kernel_profiler=True)
runtime = impl.get_runtime()
""" + _ASK_IN_A_KERNEL + """
fill()
imap = IndexMap(4, 4)
assert impl.get_runtime() is runtime and impl.current_cfg().kernel_profiler, "Taichi was started again"
print(backend.on_cpu(), imap.packed_keys, x.to_numpy().tolist())
""")
    assert out.strip().splitlines()[-1] == "True True [1, 1, 1, 1]", out


def test_on_cpu_answers_for_the_backend_taichi_runs(tmp_path):
    """After init_backend("cpu"), a program started by hand on vulkan gets the GPU's kernel variants and
    layout: the CPU's answer recorded by init_backend must not leak onto it."""
    if os.environ.get("TI_FUSION_NO_VULKAN") is not None:
        pytest.skip("TI_FUSION_NO_VULKAN is set")
    out = _run_fresh(tmp_path, """
import taichi as ti
from ti_fusion import backend
from ti_fusion.kernels.index_map import IndexMap
backend.init_backend("cpu")
assert backend.on_cpu()
try:
    ti.init(arch=ti.vulkan, log_level=ti.ERROR, enable_fallback=False)
except RuntimeError:
    print("no vulkan")
    raise SystemExit(0)
""" + _ASK_IN_A_KERNEL + """
fill()
print(backend.on_cpu(), IndexMap(4, 4).packed_keys, x.to_numpy().tolist())
""")
    if out.strip().splitlines()[-1] == "no vulkan":
        pytest.skip("no Vulkan device (apt-get install mesa-vulkan-drivers for lavapipe)")
    assert out.strip().splitlines()[-1] == "False False [2, 2, 2, 2]", out
