"""Volume rendering: samples along camera rays clipped to the scene box, log-space compositing."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...scene.rays import camera_rays, ray_box  # noqa: F401  (re-exported by renderers.nerf)
from .config import CHUNK_ELEMENTS
from .field import RadianceField

# --------------------------------------------------------------------------- volume rendering

def segment_weights(tau: Tensor) -> tuple[Tensor, Tensor]:
    """Compositing weights of segments with optical depths tau [..., S] (transmittance in front,
    in log space, times alpha = 1 - exp(-tau)), and the optical depth up to each segment's end."""
    total = tau.cumsum(-1)
    return torch.exp(tau - total) * -torch.expm1(-tau), total      # tau - total: -(sum over the previous)


def composite(sigma: Tensor, rgb: Tensor, delta: Tensor, t: Tensor, background: Tensor
              ) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha compositing of S segments per ray.

    sigma [..., S], rgb [..., S, 3], segment lengths delta and sample distances t [..., S]
    -> colour on `background` [..., 3], accumulated alpha [...], alpha-weighted depth [...]
    (divide by alpha for the mean depth). alpha_i = 1 - exp(-sigma_i delta_i); the
    transmittance before segment i is exp(-sum_{j<i} sigma_j delta_j), summed in log space.
    """
    weights, total = segment_weights(sigma * delta)         # [..., S]
    acc = weights.sum(-1)
    color = (weights[..., None] * rgb).sum(-2) + torch.exp(-total[..., -1:]) * background
    return color, acc, (weights * t).sum(-1)


@dataclass
class RayOutput:
    rgb: Tensor      # [n, R, 3] composited on the background
    alpha: Tensor    # [n, R] accumulated opacity
    depth: Tensor    # [n, R] alpha-weighted distance along the ray
    sigma: Tensor | None  # [n, R, S] density of every sample (0 where skipped), if asked for
    samples: int     # samples the network evaluated
    full_density: Tensor | None = None  # [K] the full model's density at the K evaluated samples, if asked for


def ray_samples(model: RadianceField, origins: Tensor, dirs: Tensor, *, generator: torch.Generator | None = None,
                use_grid: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sample rays [R, 3] in [near, far] clipped to the scene box, `samples` bins per ray.

    Returns distances t [R, S] (bin centres, or one uniform point per bin with a
    generator), bin lengths delta [R, S], points [R, S, 3] and valid [R, S]: the sample is
    on a ray that meets the box and (with use_grid) lies in an occupied cell.
    """
    c, grid = model.config, model.grid
    t_in, t_out = ray_box(origins, dirs, grid.lo, grid.lo + grid.size)
    t0, t1 = t_in.clamp_min(c.near), t_out.clamp_max(c.far)
    hit = t1 > t0                                                         # [R]
    span = torch.where(hit, t1 - t0, torch.zeros_like(t0))
    delta = (span / c.samples)[:, None].expand(-1, c.samples)             # [R, S]
    offset = (torch.rand(delta.shape, generator=generator) if generator is not None
              else torch.full(delta.shape, 0.5))
    t = t0[:, None] + (torch.arange(c.samples) + offset) * delta          # [R, S]
    points = origins[:, None] + t[..., None] * dirs[:, None]              # [R, S, 3]
    valid = hit[:, None].expand_as(t)
    if use_grid:
        valid = valid & grid.lookup(points.reshape(-1, 3)).view(t.shape)
    return t, delta, points, valid


def render_rays(model: RadianceField, origins: Tensor, dirs: Tensor, *, keep: Tensor | None = None,
                rescale: bool = False, use_grid: bool = True, generator: torch.Generator | None = None,
                weights: Tensor | None = None, dir_weights: Tensor | None = None,
                background: Tensor | None = None, with_sigma: bool = False,
                full_density: bool = False) -> RayOutput:
    """Render rays [R, 3] once per keep-mask [n, W] (None: n = 1, the full model).

    Sampling, the grid lookup, the encoding and the first layer run once; the rest of the
    network runs over the masks in groups of at most CHUNK_ELEMENTS values per tensor.
    Deterministic unless a `generator` is given (stratified sampling, for training);
    `use_grid=False` evaluates every sample in the box. `weights`/`dir_weights` are the
    FreeNeRF band weights of the position and direction encodings. `with_sigma` also
    returns every sample's density (training's occlusion penalty needs it); `full_density`
    the full model's density at the evaluated samples, from the same first layer (the trunk
    once more, no colour branch: what a visibility pass needs beside the masked renders).
    """
    c = model.config
    bg = torch.tensor(c.background) if background is None else background
    t, delta, points, valid = ray_samples(model, origins, dirs, generator=generator, use_grid=use_grid)
    flat = valid.flatten().nonzero()[:, 0]                                # [K] evaluated samples
    stem = model.stem(points.reshape(-1, 3)[flat], dirs[flat // c.samples], weights, dir_weights)
    # Per mask: [K, width] activations and the dense [R * S, 3] colours of the compositing.
    per_mask = max(1, flat.numel() * c.width, t.numel() * 3)
    masks = [None] if keep is None else keep.split(max(1, CHUNK_ELEMENTS // per_mask))
    colors, alphas, depths, sigmas = [], [], [], []
    for sub in masks:
        sigma_k, rgb_k = model.heads(stem, sub, rescale)                  # [n, K], [n, K, 3]
        n = sigma_k.shape[0]
        sigma = sigma_k.new_zeros(n, t.numel()).index_copy(1, flat, sigma_k).view(n, *t.shape)
        rgb = rgb_k.new_zeros(n, t.numel(), 3).index_copy(1, flat, rgb_k).view(n, *t.shape, 3)
        color, acc, depth = composite(sigma, rgb, delta, t, bg)
        colors.append(color)
        alphas.append(acc)
        depths.append(depth)
        if with_sigma:
            sigmas.append(sigma)
    full = model.units_density(stem[0], stem[1]) if full_density else None       # [K]
    return RayOutput(torch.cat(colors), torch.cat(alphas), torch.cat(depths),
                     torch.cat(sigmas) if with_sigma else None, int(flat.numel()), full)
