"""A splat model as the points a viewer draws.

Millions of splats do not belong in a browser: `scene_points` keeps at most `cap` of them,
drawn without replacement with probability proportional to each splat's importance
(opacity times its footprint, sigma squared), so the solid surface survives and faint or
tiny splats thin out first. The draw is seeded: the same model and cap give the same splats,
so values computed per splat elsewhere (`phd_core.uq.explain`) can be sent for them alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import InputError
from .protocol import Renderer
from .splats.model import GaussianModel

DEFAULT_POINT_CAP = 200_000


@dataclass
class ScenePoints:
    """`ids.numel()` of the model's `total` splats, each as a point with a colour and a size."""

    total: int              # splats in the model
    ids: Tensor             # [P] long, ascending: which splats these are
    positions: Tensor       # [P, 3] float32 centres
    colours: Tensor         # [P, 4] uint8 RGB (the view-independent colour) and opacity
    sigma: Tensor           # [P] float32 the splat's size: the geometric mean of its scales (one std)


def splat_model(renderer: Renderer) -> GaussianModel:
    """The splats behind a renderer, or an InputError for a family without splats."""
    model = getattr(renderer, "model", None)
    if not isinstance(model, GaussianModel):
        raise InputError("model", f"a {renderer.kind} model has no splats to draw as points")
    return model


def importance(model: GaussianModel) -> Tensor:
    """[G] float64: opacity times sigma squared (what a splat adds to the images it is in)."""
    sigma2 = (2.0 * model.log_scales.double().mean(dim=1)).clamp(-60.0, 60.0).exp()
    return torch.sigmoid(model.opacity_logits.double()) * sigma2


def point_subset(weights: Tensor, cap: int, seed: int = 0) -> Tensor:
    """[min(cap, W)] long ascending: indices drawn without replacement with probability
    proportional to weights [W] (Efraimidis-Spirakis keys log(u) / w, the largest kept)."""
    if cap < 1:
        raise InputError("cap", f"must be at least 1, got {cap}")
    count = len(weights)
    if count <= cap:
        return torch.arange(count)
    u = torch.rand(count, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    keys = u.clamp_min(1e-300).log() / weights.double().clamp_min(1e-300)
    return keys.topk(cap).indices.sort().values


def scene_points(renderer: Renderer, cap: int = DEFAULT_POINT_CAP, seed: int = 0) -> ScenePoints:
    """At most `cap` of the model's splats as points (module docstring)."""
    model = splat_model(renderer)
    ids = point_subset(importance(model), cap, seed)
    rgb = model.base_colours()[ids]                                           # [P, 3] float64
    opacity = torch.sigmoid(model.opacity_logits.double()[ids])[:, None]     # [P, 1]
    colours = (torch.cat([rgb, opacity], dim=1) * 255.0).round().clamp(0, 255).to(torch.uint8)
    sigma = model.log_scales.double()[ids].mean(dim=1).clamp(-60.0, 60.0).exp().float()
    return ScenePoints(total=model.num_splats, ids=ids, positions=model.means.detach()[ids].float().contiguous(),
                       colours=colours.contiguous(), sigma=sigma.contiguous())
