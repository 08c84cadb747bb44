"""PH-Dropout core library: cameras, data, renderers, trainers, PH-Dropout and metrics.

Pure library: nothing here imports web code. Importing it sets glibc's malloc to keep
freed memory (`phd_core.allocator`): the CLI, the service and library users all get it.
"""

from .allocator import keep_freed_memory

__version__ = "0.1.0"

keep_freed_memory()
