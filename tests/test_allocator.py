"""phd_core.allocator in a fresh process: with one arena, memory a thread freed serves the
next thread instead of staying in the first thread's arena; release_freed_memory gives the
freed pages back (what the service's memory budget relies on between jobs); and
keep_freed_memory, which the entry points call, applies the settings (malloc keeps freed
memory, NumPy's huge pages off) unless PHD_KEEP_FREED_MEMORY=0; bounded_heap (the service's) maps
every large block on its own, so
resident memory is the blocks alive."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CODE = """
import sys, threading
from pathlib import Path
import phd_core.allocator as allocator
allocator.keep_freed_memory()                   # as the entry points do

def rss():
    line = next(l for l in Path("/proc/self/status").read_text().splitlines() if l.startswith("VmRSS:"))
    return int(line.split()[1]) * 1024

if sys.argv[1] == "one":
    assert allocator.one_arena()
done, hold = threading.Event(), threading.Event()

def work(wait):
    blocks = [bytearray(1 << 20) for _ in range(200)]        # 200 MiB in blocks under the mmap threshold
    del blocks
    done.set()
    if wait:
        hold.wait()                                           # alive: its arena stays its own

start = rss()
first = threading.Thread(target=work, args=(True,))
first.start()
done.wait()
second = threading.Thread(target=work, args=(False,))
second.start()
second.join()
held = rss() - start
allocator.release_freed_memory()
print(held, rss() - start)
hold.set()
"""


def two_numbers(code: str, mode: str) -> tuple[int, int]:
    """Run `code` with argument `mode` in a fresh interpreter; the two numbers it prints (bytes)."""
    out = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, check=True)
    first, second = out.stdout.split()
    return int(first), int(second)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc")
def test_one_arena_reuses_what_other_threads_freed_and_release_gives_it_back() -> None:
    per_thread, one = two_numbers(CODE, "per-thread"), two_numbers(CODE, "one")
    assert per_thread[0] > 350 << 20                 # each thread's arena kept its 200 MiB
    assert one[0] < 250 << 20                        # the second thread reused the first one's
    assert one[1] < 50 << 20 and per_thread[1] < 50 << 20     # and the freed pages went back


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_keep_freed_memory_sets_the_allocator_and_can_be_turned_off() -> None:
    # _set_madvise_hugepage returns NumPy's previous setting: huge pages off after keep_freed_memory.
    code = ("import numpy._core.multiarray as m, phd_core.allocator as a, phd_core; "
            "print(a.keep_freed_memory(), m._set_madvise_hugepage(True))")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    on = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**env, "PHD_KEEP_FREED_MEMORY": "0", "NUMPY_MADVISE_HUGEPAGE": "1"})
    assert on.stdout.split() == ["True", "False"] and off.stdout.split() == ["False", "True"]


HEAP = """
import sys
from pathlib import Path
import phd_core.allocator as allocator
allocator.keep_freed_memory()                   # as the entry points do: malloc keeps freed memory (a 1 GiB heap pad)

def status(key):
    line = next(l for l in Path("/proc/self/status").read_text().splitlines() if l.startswith(key + ":"))
    return int(line.split()[1]) * 1024

if sys.argv[1] == "bounded":
    assert allocator.bounded_heap()
start, pins = status("VmRSS"), []
Path("/proc/self/clear_refs").write_text("5")     # VmHWM from here
for mib in range(20, 32, 2):                      # batches that grow a little, one alive at a time
    block = bytearray(mib << 20)
    block[::4096] = bytes(len(range(0, mib << 20, 4096)))     # touched, as tensors are
    pins.append(bytearray(4096))                  # a small object malloc places above it, kept
    del block
print(status("VmHWM") - start, status("VmRSS") - start)
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="glibc malloc and Linux peak RSS")
def test_bounded_heap_holds_the_live_block_and_unmaps_it_when_freed() -> None:
    kept, bounded = two_numbers(HEAP, "kept"), two_numbers(HEAP, "bounded")
    assert kept[1] > 28 << 20                     # the heap kept the last freed block resident
    assert bounded[0] < 32 << 20                  # the largest block (30 MiB) and little more
    assert bounded[1] < 8 << 20                   # and nothing left once it is freed
