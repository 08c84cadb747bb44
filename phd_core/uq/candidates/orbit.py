"""Orbit rings: look-at poses evenly spaced in azimuth on one or more horizontal rings."""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ...errors import InputError, check_float, check_int
from ...scene import Camera, look_at
from .frame import horizontal_axes


def orbit_cameras(count: int, *, center: Sequence[float] = (0, 0, 0), radius: float = 4.0,
                  up: Sequence[float] = (0, 0, 1), elevation: float = 0.5, rings: int = 1,
                  spread: float = 0.35, width: int = 100, height: int = 100,
                  fov_x: float = 0.6911112070083618) -> list[Camera]:
    """`count` poses on `rings` rings around `center`, looking at it.

    One ring lies at `elevation` (radians above the plane normal to `up`); several rings
    spread evenly over [elevation - spread, elevation + spread], each ring's azimuths
    offset by half a step from the ring below so that no two rings line up.
    """
    count = check_int(count, "count", 1)
    rings = check_int(rings, "rings", 1, count)
    radius = check_float(radius, "radius", 1e-9)
    elevation = check_float(elevation, "elevation", -math.pi / 2, math.pi / 2)
    spread = check_float(spread, "spread", 0, math.pi / 2)
    center_t = torch.tensor(center, dtype=torch.float64)
    up_t, ax, ay = horizontal_axes(up)
    cameras = []
    for ring in range(rings):
        size = count // rings + (ring < count % rings)          # the first rings take the remainder
        level = elevation if rings == 1 else elevation - spread + 2 * spread * ring / (rings - 1)
        level = min(max(level, -math.pi / 2 + 1e-3), math.pi / 2 - 1e-3)
        for k in range(size):
            azimuth = 2 * math.pi * (k + 0.5 * (ring % 2)) / size
            direction = math.cos(level) * (math.cos(azimuth) * ax + math.sin(azimuth) * ay) + math.sin(level) * up_t
            cameras.append(look_at((center_t + radius * direction).tolist(), center_t.tolist(), up_t.tolist(),
                                   width=width, height=height, fov_x=fov_x))
    if not cameras:
        raise InputError("count", "no poses generated")
    return cameras
