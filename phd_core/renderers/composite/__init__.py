"""Compositing backends: stage 4 of splat rendering, the only stage run once per keep-mask.

A backend is a function (fragments, values [E, C], keep [N, U] bool or None, unit [E] int64,
num_pixels) -> (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]):
entry e is dropped by mask n when not keep[n, unit[e]] (U dropout units, e.g. splats).
`COMPOSITORS` maps a name to one:

    reference   pure torch, differentiable: the tested twin of the others
    fused       one compiled pass (numba, all cores) for N masks at once, and a compiled
                backward pass (training)

`DEFAULT_COMPOSITOR` is what renders and training use unless a compositor is named.
"""

from __future__ import annotations

from typing import Callable

import torch

from ...registry import Registry
from ..splats import Fragments
from . import fused, reference

Compositor = Callable[[Fragments, torch.Tensor, "torch.Tensor | None", torch.Tensor, int],
                      tuple[torch.Tensor, torch.Tensor]]

COMPOSITORS: Registry[Compositor] = Registry("compositor")
COMPOSITORS.add("reference", reference.composite)
COMPOSITORS.add("fused", fused.composite)
DEFAULT_COMPOSITOR = "fused"


def pick_compositor(compositor: str | None) -> Compositor:
    """The backend named, or the default for None."""
    return COMPOSITORS.lookup(compositor or DEFAULT_COMPOSITOR, "compositor")


__all__ = ["COMPOSITORS", "DEFAULT_COMPOSITOR", "Compositor", "pick_compositor"]
