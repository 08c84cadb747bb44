"""Where the scene is, from the cameras alone: two answers for two needs.

`scene_bounds` (3DGS): the point the optical axes pass closest to, and the radius around it
that every camera sees in full. `frustum_bounds` (NeRF): the box around every point that
all cameras see between near and far.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ..errors import InputError
from .camera import Camera

BOUNDS_PROBE = 64          # points per axis of the frustum-intersection probe


def scene_bounds(cameras: Sequence[Camera]) -> tuple[torch.Tensor, float]:
    """Centre [3] and half-extent of the region the cameras look at.

    The centre is the least-squares point closest to every optical axis; the half-extent
    is the largest radius around it that every camera sees in full.
    """
    eye = torch.stack([c.center for c in cameras])                      # [V, 3]
    axis = -torch.stack([c.c2w[:3, 2] for c in cameras])                # [V, 3] viewing directions
    proj = torch.eye(3, dtype=torch.float64) - axis[:, :, None] * axis[:, None, :]  # [V, 3, 3]
    if len(cameras) == 1 or torch.linalg.matrix_rank(proj.sum(0)) < 3:
        centre = eye[0] + axis[0] * 4.0
    else:
        centre = torch.linalg.solve(proj.sum(0), (proj @ eye[:, :, None]).sum(0)).squeeze(1)
    dist = (eye - centre).norm(dim=-1)
    half_fov = torch.tensor([min(math.atan(c.width / (2 * c.fx)), math.atan(c.height / (2 * c.fy)))
                             for c in cameras], dtype=torch.float64)
    extent = float((dist * torch.sin(half_fov)).min())
    return centre, extent


def frustum_bounds(cameras: list[Camera], near: float, far: float) -> list[list[float]]:
    """The box around every point that all cameras see between near and far.

    For the Blender scenes (cameras at radius 4, near 2, far 6) this is about
    [-1.45, 1.45]^3, the box the scenes are known to fit in.
    """
    centers = torch.stack([c.center for c in cameras])                      # [V, 3]
    lo, hi = centers.max(0).values - far, centers.min(0).values + far       # within `far` of every camera
    if not (hi > lo).all():
        raise InputError("bounds", "the training cameras share no common view volume: pass bounds explicitly")
    axis = [torch.linspace(float(lo[k]), float(hi[k]), BOUNDS_PROBE, dtype=torch.float64) for k in range(3)]
    points = torch.cartesian_prod(*axis)                                    # [P, 3]
    seen = torch.ones(points.shape[0], dtype=torch.bool)
    for camera in cameras:
        seen &= _in_frustum(camera, points, near, far)
    if not seen.any():
        raise InputError("bounds", "the training cameras share no common view volume: pass bounds explicitly")
    step = (hi - lo) / (BOUNDS_PROBE - 1)
    box_lo = torch.maximum(points[seen].min(0).values - step, lo)
    box_hi = torch.minimum(points[seen].max(0).values + step, hi)
    return [box_lo.tolist(), box_hi.tolist()]


def _in_frustum(camera: Camera, points: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """[P] bool: the point projects into the image at a distance in [near, far]."""
    uv, depth = camera.project(points)
    u, v = uv.unbind(-1)
    dist = (points - camera.center).norm(dim=1)
    return (depth > 0) & (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height) \
        & (dist >= near) & (dist <= far)
