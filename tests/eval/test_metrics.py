"""PSNR, RMSE and SSIM against hand-computed values and an independent float64 brute force."""

import math

import numpy as np
import pytest
import torch

from phd_core.errors import InputError
from phd_core.eval import psnr, rmse, ssim

C1, C2 = 0.01 ** 2, 0.03 ** 2


def ssim_brute_force(x: np.ndarray, y: np.ndarray, size: int = 11, sigma: float = 1.5) -> float:
    """Wang et al. SSIM of [H, W, C] images: an explicit loop over every window that fits,
    centred (two-pass) moments in float64, mean over windows and channels."""
    g = np.array([math.exp(-((k - (size - 1) / 2) ** 2) / (2 * sigma ** 2)) for k in range(size)])
    window = np.outer(g, g) / np.outer(g, g).sum()
    x, y = x.astype(np.float64), y.astype(np.float64)
    height, width, channels = x.shape
    values = []
    for ch in range(channels):
        for i in range(height - size + 1):
            for j in range(width - size + 1):
                px, py = x[i:i + size, j:j + size, ch], y[i:i + size, j:j + size, ch]
                mx, my = (window * px).sum(), (window * py).sum()
                vx, vy = (window * (px - mx) ** 2).sum(), (window * (py - my) ** 2).sum()
                cxy = (window * (px - mx) * (py - my)).sum()
                values.append((2 * mx * my + C1) * (2 * cxy + C2) / ((mx ** 2 + my ** 2 + C1) * (vx + vy + C2)))
    return float(np.mean(values))


def random_pair(shape, noise, seed):
    rng = np.random.default_rng(seed)
    x = rng.random(shape)
    y = np.clip(x + noise * rng.standard_normal(shape), 0, 1)
    return x, y


def test_psnr_of_images_differing_by_0_1_is_20_db():
    a = torch.full((4, 5, 3), 0.5, dtype=torch.float64)
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-9)
    # float32 images, and a max_value that rescales the peak: 0.5 error on a 0..2 scale = 12.04 dB
    b = torch.full((4, 5, 3), 0.25)
    assert psnr(b, b + 0.5) == pytest.approx(10 * math.log10(4), abs=1e-9)
    assert psnr(b, b + 0.5, max_value=2.0) == pytest.approx(10 * math.log10(16), abs=1e-9)


def test_psnr_pools_the_squared_error_of_a_batch():
    target = torch.zeros(2, 3, 3, 3, dtype=torch.float64)
    pred = target.clone()
    pred[1] = 0.2                           # MSE 0 and 0.04: pooled 0.02
    assert psnr(pred, target) == pytest.approx(10 * math.log10(1 / 0.02), abs=1e-9)
    assert rmse(pred, target) == pytest.approx(math.sqrt(0.02), abs=1e-12)


def test_psnr_is_infinite_for_identical_images():
    a = torch.rand(5, 5, 3)
    assert psnr(a, a.clone()) == math.inf
    assert rmse(a, a.clone()) == 0.0


def test_metrics_reject_bad_input():
    a = torch.rand(5, 5, 3)
    with pytest.raises(InputError) as info:
        psnr(a, torch.rand(5, 4, 3))
    assert info.value.field == "pred"
    bad = a.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        psnr(bad, a)
    with pytest.raises(InputError):
        ssim(torch.rand(5, 5), torch.rand(5, 5))
    with pytest.raises(InputError):
        ssim(torch.rand(0, 5, 3), torch.rand(0, 5, 3))


def test_ssim_of_identical_images_is_one():
    a = torch.rand(2, 16, 16, 3)
    assert torch.allclose(ssim(a, a.clone()), torch.ones(2), atol=1e-6)


@pytest.mark.parametrize("shape, noise, window", [
    ((16, 19, 3), 0.1, 11),   # the standard window
    ((14, 14, 1), 0.5, 11),
    ((7, 9, 3), 0.2, 7),      # smaller than 11: largest odd window that fits
    ((4, 6, 2), 0.2, 3),
])
def test_ssim_matches_float64_brute_force(shape, noise, window):
    x, y = random_pair(shape, noise, seed=sum(shape))
    expected = ssim_brute_force(x, y, size=window)
    got = ssim(torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32))
    assert got.shape == ()
    assert got.item() == pytest.approx(expected, abs=1e-5)


def test_ssim_is_symmetric_and_per_image_when_batched():
    x, y = random_pair((3, 15, 13, 3), 0.3, seed=7)
    xt, yt = torch.tensor(x), torch.tensor(y)
    batch = ssim(xt, yt)
    assert batch.shape == (3,)
    assert torch.allclose(batch, ssim(yt, xt), atol=1e-12)
    for k in range(3):
        assert batch[k].item() == pytest.approx(ssim_brute_force(x[k], y[k]), abs=1e-10)
    assert len(set(batch.tolist())) == 3


def test_ssim_of_constant_images_is_the_luminance_term():
    # Zero variance everywhere: the contrast-structure factor is C2 / C2 = 1.
    a, b = 0.3, 0.7
    got = ssim(torch.full((12, 12, 3), a, dtype=torch.float64), torch.full((12, 12, 3), b, dtype=torch.float64))
    assert got.item() == pytest.approx((2 * a * b + C1) / (a * a + b * b + C1), abs=1e-12)


def test_ssim_gradient_is_finite_nonzero_and_correct():
    x, y = random_pair((11, 12, 1), 0.2, seed=3)
    pred = torch.tensor(x, requires_grad=True)
    (1 - ssim(pred, torch.tensor(y))).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(lambda p: ssim(p, torch.tensor(y)), (torch.tensor(x, requires_grad=True),))
