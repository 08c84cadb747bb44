"""Colour-mapped PNG heat maps of uncertainty maps (zeta), written atomically.

The colormap is a perceptually ordered dark-blue -> green -> yellow ramp (viridis-like),
defined by ten anchor colours spaced evenly on [0, 1] and linearly interpolated in RGB.
The scale is stated, never implicit: a pixel's value is max over channels of zeta (so the
brightest pixel of a map is the view's sigma_max), divided by `vmax` and clipped to
[0, 1]. vmax is either given (fixed, comparable across images) or the image's own max.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from .png import write_png

# Anchor colours of the ramp at 0, 1/9, ..., 1 (sRGB, 0-255).
ANCHORS = np.array([
    (68, 1, 84), (72, 40, 120), (62, 74, 137), (49, 104, 142), (38, 130, 142),
    (31, 158, 137), (53, 183, 121), (109, 205, 89), (180, 222, 44), (253, 231, 37),
], dtype=np.float64)


def apply_colormap(t: np.ndarray) -> np.ndarray:
    """Map values t in [0, 1] (any shape) to RGB uint8 [..., 3] by linear interpolation."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    position = t * (len(ANCHORS) - 1)
    low = np.minimum(np.floor(position).astype(np.int64), len(ANCHORS) - 2)
    frac = (position - low)[..., None]
    rgb = ANCHORS[low] * (1 - frac) + ANCHORS[low + 1] * frac
    return np.rint(rgb).astype(np.uint8)


def check_vmax(vmax: float) -> float:
    """A heat map's top value, checked: a positive finite number."""
    if isinstance(vmax, bool) or not isinstance(vmax, (int, float)) or not math.isfinite(vmax) or vmax <= 0:
        raise InputError("vmax", f"must be a positive finite number, got {vmax!r}")
    return float(vmax)


def colorize(values: Tensor, vmax: float | None = None) -> tuple[np.ndarray, float]:
    """Heat-map image of a [H, W] or [H, W, C] map: (RGB uint8 [H, W, 3], vmax used).

    vmax None uses the map's max; a map that is 0 everywhere then gets vmax 0 and is drawn
    in the colour of 0.
    """
    v = torch.as_tensor(values).detach().to(torch.float64)
    if v.dim() == 3:
        v = v.amax(dim=-1)
    if v.dim() != 2:
        raise InputError("values", f"heat map needs a [H, W] or [H, W, C] map, got shape {list(v.shape)}")
    if not torch.isfinite(v).all():
        raise InputError("values", "contains NaN or infinite values")
    vmax = float(v.max()) if vmax is None else check_vmax(vmax)
    scaled = (v / vmax).numpy() if vmax > 0 else np.zeros(tuple(v.shape))
    return apply_colormap(scaled), float(vmax)


def write_heatmap(path: str | Path, values: Tensor, vmax: float | None = None) -> float:
    """Write a heat-map PNG atomically; returns the vmax it was drawn with."""
    rgb, used = colorize(values, vmax)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, rgb)
    return used
