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
The entry points call it, not `import phd_core`: the `phd` command (`phd_cli.main`), the
service (`service.app.create_app`), Ray workers (`phd_core.executors.ray.run_chunk`), the
benches (bench/_harness.py) and the tests (tests/conftest.py); a library user who wants it
calls it too. Set PHD_KEEP_FREED_MEMORY=0 to leave malloc and NumPy alone. Elsewhere than
glibc the malloc part does nothing.

A process that runs large work on several threads and bounds its memory (the service) also
wants `one_arena`, `bounded_heap` and `release_freed_memory` (below).
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

# mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
MMAP_THRESHOLD_MAX = 32 << 20      # glibc's ceiling on 64-bit (larger values are refused)
TRIM_THRESHOLD = (1 << 31) - 1     # mallopt takes an int: about 2 GiB, i.e. never trim in practice
TOP_PAD = 1 << 30                  # grow the heap 1 GiB at a time (address space; pages fault in on use)
BOUNDED_MMAP_THRESHOLD = 1 << 20   # `bounded_heap`: blocks from 1 MiB up get their own mapping
BOUNDED_TOP_PAD = 128 << 10        # and the heap grows by glibc's default step


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def keep_freed_memory() -> bool:
    """Apply the settings; True when glibc accepted all three."""
    if os.environ.get("PHD_KEEP_FREED_MEMORY", "1") == "0":
        return False
    core = np._core if hasattr(np, "_core") else np.core       # NumPy 2 / 1
    set_madvise_hugepage = getattr(core.multiarray, "_set_madvise_hugepage", None)
    if set_madvise_hugepage is not None:            # NumPy's switch (env NUMPY_MADVISE_HUGEPAGE at its import)
        set_madvise_hugepage(False)
    return _mallopt((M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD))


def one_arena() -> bool:
    """Serve every thread from one malloc arena (call it before the threads start). With an
    arena per thread, what one thread frees stays in its arena, out of the others' reach: a
    process whose threads take turns with large temporaries then holds the sum of their
    peaks, not the peak of their sum (the service, 6 jobs and 2 uploads on 2 workers under a
    1 GiB budget: 1.6 GB over its idle RSS with an arena per thread, 0.77 GB with one;
    bench/bench_memory.py). True when glibc accepted it."""
    return _mallopt((M_ARENA_MAX, 1))


def bounded_heap() -> bool:
    """Serve every block of BOUNDED_MMAP_THRESHOLD or more by its own mapping, unmapped when it
    is freed, and keep the heap for small blocks: resident memory is then the blocks alive plus
    a small heap, so a memory plan that adds up the tensors alive at a job's worst moment bounds
    it. malloc serves a block from free heap space before it maps one, so the heap must grow in
    small steps (not `keep_freed_memory`'s 1 GiB) and its padding is trimmed here. Otherwise
    freed batches stay in the heap and the next ones land beside them: a rank at 400x400 with 64
    masks a batch held 113 bytes a pixel and mask where its live tensors peak at 61, and peaked
    differently from run to run (985 to 1,183 MiB, bench/bench_memory.py). Costs page faults on
    every large block (the CLI and library keep `keep_freed_memory`). True when glibc accepted it."""
    accepted = _mallopt((M_MMAP_THRESHOLD, BOUNDED_MMAP_THRESHOLD), (M_TOP_PAD, BOUNDED_TOP_PAD))
    release_freed_memory()
    return accepted


def release_freed_memory() -> bool:
    """Give the whole free pages of every arena back to the system (glibc malloc_trim): what a
    finished unit of work freed stops counting as resident. True when glibc released some."""
    libc = _libc()
    if libc is None or not hasattr(libc, "malloc_trim"):
        return False
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
    return libc.malloc_trim(0) == 1


def _mallopt(*settings: tuple[int, int]) -> bool:
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):
        return False
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    return all([libc.mallopt(param, value) == 1 for param, value in settings])
