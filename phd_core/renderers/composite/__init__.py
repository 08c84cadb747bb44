"""Compositing backends: stage 4 of splat rendering, the only stage run once per keep-mask.

A backend is a function (fragments, values [E, C], keep [N, E] bool or None, num_pixels)
-> (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]).
`COMPOSITORS` maps a name to one; `reference` (pure torch) is today's only entry, and a
fused kernel will be one module plus one `COMPOSITORS.add` beside it, checked against it.
"""

from __future__ import annotations

from typing import Callable

import torch

from ...registry import Registry
from ..splats import Fragments
from .reference import composite

Compositor = Callable[[Fragments, torch.Tensor, "torch.Tensor | None", int], tuple[torch.Tensor, torch.Tensor]]

COMPOSITORS: Registry[Compositor] = Registry("compositor")
COMPOSITORS.add("reference", composite)
DEFAULT_COMPOSITOR = "reference"

__all__ = ["COMPOSITORS", "DEFAULT_COMPOSITOR", "Compositor"]
