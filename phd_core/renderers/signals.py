"""What a render returns for PH-Dropout: the image its uncertainty is measured on.

Every family composites its model into colour over black (premultiplied colour) plus the
accumulated opacity, and a `Signal` turns those into the image `render(camera, keep, signal)`
returns. The paper measures zeta and the calibration error on the colour composited over the
background (`composited`); where dropout uncovers the backdrop, that counts the contrast to a
colour the model does not own, so r_drop and zeta move with the backdrop (docs/phdropout.md).
`premultiplied` measures them on the colour over black plus alpha, which no backdrop enters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from ..registry import Registry


@dataclass(frozen=True)
class Signal:
    name: str
    channels: int       # of the image: C in [N, H, W, C]
    help: str
    # (colour over black [N, H, W, 3], alpha [N, H, W], background [3]) -> [N, H, W, channels] in [0, 1];
    # may write into the colour's memory
    image: Callable[[Tensor, Tensor, Tensor], Tensor]


def over(color: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """Colour over black [N, H, W, 3] with alpha [N, H, W] composited on `background` [3]
    (a new tensor, not clamped)."""
    image = (1.0 - alpha)[..., None].clamp_min(0.0) * background.to(color.dtype)    # [N, H, W, 3], then in place
    image += color
    return image


def _composited(color: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    return over(color, alpha, background).clamp_(0.0, 1.0)


def _premultiplied(color: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    return torch.cat([color, alpha[..., None].to(color.dtype)], dim=-1).clamp_(0.0, 1.0)     # [N, H, W, 4]


SIGNALS: Registry[Signal] = Registry("signal")
COMPOSITED = SIGNALS.register(Signal(
    "composited", 3, "colour composited over the background (the paper's; moves with the backdrop)", _composited)).name
PREMULTIPLIED = SIGNALS.register(Signal(
    "premultiplied", 4, "colour over black plus alpha (no backdrop enters)", _premultiplied)).name
DEFAULT_SIGNAL = COMPOSITED


def signal_image(signal: str, color: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """The image of `signal` from a render's colour over black [N, H, W, 3] and alpha [N, H, W]."""
    return SIGNALS.lookup(signal, "signal").image(color, alpha, background)


def signal_channels(signal: str) -> int:
    """Channels of `signal`'s images (checked: an InputError names the field `signal`)."""
    return SIGNALS.lookup(signal, "signal").channels


def signals_help() -> str:
    return "; ".join(f"{s.name}: {s.help}" for s in SIGNALS.values())
