"""The default executor: every chunk in this process, one view per chunk, in order.

One view per chunk keeps progress and cancellation (both ride on `done`) as fine-grained
as a plain loop over the views.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence, TypeVar

from .base import Done

T = TypeVar("T")
R = TypeVar("R")


class LocalExecutor:
    name = "local"

    def connect(self) -> "LocalExecutor":
        return self

    def share(self, value: Any) -> Any:
        return value

    def split(self, items: Sequence[T]) -> list[list[T]]:
        return [[item] for item in items]

    def map(self, fn: Callable[..., R], chunks: Sequence[Any], *shared: Any, done: Done | None = None) -> list[R]:
        results = []
        for i, chunk in enumerate(chunks):
            results.append(fn(chunk, *shared))
            if done is not None:
                done(i)
        return results

    def __repr__(self) -> str:
        return "LocalExecutor()"


LOCAL = LocalExecutor()
