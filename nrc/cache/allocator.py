"""Process-wide tuning of glibc malloc for large, short-lived CPU tensors.

PyTorch's CPU allocator passes every tensor allocation to ``malloc``. glibc serves blocks above its
mmap threshold (adaptive, at most 32 MiB by default) with fresh ``mmap`` pages and unmaps them on
``free``, so each large temporary pays a page fault per 4 KiB page when first written. The radiance
cache allocates tens of MiB of temporaries per step (corner indices and weights of every hash-grid
level, the table gradient). In this project's VM an element-wise op writing a fresh 32 MiB tensor took
~15x longer than on reused memory, and a training step of a 16-level hash-grid cache (2^16 points,
one thread) ~1.6x longer. Raising the mmap and trim thresholds makes glibc keep freed memory in the
heap and reuse it. Cost: the process's resident size stays at its peak instead of shrinking.
"""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(threshold_bytes: int = 1 << 30) -> bool:
    """Let glibc keep and reuse freed blocks of up to ``threshold_bytes`` (< 2^31) instead of unmapping them.

    Idempotent and process-wide. Returns ``False`` (doing nothing) when the C library is not glibc.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    if not hasattr(libc, "gnu_get_libc_version"):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    value = min(int(threshold_bytes), (1 << 31) - 1)
    results = (mallopt(_M_MMAP_THRESHOLD, value), mallopt(_M_TRIM_THRESHOLD, value), mallopt(_M_TOP_PAD, 64 << 20))
    return all(r == 1 for r in results)
