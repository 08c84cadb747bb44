"""One error type for bad input, carrying the offending field, and the number checks
every layer shares.

Every layer (library, CLI, service) reports user mistakes through `InputError`, so the
CLI can print it and the service can turn it into a 422 with the field named.
"""

from __future__ import annotations

import math
import operator
import reprlib
from typing import Any, Iterable

SHOWN_CHARS = 120       # a value a message quotes: its repr, abbreviated (reprlib), cut to this many characters
MAX_NOTES = 16          # notes a model carries at most (they quote what its files said, which may be anything)
NOTE_CHARS = 1000       # ... each cut to this many characters


class InputError(ValueError):
    """Bad user input: `field` names what is wrong, `reason` says why."""

    def __init__(self, field: str, reason: str):
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason

    def __reduce__(self):
        # Pickle rebuilds an exception by calling its class with `args`, which this __init__
        # (and a subclass's) does not take: rebuild from the state instead, so an InputError
        # raised in another process (a Ray worker) arrives as itself.
        return _rebuild_error, (type(self), self.args, self.__dict__)


class TooLarge(InputError):
    """Input past a size limit (an archive that inflates past what may be read, a model past the
    memory budget): the service answers 413, not 422."""


class ModelNote(UserWarning):
    """What a model or capture loader decided that the user should know (the frame it chose,
    and how well it fits; photos it undistorted, and where it keeps them)."""


class ModelWarning(UserWarning):
    """A loaded model or capture that will probably not give what the user expects (its cameras
    miss its splats; LLFF poses beside a COLMAP model with lens distortion)."""


def cut(text: str, limit: int) -> str:
    """`text`, or its first `limit` - 1 characters and an ellipsis when it is longer."""
    return text if len(text) <= limit else text[:limit - 1] + "\u2026"


_SHOWN = reprlib.Repr()
_SHOWN.maxstring = _SHOWN.maxother = SHOWN_CHARS


def shown(value: Any) -> str:
    """`value` as a message quotes it: its repr with long strings, lists and deep nesting
    abbreviated, at most SHOWN_CHARS characters (a file's value may be anything)."""
    return cut(_SHOWN.repr(value), SHOWN_CHARS)


def bounded_notes(notes: Iterable[str]) -> list[str]:
    """The first MAX_NOTES of `notes`, each cut to NOTE_CHARS characters."""
    return [cut(note, NOTE_CHARS) for _, note in zip(range(MAX_NOTES), notes)]


def _rebuild_error(cls: type[InputError], args: tuple, state: dict) -> InputError:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


def check_int(value: Any, name: str, minimum: int | None = None, maximum: int | None = None) -> int:
    """`value` as an int (bools refused) within [minimum, maximum], else an InputError naming `name`."""
    if isinstance(value, bool):
        raise InputError(name, f"must be an integer, got {shown(value)}")
    try:
        value = operator.index(value)
    except TypeError:
        raise InputError(name, f"must be an integer, got {shown(value)}") from None
    _check_range(value, name, minimum, maximum)
    return value


def check_float(value: Any, name: str, minimum: float | None = None, maximum: float | None = None, *,
                open_min: bool = False, open_max: bool = False) -> float:
    """`value` as a finite float (bools refused) within [minimum, maximum], else an InputError;
    open_min / open_max exclude the bound itself ((0, 1]: minimum=0, maximum=1, open_min=True)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(name, f"must be a number, got {shown(value)}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(name, f"must be finite, got {value}")
    _check_range(value, name, minimum, maximum, open_min, open_max)
    return value


def check_bool(value: Any, name: str) -> bool:
    """`value` when it is True or False, else an InputError naming `name`."""
    if not isinstance(value, bool):
        raise InputError(name, f"must be true or false, got {shown(value)}")
    return value


NAMED_COLORS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5), "gray": (0.5, 0.5, 0.5)}


def check_color(value: Any, name: str) -> tuple[float, float, float]:
    """'white', 'black', 'grey' (or 'gray', 0.5) or three numbers in [0, 1] -> (r, g, b)."""
    if isinstance(value, str):
        if value.strip().lower() not in NAMED_COLORS:
            raise InputError(name, f"must be 'white', 'black', 'grey' or three numbers in [0, 1], got {shown(value)}")
        return NAMED_COLORS[value.strip().lower()]
    try:
        color = [float(c) for c in value]
    except (TypeError, ValueError):
        raise InputError(name, f"must be three numbers in [0, 1], got {shown(value)}") from None
    if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
        raise InputError(name, f"must be three numbers in [0, 1], got {shown(value)}")
    return color[0], color[1], color[2]


def _check_range(value: float, name: str, minimum: float | None, maximum: float | None,
                 open_min: bool = False, open_max: bool = False) -> None:
    low = minimum is not None and (value <= minimum if open_min else value < minimum)
    high = maximum is not None and (value >= maximum if open_max else value > maximum)
    if minimum is not None and maximum is not None and (low or high):
        raise InputError(name, f"must lie in {'(' if open_min else '['}{minimum}, {maximum}{')' if open_max else ']'}, "
                               f"got {value}")
    if low:
        raise InputError(name, f"must be {'above' if open_min else 'at least'} {minimum}, got {value}")
    if high:
        raise InputError(name, f"must be {'below' if open_max else 'at most'} {maximum}, got {value}")
