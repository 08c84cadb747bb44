"""Executors: where PH-Dropout's per-view work runs (ranking, calibration, selection).

The engine (`phd_core.uq`) cuts its views into chunks, maps one function over them and
merges the results in order, so every executor gives exactly the single-process answer
for a seed: the keep-masks are drawn once, in the caller, and every chunk gets the same ones.

    local  (default) this process, one view per chunk; needs nothing beyond the base install
    ray    Ray tasks on a cluster (`pip install .[ray]`); ray is imported only when used

An executor is one module plus one `ExecutorKind` in EXECUTORS (its name and a factory taking
the cluster address, None for the executor's default); the CLI and the service read the
names from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..registry import Registry
from .base import Executor, ExecutorError
from .local import LOCAL, LocalExecutor


@dataclass(frozen=True)
class ExecutorKind:
    name: str
    make: Callable[[str | None], Executor]     # (cluster address, None: the default) -> the executor


def _ray(address: str | None = None) -> Executor:
    from .ray import RayExecutor  # the module imports ray only when the executor connects

    return RayExecutor(address)


def _local(address: str | None = None) -> Executor:
    return LOCAL


EXECUTORS: Registry[ExecutorKind] = Registry("executor")
EXECUTORS.register(ExecutorKind("local", _local))
EXECUTORS.register(ExecutorKind("ray", _ray))


def make_executor(name: str = "local", address: str | None = None, field: str = "executor") -> Executor:
    """The executor registered as `name` (an InputError naming `field` when unknown)."""
    return EXECUTORS.lookup(name, field).make(address)


__all__ = ["EXECUTORS", "LOCAL", "Executor", "ExecutorError", "ExecutorKind", "LocalExecutor", "make_executor"]
