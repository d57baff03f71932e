"""What the benchmarks that time NumPy share: NumPy at its best (``keep_freed_memory``), the conditions it
ran under for their headers (``numpy_conditions``), and the pause that keeps OpenBLAS's threads out of the
kernels' timings (``BLAS_SETTLE_S``).

The benchmarks import it as a sibling (``python scripts/bench_x.py`` has scripts/ on its path); it imports
nothing from scripts/, so that a test can load it from its file.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

# NumPy's matrix products wake OpenBLAS's worker threads, which spin for tens of ms afterwards: a benchmark
# waits this long after a NumPy call before timing the kernels, so that they do not share the cores
BLAS_SETTLE_S = 0.2

# glibc's mallopt parameters
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # the ceiling of glibc's own adaptive threshold on 64-bit


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed blocks of up to 32 MiB for reuse instead of returning them to the system
    (benchmarks call this before timing the NumPy references). By default blocks above a threshold that
    glibc adapts at run time are mmap-ed and unmapped on free, so NumPy's large temporaries page-fault
    afresh on every call, in some processes and not in others (docs/BENCHMARKS.md says by how much). Kept,
    NumPy is timed at its best, every run alike. Returns whether it took effect (False off glibc)."""
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)) and \
            bool(libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30))
    except (OSError, AttributeError):
        return False


# Environment settings that change how fast NumPy's BLAS runs. Some machines set OPENBLAS_CORETYPE (to an
# older core's kernels, as a guard against OpenBLAS bugs on newer CPUs); a benchmark names them beside
# its ratios.
BLAS_SETTINGS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def numpy_conditions(kept_freed_memory: bool) -> str:
    """How NumPy runs in a benchmark, for its header: freed memory kept or not (``keep_freed_memory``) and
    the BLAS settings in the environment."""
    text = ("freed memory kept (glibc): NumPy timed at its best" if kept_freed_memory
            else "freed memory returned to the system (not glibc)")
    blas = [f"{k}={os.environ[k]}" for k in BLAS_SETTINGS if k in os.environ]
    return text + (f"; NumPy's BLAS under {', '.join(blas)}" if blas else "")
