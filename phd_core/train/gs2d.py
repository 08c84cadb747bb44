"""Fit a 2D Gaussian Splatting model (surfels) with the splat loop (`phd_core.train.splats`).

The loop, schedule, density control and sidecar are the 3DGS ones; a `Recipe` swaps in the
surfel model and rasteriser, random initial orientations, and the two 2DGS regularisers
(Huang et al. 2024), on by default (weights `SurfelOptions`: 1 and 0.05; 0 turns one off: on
lego at 16 views they raised the test PSNR by 0.14-0.25 dB, docs/gs2d.md):

- depth distortion: per pixel sum_ij w_i w_j (d_i - d_j)^2 / 2 over the compositing
  weights w and intersection depths d, divided by the squared scene extent so the weight
  does not depend on the scene's units. It pulls each ray's surfels together. (The paper
  uses |d_i - d_j| on NDC depth; the squared form needs only per-pixel sums, so it
  runs through any compositing backend.) From 10% of the run.
- normal consistency: per pixel sum_i w_i (1 - n_i . N), with n_i the surfels' normals
  and N the normal of the rendered depth map (finite differences of the back-projected
  expected depth). It aligns surfels with the surface they form. From 25% of the run.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any, Sequence, cast

import torch

from ..renderers.gs2d import SurfelModel, SurfelOutput, SurfelRenderer, rasterize_surfels
from ..renderers.gs2d.family import SurfelOptions
from ..scene import Camera
from .splats import Recipe, train_splats

DISTORTION_FROM = 0.1   # fractions of the run before each regulariser starts
NORMAL_FROM = 0.25


def depth_normals(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Normals [H-2, W-2, 3] of the surface a depth map [H, W] describes, camera frame
    (OpenCV axes), facing the camera: central differences of the back-projected pixels."""
    h, w = depth.shape
    xs = (torch.arange(w, dtype=depth.dtype) + 0.5 - camera.cx) / camera.fx
    ys = (torch.arange(h, dtype=depth.dtype) + 0.5 - camera.cy) / camera.fy
    points = torch.stack([xs[None, :] * depth, ys[:, None] * depth, depth], dim=-1)   # [H, W, 3]
    along_x = points[1:-1, 2:] - points[1:-1, :-2]
    along_y = points[2:, 1:-1] - points[:-2, 1:-1]
    normal = torch.linalg.cross(along_y, along_x)      # towards the camera for a visible surface
    return normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def regulariser(out: SurfelOutput, camera: Camera, fraction: float, extent: float, *,
                distortion_weight: float, normal_weight: float) -> torch.Tensor:
    """The weighted 2DGS regularisers of one training render (N = 1)."""
    loss = out.rgb.new_zeros(())
    # a positive weight turns the recipe's geometry render on, which sets distortion and normal
    if distortion_weight > 0 and fraction >= DISTORTION_FROM:
        assert out.distortion is not None
        loss = loss + distortion_weight * out.distortion[0].mean() / (extent * extent)
    if normal_weight > 0 and fraction >= NORMAL_FROM:
        assert out.normal is not None
        alpha = out.alpha[0]
        surface = depth_normals(out.depth[0] / alpha.clamp_min(1e-6), camera)        # [H-2, W-2, 3]
        rendered = out.normal[0][1:-1, 1:-1]                                          # sum_i w_i n_i
        loss = loss + normal_weight * (alpha[1:-1, 1:-1] - (rendered * surface).sum(-1)).mean()
    return loss


def recipe(depth_distortion: float = SurfelOptions.depth_distortion,
           normal_consistency: float = SurfelOptions.normal_consistency) -> Recipe:
    """The 2DGS recipe for the shared loop; regularisers on for positive weights."""
    weights = SurfelOptions(depth_distortion, normal_consistency)
    regularise = weights.depth_distortion > 0 or weights.normal_consistency > 0
    return Recipe("2dgs", SurfelModel, SurfelRenderer, partial(rasterize_surfels, geometry=regularise),
                  partial(regulariser, distortion_weight=weights.depth_distortion,
                          normal_weight=weights.normal_consistency) if regularise else None, random_rotations=True)


def train_surfels(data: str | Path, *, views: int | Sequence[int] = 16, downscale: float = 2,
                  iterations: int | None = None, seed: int = 0, out: str | Path, progress: bool = True,
                  depth_distortion: float = SurfelOptions.depth_distortion,
                  normal_consistency: float = SurfelOptions.normal_consistency, **overrides: Any) -> SurfelRenderer:
    """Train 2DGS on a split of a capture (`split`, default train); writes `out` in the 2DGS
    reference PLY layout plus the sidecar `<stem>.json` (`phd_core.train.splats.train_splats`,
    whose keywords `split`, `init`, `on_step` and TrainConfig fields `overrides` are)."""
    renderer = train_splats(data, recipe(depth_distortion, normal_consistency), views=views, downscale=downscale,
                            iterations=iterations, seed=seed, out=out, progress=progress, **overrides)
    return cast(SurfelRenderer, renderer)               # what the 2DGS recipe builds
