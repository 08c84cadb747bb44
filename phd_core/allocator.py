"""Process-wide glibc malloc settings for the renderer's large temporaries.

By default glibc serves blocks above a dynamic threshold with fresh mmap calls and returns
freed memory to the kernel, so a render loop maps, faults in and unmaps the same large
buffers on every call: measured on ranking, system time was about twice the user time
(docs/performance.md). `keep_freed_memory` tells malloc to serve blocks up to its largest
mmap threshold from the heap, never to trim the heap and to grow it in large steps, which
is what MALLOC_MMAP_THRESHOLD_/MALLOC_TRIM_THRESHOLD_/MALLOC_TOP_PAD_ in the environment
do. It also stops NumPy from asking for transparent huge pages on its large arrays (its
default on Linux): the kernels' scratch arrays then sit in 2 MiB pages that the kernel
zeroes whole on every fresh fault, which doubled calibration's system time (0.73 s -> 0.36 s
median of 5 runs, `phd calibrate` of docs/performance.md's model).
`phd_core` calls it at import (so the CLI, the service and library users get it); set
PHD_KEEP_FREED_MEMORY=0 to leave malloc and NumPy alone. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

# mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20      # glibc's ceiling on 64-bit (larger values are refused)
TRIM_THRESHOLD = (1 << 31) - 1     # mallopt takes an int: about 2 GiB, i.e. never trim in practice
TOP_PAD = 1 << 30                  # grow the heap 1 GiB at a time (address space; pages fault in on use)


def keep_freed_memory() -> bool:
    """Apply the settings; True when glibc accepted all three."""
    if os.environ.get("PHD_KEEP_FREED_MEMORY", "1") == "0":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    results = [mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX), mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD),
               mallopt(M_TOP_PAD, TOP_PAD)]
    core = np._core if hasattr(np, "_core") else np.core       # NumPy 2 / 1
    set_madvise_hugepage = getattr(core.multiarray, "_set_madvise_hugepage", None)
    if set_madvise_hugepage is not None:            # NumPy's switch (env NUMPY_MADVISE_HUGEPAGE at its import)
        set_madvise_hugepage(False)
    return all(r == 1 for r in results)
