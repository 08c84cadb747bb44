"""Candidate poses on a band of the upper hemisphere around the scene, looking at its centre."""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ...errors import InputError
from ...scene import Camera, look_at
from .frame import horizontal_axes


def hemisphere_cameras(count: int, *, center: Sequence[float] = (0, 0, 0), radius: float = 4.0,
                       min_elevation: float = 0.0, max_elevation: float = math.pi / 2,
                       width: int = 100, height: int = 100, fov_x: float = 0.6911112070083618,
                       up: Sequence[float] = (0, 0, 1)) -> list[Camera]:
    """`count` look-at poses spread evenly (Fibonacci spiral) over a band of the upper
    hemisphere around `center`: candidate poses for next-best-view ranking.

    Elevations are in radians above the plane normal to `up`; the full upper hemisphere
    is [0, pi/2]. An orbit is min_elevation == max_elevation.
    """
    if count < 1:
        raise InputError("count", f"must be at least 1, got {count}")
    if radius <= 0 or not math.isfinite(radius):
        raise InputError("radius", f"must be a positive finite number, got {radius}")
    if not -math.pi / 2 <= min_elevation <= max_elevation <= math.pi / 2:
        raise InputError("elevation", "need -pi/2 <= min_elevation <= max_elevation <= pi/2")
    up_t, ax, ay = horizontal_axes(up)      # two axes perpendicular to `up` span the horizontal plane
    golden = math.pi * (3.0 - math.sqrt(5.0))
    sin_lo, sin_hi = math.sin(min_elevation), math.sin(max_elevation)
    center_t = torch.tensor(center, dtype=torch.float64)
    cameras = []
    for i in range(count):
        # Uniform in sin(elevation) gives uniform area density on the sphere band.
        s = sin_lo + (sin_hi - sin_lo) * ((i + 0.5) / count)
        elevation = math.asin(min(1.0, max(-1.0, s)))
        azimuth = golden * i
        direction = (math.cos(elevation) * (math.cos(azimuth) * ax + math.sin(azimuth) * ay)
                     + math.sin(elevation) * up_t)
        eye = center_t + radius * direction
        cameras.append(look_at(eye.tolist(), center_t.tolist(), up_t.tolist(),
                               width=width, height=height, fov_x=fov_x))
    return cameras


def sphere_cameras(count: int, *, center: Sequence[float] = (0, 0, 0), radius: float = 4.0,
                   width: int = 100, height: int = 100, fov_x: float = 0.6911112070083618,
                   up: Sequence[float] = (0, 0, 1)) -> list[Camera]:
    """`count` look-at poses spread evenly over the whole sphere around `center`."""
    return hemisphere_cameras(count, center=center, radius=radius, min_elevation=-math.pi / 2,
                              max_elevation=math.pi / 2, width=width, height=height, fov_x=fov_x, up=up)
