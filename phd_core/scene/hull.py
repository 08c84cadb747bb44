"""The visual hull: what no training view sees as pure background.

A view carves a point when the pixels the point can cover lie inside the image and none
of them is foreground (alpha above a threshold). A point covers the one pixel it
projects into; a ball of radius r around it (a grid cell) covers the square of pixels
around its projection wide enough to hold the ball's image, plus one pixel on each side.
Trainers seed their models from it: 3DGS draws its first splats inside it, NeRF starts
its occupancy grid as it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .camera import Camera


@dataclass
class Footprint:
    """The pixel block [v0, v1) x [u0, u1) each of P points covers in one view."""

    u0: Tensor          # [P] long, clamped to the image
    v0: Tensor          # [P] long
    u1: Tensor          # [P] long, exclusive
    v1: Tensor          # [P] long, exclusive
    inside: Tensor      # [P] bool: in front of the camera and the whole block lies in the image


def footprint(camera: Camera, points: Tensor, radius: float = 0.0) -> Footprint:
    """The pixels that points [P, 3] (radius 0), or balls of `radius` around them, cover."""
    uv, depth = camera.project(points, min_depth=max(radius, 1e-6))
    u, v = uv.unbind(-1)
    if radius > 0:
        z = depth.clamp_min(radius)
        reach = radius * max(camera.fx, camera.fy) / (z - radius).clamp_min(1e-6) + 1
    else:
        reach = torch.zeros_like(u)
    u0, u1 = (u - reach).floor(), (u + reach).floor() + 1
    v0, v1 = (v - reach).floor(), (v + reach).floor() + 1
    inside = (depth > radius) & (u0 >= 0) & (v0 >= 0) & (u1 <= camera.width) & (v1 <= camera.height)
    return Footprint(u0.clamp(0, camera.width - 1).long(), v0.clamp(0, camera.height - 1).long(),
                     u1.clamp(0, camera.width).long(), v1.clamp(0, camera.height).long(), inside)


def visual_hull(points: Tensor, cameras: Sequence[Camera], alphas: Sequence[Tensor], *, radius: float = 0.0,
                threshold: float = 0.0) -> Tensor:
    """[P] bool: the points [P, 3] (or balls of `radius` around them) that no view carves.

    alphas: one mask [H_v, W_v] per camera, at its size; a pixel is foreground where alpha > threshold.
    The foreground count of each block comes from an integral image, so the test is exact.
    """
    inside = torch.ones(points.shape[0], dtype=torch.bool)
    for camera, alpha in zip(cameras, alphas):
        block = footprint(camera, points, radius)
        counts = F.pad((alpha > threshold).double().cumsum(0).cumsum(1), (1, 0, 1, 0))   # [H+1, W+1]
        foreground = (counts[block.v1, block.u1] - counts[block.v0, block.u1]
                      - counts[block.v1, block.u0] + counts[block.v0, block.u0])
        inside &= ~(block.inside & (foreground == 0))
    return inside
