"""PNG encoding of images, the one copy every writer uses (CLI, demo, heat maps, service)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .files import write_bytes_atomic


def png_bytes(image: torch.Tensor | np.ndarray) -> bytes:
    """PNG of an RGB image: uint8 [H, W, 3] as it is, or float [H, W, 3] in [0, 1] (clamped, rounded)."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu()
        if image.is_floating_point():
            image = (image.clamp(0, 1) * 255).round().to(torch.uint8)
        image = image.numpy()
    return iio.imwrite("<bytes>", image, extension=".png")


def write_png(path: str | Path, image: torch.Tensor | np.ndarray) -> None:
    """Write `image` (see `png_bytes`) as a PNG file atomically."""
    write_bytes_atomic(path, png_bytes(image))
