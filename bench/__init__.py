"""The benchmarks: run each from the checkout's root as a module, `python -m bench.bench_speed`
(bench/README.md). Python imports this package before the script, so the process settings of
the `phd` command apply before any script loads torch: idle OpenMP threads sleep instead of
spinning (with spinning, torch on a busy 2-core machine runs several times slower,
docs/gaussians.md), and glibc's malloc keeps freed memory (phd_core.allocator;
PHD_KEEP_FREED_MEMORY=0 turns it off). What the scripts share is in bench/_harness.py."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")     # read once, when torch loads OpenMP

from phd_core.allocator import keep_freed_memory  # noqa: E402  (after the line above; loads no torch)

keep_freed_memory()
