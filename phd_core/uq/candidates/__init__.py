"""Candidate-pose generators: where a next-best view may be taken from.

`GENERATORS` maps a name to a `Generator`; adding one is one module plus one `register`
call. Today: `hemisphere` (look-at poses spread evenly over a band of the upper
hemisphere).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ...registry import Registry
from ...scene import Camera
from .hemisphere import hemisphere_cameras


@dataclass(frozen=True)
class Generator:
    name: str
    summary: str                                  # one line for --help, the API schema and the docs
    generate: Callable[..., list[Camera]]         # (count, **options) -> count candidate poses


GENERATORS: Registry[Generator] = Registry("candidate generator")


def register(generator: Generator) -> Generator:
    """Add a generator under its name (a name is registered once)."""
    return GENERATORS.add(generator.name, generator)


register(Generator("hemisphere", "look-at poses spread evenly (Fibonacci spiral) over a band of the upper "
                   "hemisphere", hemisphere_cameras))


def get_generator(name: str) -> Generator:
    """The registered generator called `name`, or an InputError listing the known names."""
    return GENERATORS.lookup(name, "generator")


__all__ = ["GENERATORS", "Generator", "get_generator", "hemisphere_cameras", "register"]
