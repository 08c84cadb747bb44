"""The executor protocol: share once, split into chunks, map a function over the chunks."""

from __future__ import annotations

from typing import Any, Callable, Protocol, Sequence, TypeVar, runtime_checkable

T = TypeVar("T")
R = TypeVar("R")

# Called with a chunk's position when that chunk's result is in (progress and cancellation:
# an exception raised here stops the map and is re-raised by it).
Done = Callable[[int], None]


class ExecutorError(RuntimeError):
    """The executor could not run a chunk (a cluster lost, workers dying past their retries):
    the work itself was fine, so callers may try again later."""


@runtime_checkable
class Executor(Protocol):
    name: str

    def connect(self) -> "Executor":
        """Reach the workers now (a cluster executor joins its cluster; an InputError when it
        cannot), so that a service fails at start-up rather than at its first job."""
        ...

    def share(self, value: Any) -> Any:
        """A handle that `map` passes to every chunk as `value`, stored where workers read it
        (Ray's object store) once. `value` must not change afterwards."""
        ...

    def split(self, items: Sequence[T]) -> list[list[T]]:
        """`items` cut into consecutive chunks, in order (one chunk is one unit of work)."""
        ...

    def map(self, fn: Callable[..., R], chunks: Sequence[Any], *shared: Any, done: Done | None = None) -> list[R]:
        """[fn(chunk, *shared) for chunk in chunks], in the order of `chunks`.

        `fn` must be picklable (a module-level function or a functools.partial of one);
        `shared` and the chunks may be handles from `share`. Stops at the first error
        (from fn or from `done`) and re-raises it.
        """
        ...
