"""Where candidate poses go: the scene's centre, size and up direction, derived from the
training cameras when there are any, else from the model's splats, robust to floaters.

With cameras: the centre is the point the optical axes pass closest to
(`phd_core.scene.scene_bounds`), the radius the median camera distance to it, up the capture's
(`phd_core.scene.capture_up`: orthogonal to the cameras' horizontal image axes, refined on the
plane the capture stands on when the points, SfM points or opaque splat centres, show one), and
the intrinsics those of the first camera. With splats only: the centre is the per-axis median of
the opaque splats, the object radius the 90th percentile of their distances to it (a few far
floaters move neither), and the camera radius the distance at which a sphere of that radius
fills 80% of the default field of view; up is +z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from ...errors import InputError
from ...scene import Camera, capture_up, scene_bounds

DEFAULT_FOV_X = 0.6911112070083618     # the NeRF-synthetic field of view
DEFAULT_SIZE = 100


@dataclass
class SceneFrame:
    center: torch.Tensor                 # [3] float64
    radius: float                        # camera distance from the centre
    up: torch.Tensor                     # [3] unit
    elevation: float                     # median elevation of the training cameras (0.5 rad without)
    cameras: list[Camera]                # the training cameras ([] when unknown)
    template: Camera | None              # intrinsics to copy onto generated poses


def horizontal_axes(up: Sequence[float] | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit `up` and two unit axes spanning the plane normal to it."""
    up_t = torch.as_tensor(up, dtype=torch.float64).clone()
    if up_t.shape != (3,) or not torch.isfinite(up_t).all() or up_t.norm() < 1e-12:
        raise InputError("up", f"must be a non-zero 3-vector, got {up_t.tolist()}")
    up_t = up_t / up_t.norm()
    helper = torch.tensor([1.0, 0, 0], dtype=torch.float64)
    if abs(float(helper @ up_t)) > 0.9:
        helper = torch.tensor([0, 1.0, 0], dtype=torch.float64)
    ax = torch.linalg.cross(up_t, helper)
    ax = ax / ax.norm()
    return up_t, ax, torch.linalg.cross(up_t, ax)


def scene_frame(cameras: Sequence[Camera] | None = None, points: torch.Tensor | None = None,
                up: Sequence[float] | torch.Tensor | None = None) -> SceneFrame:
    """The frame candidate poses are placed in (see the module docstring); `up` given (the
    caller's, or one found earlier and stored) stands for `capture_up`'s."""
    cameras = list(cameras or [])
    if cameras:
        center, _ = scene_bounds(cameras)
        eyes = torch.stack([c.center for c in cameras])                            # [V, 3]
        up = capture_up(cameras, points).vector if up is None else horizontal_axes(up)[0]
        offsets = eyes - center
        radius = float(offsets.norm(dim=1).median())
        sines = (offsets @ up) / offsets.norm(dim=1).clamp_min(1e-12)
        elevation = float(torch.asin(sines.clamp(-1, 1)).median())
        return SceneFrame(center, max(radius, 1e-6), up, elevation, cameras, cameras[0])
    if points is None or len(points) == 0:
        raise InputError("cameras", "no training cameras and no splats to place candidate poses around: give "
                         "center and radius")
    pts = points.detach().to(torch.float64)
    center = pts.median(dim=0).values
    reach = float(torch.quantile((pts - center).norm(dim=1)[:200_000], 0.9))
    radius = max(reach, 1e-6) / math.sin(0.8 * DEFAULT_FOV_X / 2)
    return SceneFrame(center, radius, torch.tensor([0, 0, 1.0], dtype=torch.float64), 0.5, [], None)


def scene_points(renderer: object) -> torch.Tensor | None:
    """Positions of a splat model's opaque splats (opacity >= 0.5; all if none is), else None."""
    model = getattr(renderer, "model", None)
    means = getattr(model, "means", None)
    if not isinstance(means, torch.Tensor) or means.ndim != 2 or means.shape[1] != 3:
        return None
    logits = getattr(model, "opacity_logits", None)
    if isinstance(logits, torch.Tensor) and logits.shape == means.shape[:1]:
        opaque = torch.sigmoid(logits.detach()) >= 0.5
        if opaque.any():
            return means.detach()[opaque]
    return means.detach()
