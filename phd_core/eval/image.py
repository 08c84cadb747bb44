"""Image quality metrics: PSNR, SSIM and RMSE on [..., H, W, C] images in [0, 1].

SSIM follows Wang et al. (2004) as evaluation code reports it (and as scikit-image does
with gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1): an
11x11 normalised Gaussian window with sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, statistics
only where the window fits entirely inside the image ('valid', no padding), averaged over
positions and channels. It is differentiable, so trainers use 1 - ssim as the D-SSIM loss.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..errors import InputError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def psnr(pred: torch.Tensor, target: torch.Tensor, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of the mean squared error over ALL elements
    (a batch is pooled, not averaged per image); inf when the images are identical."""
    mse = _mse(pred, target)
    return math.inf if mse == 0 else 10 * math.log10(max_value ** 2 / mse)


def rmse(pred: torch.Tensor, target: torch.Tensor) -> float:
    """Root mean squared error over all elements."""
    return math.sqrt(_mse(pred, target))


def _mse(pred: torch.Tensor, target: torch.Tensor) -> float:
    _check_pair(pred, target, min_dims=1)
    mse = torch.mean((pred.double() - target.double()) ** 2).item()  # float64: near-equal images keep their digits
    if not math.isfinite(mse):
        raise InputError("pred", "images contain NaN or infinite values")
    return mse


def ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of [H, W, C] images (a scalar tensor) or of each image of a [B, H, W, C]
    batch (a [B] tensor).

    Images smaller than 11 pixels on a side use the largest odd window that fits, with the
    same sigma, so tiny test renders still get a defined value.
    """
    _check_pair(pred, target, min_dims=3)
    if pred.dim() not in (3, 4):
        raise InputError("pred", f"expected [H, W, C] or [B, H, W, C], got shape {list(pred.shape)}")
    batched = pred.dim() == 4
    dtype = torch.promote_types(pred.dtype, target.dtype)
    x = (pred if batched else pred[None]).permute(0, 3, 1, 2).to(dtype)     # [B, C, H, W]
    y = (target if batched else target[None]).permute(0, 3, 1, 2).to(dtype)
    c, h, w = x.shape[1:]
    size = min(SSIM_WINDOW, h - (h + 1) % 2, w - (w + 1) % 2)   # largest odd size <= min(11, H, W)
    g = _gaussian(size, SSIM_SIGMA, x.dtype)                    # [size]

    # Filter the five local moments of every channel in one depthwise, separable pass.
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)      # [B, 5C, H, W]
    stack = F.conv2d(stack, g.view(1, 1, size, 1).expand(5 * c, 1, size, 1), groups=5 * c)
    stack = F.conv2d(stack, g.view(1, 1, 1, size).expand(5 * c, 1, 1, size), groups=5 * c)
    mu_x, mu_y, e_xx, e_yy, e_xy = stack.split(c, dim=1)       # each [B, C, H - size + 1, W - size + 1]
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
                / ((mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2)))
    per_image = ssim_map.mean(dim=(1, 2, 3))                   # [B]
    return per_image if batched else per_image[0]


def _gaussian(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    """1-D Gaussian [size] that sums to 1; its outer product is the normalised 2-D window."""
    offsets = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-offsets ** 2 / (2 * sigma ** 2))
    return (g / g.sum()).to(dtype)


def _check_pair(pred: torch.Tensor, target: torch.Tensor, min_dims: int) -> None:
    if pred.shape != target.shape:
        raise InputError("pred", f"shape {list(pred.shape)} differs from target shape {list(target.shape)}")
    if pred.dim() < min_dims:
        raise InputError("pred", f"needs at least {min_dims} dimensions, got shape {list(pred.shape)}")
    if pred.numel() == 0:
        raise InputError("pred", f"image is empty: shape {list(pred.shape)}")
    if not pred.dtype.is_floating_point or not target.dtype.is_floating_point:
        raise InputError("pred", f"images must be floating point, got {pred.dtype} and {target.dtype}")
