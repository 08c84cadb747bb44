"""Camera rays: one per pixel centre, and where they cross an axis-aligned box."""

from __future__ import annotations

import torch
from torch import Tensor

from .camera import Camera


def camera_rays(camera: Camera) -> tuple[Tensor, Tensor]:
    """Origins and unit directions of every pixel centre, row-major: ([H*W, 3], [H*W, 3]) float32."""
    j, i = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                          torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    # OpenGL camera: +x right, +y up, looking down -z; image rows grow downwards.
    d_cam = torch.stack([(i + 0.5 - camera.cx) / camera.fx, -(j + 0.5 - camera.cy) / camera.fy,
                         -torch.ones_like(i)], -1).reshape(-1, 3)
    dirs = d_cam @ camera.c2w[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = camera.center.expand_as(dirs)
    return origins.float().contiguous(), dirs.float().contiguous()


def ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances [R] of rays through the box [lo, hi] (entry >= exit: a miss)."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t_lo, t_hi = (lo - origins) / safe, (hi - origins) / safe
    return torch.minimum(t_lo, t_hi).amax(-1), torch.maximum(t_lo, t_hi).amin(-1)


def pixels_in_box(camera: Camera, lo: Tensor, hi: Tensor) -> Tensor:
    """[H, W] bool: the pixels whose ray crosses the box [lo, hi] in front of the camera."""
    origins, dirs = camera_rays(camera)
    t_in, t_out = ray_box(origins.double(), dirs.double(), lo.double(), hi.double())
    return ((t_out > t_in) & (t_out > 0)).view(camera.height, camera.width)
