"""Options several commands share: `--background`."""

from __future__ import annotations

import argparse
from typing import Any

from phd_core.errors import NAMED_COLORS, InputError, check_color


def add_background_arg(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--background", nargs="+", metavar="COLOUR", default=None,
                        help=f"{what}: a name ({', '.join(NAMED_COLORS)}) or three numbers R G B in [0, 1]")


def parse_background(values: list[str] | None) -> tuple[float, float, float] | None:
    """--background as (r, g, b), None when not given; a clear error naming the flag otherwise."""
    if values is None:
        return None
    if len(values) == 1:
        return check_color(values[0], "background")
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        raise InputError("background", f"expected a name or three numbers in [0, 1], got {' '.join(values)!r}") from None
    return check_color(numbers, "background")


def apply_background(renderer: Any, values: list[str] | None) -> None:
    """Render a splat model over --background, when given (a NeRF checkpoint refuses it)."""
    color = parse_background(values)
    if color is not None:
        from phd_core.renderers.gs3d import set_background

        set_background(renderer, color)
