"""Generated captures whose up is known, for the upright frame (`phd_core.scene.capture_up`):
everything is turned by TILT first, so the true up (UP) is no coordinate axis. `one_side` is
the capture the old rule (the cameras' mean up) gets wrong: hand-held photos looking down at an
object from one side; `column` an upright object whose top is red and bottom blue."""

from __future__ import annotations

import math

import torch

from phd_core.renderers.gs3d import GaussianModel
from phd_core.renderers.splats import SH_C0
from phd_core.scene import Camera, look_at


def turn(axis: tuple[float, float, float], degrees: float) -> torch.Tensor:
    """Rodrigues' rotation [3, 3] float64 about `axis` by `degrees`."""
    k = torch.tensor(axis, dtype=torch.float64)
    x, y, z = (k / k.norm()).tolist()
    cross = torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64)
    angle = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


TILT = turn((1.0, 2.0, 0.5), 35.0)                   # the world the captures are taken in
UP = TILT @ torch.tensor([0, 0, 1.0], dtype=torch.float64)


def photo(eye, target, roll: float = 0.0, up=(0.0, 0.0, 1.0), size: tuple[int, int] = (48, 36)) -> Camera:
    """A look-at camera (level: right axis horizontal) rolled by `roll` degrees about its
    viewing axis, then turned into the TILT world."""
    camera = look_at(eye, target, up, width=size[0], height=size[1], fov_x=0.8)
    c2w = camera.c2w.clone()
    c2w[:3, :3] = TILT @ turn(tuple(c2w[:3, 2].tolist()), roll) @ c2w[:3, :3]
    c2w[:3, 3] = TILT @ c2w[:3, 3]
    return Camera(c2w, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)


def one_side(count: int = 30, *, rolls: list[float] | None = None, seed: int = 0,
             size: tuple[int, int] = (48, 36)) -> list[Camera]:
    """Hand-held photos of an object at the origin from one side: headings within +-50 degrees,
    looking down 25 to 55 degrees from 3 units away, rolled by `rolls` degrees on top of 2
    degrees rms of hand shake."""
    gen = torch.Generator().manual_seed(seed)
    heading = (torch.rand(count, generator=gen, dtype=torch.float64) - 0.5) * math.radians(100)
    elevation = math.radians(25) + torch.rand(count, generator=gen, dtype=torch.float64) * math.radians(30)
    shake = (torch.randn(count, generator=gen, dtype=torch.float64) * 2.0).tolist()
    return [photo((3 * math.cos(e) * math.cos(h), 3 * math.cos(e) * math.sin(h), 3 * math.sin(e)), (0, 0, 0),
                  shake[i] + (rolls[i] if rolls else 0.0), size=size)
            for i, (h, e) in enumerate(zip(heading.tolist(), elevation.tolist()))]


def degrees_from_up(vector: torch.Tensor) -> float:
    """The angle between `vector` [3] and UP, in degrees."""
    cosine = float((vector / vector.norm()) @ UP)
    return math.degrees(math.acos(max(-1.0, min(1.0, cosine))))


def mean_up(cameras: list[Camera]) -> torch.Tensor:
    """The rule before capture_up: the mean of the cameras' up axes [3] (not unit)."""
    return torch.stack([c.c2w[:3, 1] for c in cameras]).mean(0)


RED, BLUE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


def column(splats: int = 40, height: float = 1.2) -> GaussianModel:
    """An upright column of opaque splats along UP through the origin: the top half red, the
    bottom half blue."""
    along = torch.linspace(-height / 2, height / 2, splats, dtype=torch.float64)       # [S]
    colours = torch.tensor([RED if a > 0 else BLUE for a in along.tolist()], dtype=torch.float64)
    return GaussianModel(
        means=(along[:, None] * UP).float(),
        log_scales=torch.full((splats, 3), math.log(0.05)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(splats, 1),
        opacity_logits=torch.full((splats,), 5.0),
        sh=((colours - 0.5) / SH_C0).float()[:, None, :],
    )


def scene_points(parts: dict[str, int], seed: int = 0) -> torch.Tensor:
    """Points [P, 3] float64 of a scene around the `one_side` capture, turned into the TILT world:
    `parts` says how many points each part gets, of
      floor:   the ground (z = 0) within 4 units of the object, 2 mm of scatter;
      object:  a box 1 x 1 x 1.2 standing on it at the origin (points filling it);
      wall:    a wall (y = -3) behind the object, 8 wide and 4 high;
      ceiling: a ceiling (z = 4) above the cameras;
      clutter: a flat box 8 x 8 x 1.5 filled evenly (a room of low furniture, no floor)."""
    gen = torch.Generator().manual_seed(seed)

    def uniform(count: int, low: list[float], high: list[float]) -> torch.Tensor:
        box = torch.rand(count, 3, generator=gen, dtype=torch.float64)
        return torch.tensor(low, dtype=torch.float64) + box * (torch.tensor(high) - torch.tensor(low))

    boxes = {"floor": ([-4, -4, 0], [4, 4, 0]), "object": ([-0.5, -0.5, 0], [0.5, 0.5, 1.2]),
             "wall": ([-4, -3, 0], [4, -3, 4]), "ceiling": ([-4, -4, 4], [4, 4, 4]),
             "clutter": ([-4, -4, 0], [4, 4, 1.5])}
    points = torch.cat([uniform(count, *boxes[name]) for name, count in parts.items()])
    points += torch.randn(points.shape, generator=gen, dtype=torch.float64) * 0.002
    return points @ TILT.T
