"""A forward-facing spiral for LLFF-like captures: poses on an elliptical spiral around the
mean training pose, all looking at one focus point in front of it."""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ...errors import InputError, check_float, check_int
from ...scene import Camera, capture_up
from .frame import horizontal_axes


def spiral_cameras(count: int, *, cameras: Sequence[Camera], focus: float | None = None,
                   points: torch.Tensor | None = None, rotations: float = 2.0, scale: float = 1.0,
                   up: Sequence[float] | None = None) -> list[Camera]:
    """`count` poses on a spiral in front of the training cameras, with their intrinsics.

    The spiral is centred on the mean camera pose, made level: its viewing axis is the
    cameras' mean, its right axis horizontal (orthogonal to `up`, by default the capture's:
    `phd_core.scene.capture_up`). Its radii along that pose's right, up and forward axes are
    the 90th percentile of the cameras' offsets from it (times `scale`), so it sweeps the
    region the capture covered. Every pose looks at the focus point `focus` in front of the
    mean pose, with a horizontal right axis: by default the median depth of `points` (the
    SfM points or splats) in front of it, else the distance to where the optical axes meet.
    """
    count = check_int(count, "count", 1)
    rotations = check_float(rotations, "rotations", 0)
    scale = check_float(scale, "scale", 0)
    if not cameras:
        raise InputError("cameras", "the spiral generator needs the training cameras")
    vertical = horizontal_axes(capture_up(cameras).vector if up is None else up)[0]    # [3] unit
    eyes = torch.stack([c.center for c in cameras])                               # [V, 3]
    mean_eye = eyes.mean(0)
    back = _unit(torch.stack([c.c2w[:3, 2] for c in cameras]).mean(0), "cameras")     # OpenGL +z: backwards
    right = _unit(torch.linalg.cross(vertical, back), "cameras")
    basis = torch.stack([right, torch.linalg.cross(back, right), back], dim=1)    # [3, 3] columns
    local = (eyes - mean_eye) @ basis                                             # [V, 3]
    radii = torch.quantile(local.abs(), 0.9, dim=0) * scale                       # [3]
    if focus is None:
        focus = _focus_depth(cameras, mean_eye, back, points)
    focus = check_float(focus, "focus", 1e-9)
    target = mean_eye - focus * back
    template = cameras[0]
    out = []
    for k in range(count):
        t = 2 * math.pi * rotations * k / count
        offset = torch.tensor([math.cos(t), -math.sin(t), -math.sin(0.5 * t)], dtype=torch.float64) * radii
        eye = mean_eye + basis @ offset
        z = _unit(eye - target, "focus")                                          # backwards, as OpenGL
        x = _unit(torch.linalg.cross(vertical, z), "focus")
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, torch.linalg.cross(z, x), z, eye
        out.append(Camera(c2w, template.fx, template.fy, template.cx, template.cy, template.width, template.height,
                          template.max_size))
    return out


def _focus_depth(cameras: Sequence[Camera], mean_eye: torch.Tensor, back: torch.Tensor,
                 points: torch.Tensor | None) -> float:
    if points is not None and len(points):
        depth = (mean_eye - points.to(torch.float64)) @ back                      # [P] along the viewing axis
        depth = depth[depth > 0]
        if len(depth):
            return float(depth.median())
    from ...scene import scene_bounds

    centre, _ = scene_bounds(cameras)
    distance = float((mean_eye - centre) @ back)
    if not distance > 0:
        raise InputError("focus", "cannot tell how far in front of the cameras the scene lies: give focus")
    return distance


def _unit(v: torch.Tensor, field: str) -> torch.Tensor:
    if v.norm() < 1e-9:
        raise InputError(field, "the cameras' axes cancel out: the capture is not forward-facing")
    return v / v.norm()
