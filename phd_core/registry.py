"""A registry: name -> entry, each name registered once.

Every growth point (model families, capture formats, strategies, ...) is one of these, with
one idiom: an entry carries its `name`, joins with `REGISTRY.register(entry)`, and is found
with `REGISTRY.lookup(name, field)`, whose error names the field and the known entries. The
CLI and the service read their allowed names from the registries, so a new entry needs no
other edit. Registries whose entries recognise files (capture formats, trainer outputs) try
them `in_order()`: by each entry's `order`, lowest first, never by import order.
"""

from __future__ import annotations

from typing import Protocol, TypeVar

from .errors import InputError


class Named(Protocol):
    @property
    def name(self) -> str: ...


T = TypeVar("T", bound=Named)


class Registry(dict[str, T]):
    def __init__(self, what: str):
        super().__init__()
        self.what = what            # for messages: "strategy", "model family"

    def register(self, entry: T) -> T:
        """Add `entry` under its name; a name is registered once."""
        if entry.name in self:
            raise ValueError(f"{self.what} {entry.name!r} is already registered")
        self[entry.name] = entry
        return entry

    def unknown(self, name: str) -> str:
        """Why `name` is not accepted: the message names the known entries."""
        return f"unknown {self.what} {name!r}; known: {', '.join(sorted(self))}"

    def lookup(self, name: str, field: str) -> T:
        """The entry called `name`, or an InputError naming `field` and the known names."""
        if name not in self:
            raise InputError(field, self.unknown(name))
        return self[name]

    def in_order(self) -> list[T]:
        """The entries by their `order` (registries of entries that have one), lowest first."""
        return sorted(self.values(), key=lambda entry: entry.order)  # type: ignore[attr-defined]
