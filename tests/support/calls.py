"""Counting the calls a test expects a code path to make (or not to make)."""

from __future__ import annotations

from typing import Any


def count_calls(monkeypatch: Any, owner: object, name: str) -> dict[str, int]:
    """Replace `owner.name` (a module's function or an object's method) for the test with a
    wrapper that counts its calls in the returned {"calls": n}."""
    calls = {"calls": 0}
    original = getattr(owner, name)

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls["calls"] += 1
        return original(*args, **kwargs)
    monkeypatch.setattr(owner, name, counted)
    return calls
