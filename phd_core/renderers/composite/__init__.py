"""Compositing backends: stage 4 of splat rendering, the only stage run once per keep-mask.

A backend is a function (fragments, values [E, C], keep [N, U] bool or None, unit [E] int64,
num_pixels) -> (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]):
entry e is dropped by mask n when not keep[n, unit[e]] (U dropout units, e.g. splats).
`COMPOSITORS` holds each as a `Compositor`, which is called like the function it names:

    reference   pure torch, differentiable: the tested twin of the others
    fused       one compiled pass (numba, all cores) for N masks at once, and a compiled
                backward pass (training)

`DEFAULT_COMPOSITOR` is what renders and training use unless a compositor is named.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from ...registry import Registry
from ..splats.maths import Fragments
from . import fused, reference


@dataclass(frozen=True)
class Compositor:
    """A compositing backend under its name; called as its function."""

    name: str
    composite: Callable[[Fragments, torch.Tensor, "torch.Tensor | None", torch.Tensor, int],
                        tuple[torch.Tensor, torch.Tensor]]

    def __call__(self, frags: Fragments, values: torch.Tensor, keep: torch.Tensor | None, unit: torch.Tensor,
                 num_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.composite(frags, values, keep, unit, num_pixels)


COMPOSITORS: Registry[Compositor] = Registry("compositor")
COMPOSITORS.register(Compositor("reference", reference.composite))
COMPOSITORS.register(Compositor("fused", fused.composite))
DEFAULT_COMPOSITOR = "fused"


def pick_compositor(compositor: str | None) -> Compositor:
    """The backend named, or the default for None."""
    return COMPOSITORS.lookup(compositor or DEFAULT_COMPOSITOR, "compositor")


__all__ = ["COMPOSITORS", "DEFAULT_COMPOSITOR", "Compositor", "pick_compositor"]
