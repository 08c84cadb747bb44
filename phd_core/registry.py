"""A registry: name -> entry, each name registered once.

Every growth point (model families, next-best-view strategies) is one of these, and the CLI
and the service read their allowed names from it, so a new entry needs no other edit.
"""

from __future__ import annotations

from typing import TypeVar

from .errors import InputError

T = TypeVar("T")


class Registry(dict[str, T]):
    def __init__(self, what: str):
        super().__init__()
        self.what = what            # for messages: "strategy", "model family"

    def add(self, name: str, entry: T) -> T:
        """Register `entry` under `name`; a name is registered once."""
        if name in self:
            raise ValueError(f"{self.what} {name!r} is already registered")
        self[name] = entry
        return entry

    def unknown(self, name: str) -> str:
        """Why `name` is not accepted: the message names the known entries."""
        return f"unknown {self.what} {name!r}; known: {', '.join(sorted(self))}"

    def lookup(self, name: str, field: str) -> T:
        """The entry called `name`, or an InputError naming `field` and the known names."""
        if name not in self:
            raise InputError(field, self.unknown(name))
        return self[name]
