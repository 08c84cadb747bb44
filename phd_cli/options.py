"""Options several commands share: `--background`, `--other-capture`, and the help of a model argument."""

from __future__ import annotations

import argparse
from typing import Any

from phd_core.errors import NAMED_COLORS, InputError, check_color
from phd_core.renderers import family_titles, set_background


def model_help() -> str:
    """What a model argument takes: a file of any registered family, or any registered
    trainer's output folder (its layout, as each trainer leaves it)."""
    from phd_core.renderers.outputs import OUTPUTS

    return (f"trained model: {family_titles('or')}; or a trainer's output folder as is: "
            f"{'; '.join(f.title for f in OUTPUTS.in_order())} (its own cameras and split; poses in the "
            "capture's frame, docs/formats.md)")


def add_background_arg(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--background", nargs="+", metavar="COLOUR", default=None,
                        help=f"{what}: a name ({', '.join(NAMED_COLORS)}) or three numbers R G B in [0, 1]")


def add_other_capture_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--other-capture", action="store_true",
                        help="go on with a capture that is not the one the model was trained on (its cameras see "
                             "almost none of the model, it holds none of the model's training views, or its photos "
                             "fit the model far worse than the training views did: docs/formats.md): a note says "
                             "so instead of the error")


def parse_background(values: list[str] | None) -> tuple[float, float, float] | None:
    """--background as (r, g, b), None when not given; a clear error naming the flag otherwise."""
    if values is None:
        return None
    if len(values) == 1:
        return check_color(values[0], "background")
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        raise InputError("background",
                         f"expected a name or three numbers in [0, 1], got {' '.join(values)!r}") from None
    return check_color(numbers, "background")


def apply_background(renderer: Any, values: list[str] | None) -> None:
    """Render the model over --background, when given (a model that carries its own refuses it)."""
    color = parse_background(values)
    if color is not None:
        set_background(renderer, color)
