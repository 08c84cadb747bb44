"""Jittered copies of the training poses: small moves around views the model already knows."""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ...errors import InputError, check_float, check_int
from ...scene import Camera, capture_up
from .frame import horizontal_axes


def jitter_cameras(count: int, *, cameras: Sequence[Camera], radius: float = 1.0, position: float = 0.05,
                   angle: float = 5.0, seed: int = 0, up: Sequence[float] | None = None) -> list[Camera]:
    """`count` copies of the training poses (cycling through them), each moved by a Gaussian
    offset of std `position * radius` and turned by a Gaussian pitch about its own right axis
    and a Gaussian yaw about `up` (by default the capture's: `phd_core.scene.capture_up`),
    each of std `angle` degrees. Neither turn rolls the camera: a copy is as level as the pose
    it copies. Intrinsics as the copied camera. Seeded."""
    count = check_int(count, "count", 1)
    position = check_float(position, "position", 0)
    angle = check_float(angle, "angle", 0, 180)
    radius = check_float(radius, "radius", 0)
    seed = check_int(seed, "seed", 0)
    if not cameras:
        raise InputError("cameras", "the jitter generator needs the training cameras")
    vertical = horizontal_axes(capture_up(cameras).vector if up is None else up)[0]    # [3] unit
    gen = torch.Generator().manual_seed(seed)
    out = []
    for k in range(count):
        source = cameras[k % len(cameras)]
        shift = torch.randn(3, generator=gen, dtype=torch.float64) * position * radius
        pitch, yaw = (torch.randn(2, generator=gen, dtype=torch.float64) * math.radians(angle)).tolist()
        c2w = source.c2w.clone()
        c2w[:3, :3] = _axis_angle(vertical, yaw) @ _axis_angle(c2w[:3, 0], pitch) @ c2w[:3, :3]
        c2w[:3, 3] += shift
        out.append(Camera(c2w, source.fx, source.fy, source.cx, source.cy, source.width, source.height,
                          source.max_size))
    return out


def _axis_angle(axis: torch.Tensor, theta: float) -> torch.Tensor:
    """Rodrigues' rotation [3, 3] of `theta` radians about the unit `axis`."""
    x, y, z = axis.tolist()
    k = torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(theta) * k + (1 - math.cos(theta)) * (k @ k)
