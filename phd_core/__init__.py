"""PH-Dropout core library: cameras, data, renderers, trainers, PH-Dropout and metrics.

Pure library: nothing here imports web code, and importing it changes nothing process-wide.
The entry points (the `phd` command, the service, Ray workers, the benches, the tests) set
glibc's malloc to keep freed memory (`phd_core.allocator.keep_freed_memory`).
"""

__version__ = "0.1.0"
