"""The Ray executor: chunks of views as Ray tasks on a cluster (`pip install .[ray]`).

The model and the keep-masks go to the object store once (`share`; a shared renderer is
remembered for as long as it lives, so the service's cached models are put once, not once
per job); every chunk is one task that reads them from there. A task whose worker dies is
run again (`max_retries`, Ray's retry of system failures); an error raised by the work
itself (bad input) is not retried and comes back as the original exception. Chunks finish
in any order but merge in order, so the answer is the local one.

Addresses: "auto" (default) joins the cluster `ray start` runs on this machine (or
RAY_ADDRESS); "local" starts a private one-machine instance; anything else is a cluster
address ("host:6379", "ray://host:10001"). A process that is already connected to Ray
(`ray.init` called) keeps that connection. Every node needs this package installed.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any, Callable, Sequence, TypeVar

from ..allocator import keep_freed_memory
from ..errors import InputError
from .base import Done, ExecutorError

T = TypeVar("T")
R = TypeVar("R")

DEFAULT_MAX_RETRIES = 3            # runs of a task whose worker died, after the first
CHUNKS_PER_CPU = 2                 # chunks per cluster CPU: balances uneven views, bounds per-task overhead


def import_ray():
    """The ray module, or an InputError that says how to install it."""
    try:
        import ray
    except ImportError:
        raise InputError("ray", "Ray is not installed: pip install 'ph-dropout-service[ray]' "
                                "(or pip install ray)") from None
    return ray


_worker_ready = False


def run_chunk(fn: Callable[..., R], chunk: Any, *shared: Any) -> R:
    """What one Ray task runs (module level, so workers import it instead of unpickling code).
    A worker's first task applies the `phd` command's malloc settings (phd_core.allocator)."""
    global _worker_ready
    if not _worker_ready:
        keep_freed_memory()
        _worker_ready = True
    return fn(chunk, *shared)


class RayExecutor:
    name = "ray"

    def __init__(self, address: str | None = None, *, max_retries: int = DEFAULT_MAX_RETRIES,
                 chunks_per_cpu: int = CHUNKS_PER_CPU):
        self.address = address or "auto"
        self.max_retries = max_retries
        self.chunks_per_cpu = chunks_per_cpu
        self._lock = threading.Lock()
        self._task: Any = None          # the Ray remote function, once connected
        self._shared: dict[int, tuple[weakref.ref, Any]] = {}     # id(value) -> (weakref, ObjectRef)

    def connect(self) -> "RayExecutor":
        """Join (or start) the cluster once; an InputError naming field 'ray' when that fails."""
        with self._lock:
            if self._task is not None:
                return self
            ray = import_ray()
            if not ray.is_initialized():
                try:
                    if self.address == "local":
                        ray.init(include_dashboard=False, log_to_driver=False)
                    else:
                        ray.init(address=self.address, log_to_driver=False)
                except (ConnectionError, RuntimeError, ValueError) as exc:
                    raise InputError("ray", f"cannot connect to the Ray cluster at {self.address!r}: {exc}") from None
            self._task = ray.remote(run_chunk).options(num_cpus=1, max_retries=self.max_retries,
                                                        retry_exceptions=False)
        return self

    def cpus(self) -> int:
        """CPUs of the cluster (what `split` sizes its chunks by)."""
        self.connect()
        return max(1, int(import_ray().cluster_resources().get("CPU", 1)))

    def share(self, value: Any) -> Any:
        ray = import_ray()
        self.connect()
        if isinstance(value, ray.ObjectRef):
            return value
        with self._lock:
            entry = self._shared.get(id(value))
            if entry is not None and entry[0]() is value:
                return entry[1]
        handle = ray.put(value)
        try:
            key = id(value)
            alive = weakref.ref(value, lambda _: self._forget(key))
        except TypeError:               # not weak-referenceable (tuples, lists): not remembered
            return handle
        with self._lock:
            self._shared[key] = (alive, handle)
        return handle

    def _forget(self, key: int) -> None:
        self._shared.pop(key, None)     # no lock: a weakref callback may run inside a locked section

    def split(self, items: Sequence[T]) -> list[list[T]]:
        items = list(items)
        count = min(len(items), self.cpus() * self.chunks_per_cpu)
        bounds = [round(i * len(items) / count) for i in range(count + 1)] if count else [0]
        return [items[a:b] for a, b in zip(bounds, bounds[1:])]

    def map(self, fn: Callable[..., R], chunks: Sequence[Any], *shared: Any, done: Done | None = None) -> list[R]:
        ray = import_ray()
        self.connect()
        handles = [self.share(value) for value in shared]
        pending = [self._task.remote(fn, chunk, *handles) for chunk in chunks]
        position = {ref: i for i, ref in enumerate(pending)}
        results: list[Any] = [None] * len(pending)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    results[position[ref]] = self._get(ray, ref, fn)
                    if done is not None:
                        done(position[ref])
        except BaseException:
            for ref in pending:         # a failed or cancelled map leaves no work behind
                ray.cancel(ref)
            raise
        return results

    def _get(self, ray, ref, fn: Callable) -> Any:
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, Exception):
                raise cause from None   # the work's own error (an InputError stays one)
            raise
        except ray.exceptions.RayError as exc:
            name = getattr(fn, "func", fn).__name__
            raise ExecutorError(f"Ray could not finish a chunk of {name} (retries: {self.max_retries}): "
                               f"{type(exc).__name__}: {exc}") from None

    def __repr__(self) -> str:
        return f"RayExecutor(address={self.address!r})"
