"""Process-wide glibc malloc settings for the renderer's large temporaries.

By default glibc serves blocks above a dynamic threshold with fresh mmap calls and returns
freed memory to the kernel, so a render loop maps, faults in and unmaps the same large
buffers on every call: measured on ranking, system time was about twice the user time
(docs/performance.md). `keep_freed_memory` tells malloc to serve blocks up to its largest
mmap threshold from the heap, never to trim the heap and to grow it in large steps, which
is what MALLOC_MMAP_THRESHOLD_/MALLOC_TRIM_THRESHOLD_/MALLOC_TOP_PAD_ in the environment
do. `phd_core` calls it at import (so the CLI, the service and library users get it); set
PHD_KEEP_FREED_MEMORY=0 to leave malloc alone. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import os

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
    return all(r == 1 for r in results)
