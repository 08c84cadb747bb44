"""Compositing backends: stage 4 of splat rendering, the only stage run once per keep-mask.

A backend is a function (fragments, values [E, C], keep [N, U] bool or None, unit [E] int64,
num_pixels) -> (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]):
entry e is dropped by mask n when not keep[n, unit[e]] (U dropout units, e.g. splats).
`COMPOSITORS` maps a name to one:

    reference   pure torch, differentiable: training, and the tested twin of the others
    fused       one compiled pass (numba, all cores) for N masks at once; no gradients

`DEFAULT_COMPOSITOR` is what renders without gradients use; training uses `reference`.
"""

from __future__ import annotations

from typing import Callable, Sequence

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
DIFFERENTIABLE_COMPOSITOR = "reference"



def pick_compositor(compositor: str | None, tensors: Sequence[torch.Tensor]) -> Compositor:
    """The backend named, or for None: the differentiable one when any of the model's
    `tensors` needs a gradient here (training), else the default."""
    if compositor is None:
        needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
        compositor = DIFFERENTIABLE_COMPOSITOR if needs_grad else DEFAULT_COMPOSITOR
    return COMPOSITORS.lookup(compositor, "compositor")


__all__ = ["COMPOSITORS", "DEFAULT_COMPOSITOR", "DIFFERENTIABLE_COMPOSITOR", "Compositor", "pick_compositor"]
