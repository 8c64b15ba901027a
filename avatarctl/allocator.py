"""glibc allocator tuning for the compute stages (fit, render, eval, demo).

PyTorch on the CPU allocates and frees many large tensors per ray chunk. glibc serves allocations above its mmap
threshold (dynamic, at most 32 MiB by default) with fresh `mmap` pages and returns them to the OS on free, so each
chunk page-faults its working set in again. Measured on the 2-core dev machine (`avatarctl render P --frames 0
--views cam01,cam04`, cpu-preset model, 2 threads): 9.80 s per 256² image with 18.0 s of system time and 7.9M minor
faults, vs 5.53 s per image, 1.7 s system time, 0.7M faults with the tuning below; peak RSS 2.44 -> 3.05 GB.

`tune()` raises the mmap threshold and the trim threshold (freed memory stays in the heap for reuse) with
`mallopt`. It is called explicitly by the CLI entry point, never at import. Off with `AVATARCTL_MALLOC_TUNING=0`;
a no-op where glibc is absent (macOS, musl).
"""

from __future__ import annotations

import os

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3  # glibc malloc.h
MMAP_THRESHOLD = 2**31 - 1  # mallopt takes a C int: ~2 GiB, above any per-chunk tensor, so they come from the heap
TRIM_THRESHOLD = 2**31 - 1
TOP_PAD = 1 << 28  # grow the heap 256 MiB at a time


def tune() -> bool:
    """Apply the tuning; True if glibc accepted every setting."""
    if os.environ.get("AVATARCTL_MALLOC_TUNING", "1") == "0":
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    ok = True
    for param, value in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD)):
        ok = bool(mallopt(param, value)) and ok
    return ok
