"""Small renderers that implement the renderer protocol, for testing PH-Dropout.

BlobRenderer: every unit is a coloured isotropic Gaussian blob in 3D, projected with the
pinhole camera and alpha-composited over the background in unit order (compositing
"over"), or subtracted from the background with weights that sum to at most 1
("additive": the image is linear in the keep-mask, so the calibration error is provably
non-decreasing in the dropout ratio under nested masks). Dropping units changes the image
smoothly; every unit dropped gives the background.
ConstantRenderer ignores the mask (identical samples); EmptyRenderer has no units.
"""

from __future__ import annotations

import math

import torch

from phd_core.renderers import DEFAULT_SIGNAL, CameraView, check_keep, signal_channels
from phd_core.scene import Camera, look_at


class BlobRenderer:
    kind = "toy"

    def __init__(self, means: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor, scales: torch.Tensor,
                 *, background=(1.0, 1.0, 1.0), compositing: str = "over", training_cameras=None):
        self.means = means.to(torch.float64)            # [U, 3]
        self.colors = colors.to(torch.float64)          # [U, 3]
        self.opacities = opacities.to(torch.float64)    # [U]
        self.scales = scales.to(torch.float64)          # [U] world-space std of each blob
        self.background = torch.tensor(background, dtype=torch.float64)
        self.compositing = compositing
        self.training_cameras = training_cameras
        self.calls = 0                                  # number of render() calls, for batching tests

    @classmethod
    def random(cls, num_units: int = 40, seed: int = 0, **kw) -> "BlobRenderer":
        g = torch.Generator().manual_seed(seed)
        means = (torch.rand(num_units, 3, generator=g, dtype=torch.float64) - 0.5) * 1.6
        colors = torch.rand(num_units, 3, generator=g, dtype=torch.float64)
        opacities = 0.3 + 0.6 * torch.rand(num_units, generator=g, dtype=torch.float64)
        scales = 0.15 + 0.25 * torch.rand(num_units, generator=g, dtype=torch.float64)
        return cls(means, colors, opacities, scales, **kw)

    @property
    def num_units(self) -> int:
        return self.means.shape[0]

    def describe(self) -> dict:
        return {"kind": self.kind, "num_units": self.num_units, "compositing": self.compositing}

    def alphas(self, camera: Camera) -> torch.Tensor:
        """Per-unit coverage of every pixel: [U, H, W] float64 in [0, 0.99]."""
        w2c = camera.world_to_camera()
        points = self.means @ w2c[:3, :3].T + w2c[:3, 3]                 # [U, 3] camera space (OpenCV)
        depth = points[:, 2]
        visible = depth > 0.1
        z = torch.where(visible, depth, torch.ones_like(depth))
        u = camera.fx * points[:, 0] / z + camera.cx                     # [U] pixel coordinates
        v = camera.fy * points[:, 1] / z + camera.cy
        radius = self.scales * camera.fx / z                             # [U] pixels
        px = torch.arange(camera.width, dtype=torch.float64) + 0.5
        py = torch.arange(camera.height, dtype=torch.float64) + 0.5
        d2 = (px[None, None, :] - u[:, None, None]) ** 2 + (py[None, :, None] - v[:, None, None]) ** 2
        alpha = self.opacities[:, None, None] * torch.exp(-0.5 * d2 / radius[:, None, None] ** 2)
        return torch.where(visible[:, None, None], alpha, torch.zeros_like(alpha)).clamp(max=0.99)

    def prepare(self, camera: Camera) -> CameraView:
        return CameraView(self, camera)

    def render(self, camera: Camera, keep: torch.Tensor | None = None,
               signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        self.calls += 1
        keep = check_keep(keep, self.num_units)
        if keep is None:
            keep = torch.ones(1, self.num_units, dtype=torch.bool)
        alpha = keep.to(torch.float64)[:, :, None, None] * self.alphas(camera)[None]   # [N, U, H, W]
        if self.compositing == "additive":
            weights = alpha / max(self.num_units, 1)                     # sum over units <= 1
            color, covered = torch.einsum("nuhw,uc->nhwc", weights, self.colors), weights.sum(1)
            image = self.background - torch.einsum("nuhw,uc->nhwc", weights, self.background - self.colors)
        else:
            # Unit order: transmittance before unit g is prod_{j<g} (1 - alpha_j).
            transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha], 1), 1)
            color = torch.einsum("nuhw,uc->nhwc", alpha * transmittance[:, :-1], self.colors)
            covered = 1 - transmittance[:, -1]
            image = color + transmittance[:, -1, :, :, None] * self.background
        if signal_channels(signal) == 4:                                 # colour over black plus alpha
            image = torch.cat([color, covered[..., None]], -1)
        return image.to(torch.float32).clamp(0, 1)


class ConstantRenderer:
    """Ignores the keep-mask: every sample is the same (non-trivial) image."""

    kind = "toy"
    training_cameras = None

    def __init__(self, num_units: int = 10, value: float | None = None):
        self._num_units = num_units
        self.value = value

    @property
    def num_units(self) -> int:
        return self._num_units

    def describe(self) -> dict:
        return {"kind": self.kind, "num_units": self.num_units}

    def prepare(self, camera: Camera) -> CameraView:
        return CameraView(self, camera)

    def render(self, camera: Camera, keep: torch.Tensor | None = None,
               signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        keep = check_keep(keep, self.num_units)
        n = 1 if keep is None else keep.shape[0]
        if self.value is not None:
            image = torch.full((camera.height, camera.width, 3), self.value)
        else:  # a smooth pattern with values that are not exactly representable sums
            y = torch.linspace(0.1, 0.9, camera.height)[:, None, None]
            x = torch.linspace(0.2, 0.7, camera.width)[None, :, None]
            image = (0.3 * y + 0.6 * x + torch.tensor([0.0, 0.05, 0.1])).clamp(0, 1) / 3 + 1 / 7
        if signal_channels(signal) == 4:                                 # opaque everywhere
            image = torch.cat([image, torch.ones_like(image[..., :1])], -1)
        return image.to(torch.float32).expand(n, -1, -1, -1).clone()


class EmptyRenderer(ConstantRenderer):
    """A model without units: the background everywhere."""

    def __init__(self):
        super().__init__(num_units=0, value=1.0)


def ring_cameras(count: int = 6, size: int = 12, radius: float = 4.0, height: float = 1.0) -> list[Camera]:
    """Cameras on a ring around the origin, looking at it."""
    cameras = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        eye = (radius * math.cos(angle), radius * math.sin(angle), height)
        cameras.append(look_at(eye, (0, 0, 0), (0, 0, 1), width=size, height=size, fov_x=0.7))
    return cameras


def away_camera(size: int = 12) -> Camera:
    """A camera outside the scene looking away from it: sees only background."""
    return look_at((0, 0, 4), (0, 0, 10), (0, 1, 0), width=size, height=size, fov_x=0.7)
