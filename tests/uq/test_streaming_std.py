"""The std over N masks is accumulated chunk by chunk (RunningStd): memory holds one chunk of
renders, never all N, and the result is the float64 two-pass std whatever the chunking."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from phd_core import uq as phd
from phd_core.errors import InputError
from support.toy_renderers import BlobRenderer, ConstantRenderer, ring_cameras


@pytest.mark.parametrize("chunks", [[7], [1] * 7, [3, 4], [2, 1, 4]])
def test_running_std_matches_float64_reference_for_any_chunking(chunks: list[int]) -> None:
    g = torch.Generator().manual_seed(0)
    samples = 1000.0 + torch.rand(sum(chunks), 5, 4, generator=g, dtype=torch.float64)  # offset: cancellation bait
    running = phd.RunningStd()
    for part in samples.split(chunks):
        running.add(part.float())
    std, mean = running.result(ddof=1)
    reference = samples.float().double().numpy()
    np.testing.assert_allclose(std.numpy(), reference.std(axis=0, ddof=1), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(mean.numpy(), reference.mean(axis=0), rtol=1e-12)


def test_identical_samples_give_exactly_zero_in_any_chunking() -> None:
    image = torch.full((3, 4), 0.1234567, dtype=torch.float32)
    for dtype in (torch.float32, torch.float64):
        running = phd.RunningStd(dtype)
        for m in (1, 5, 2, 64):
            running.add(image.expand(m, 3, 4))
        std, mean = running.result()
        assert torch.count_nonzero(std) == 0
        assert torch.equal(mean, image.to(dtype))


def test_limit_mask_batch_bounds_the_render_batch_and_keeps_the_numbers() -> None:
    renderer = BlobRenderer.random(30, seed=3)
    camera = ring_cameras(1)[0]
    full = phd.view_uncertainty(renderer, camera, ratio=0.3, samples=20, seed=2, keep_maps=True)
    renderer.calls = 0
    with phd.limit_mask_batch(3):
        small = phd.view_uncertainty(renderer, camera, ratio=0.3, samples=20, seed=2, keep_maps=True)
    assert renderer.calls == 7                      # ceil(20 / 3) renders of at most 3 masks
    torch.testing.assert_close(small.zeta, full.zeta, rtol=0, atol=1e-6)
    assert small.sigma_max == pytest.approx(full.sigma_max, abs=1e-7)
    renderer.calls = 0
    phd.view_uncertainty(renderer, camera, ratio=0.3, samples=20, seed=2)
    assert renderer.calls == 1                      # the limit ended with its block
    with pytest.raises(InputError) as exc:
        with phd.limit_mask_batch(0):
            pass
    assert exc.value.field == "masks"


def test_constant_renders_give_zero_uncertainty_through_chunks() -> None:
    with phd.limit_mask_batch(2):
        view = phd.view_uncertainty(ConstantRenderer(8, value=0.3), ring_cameras(1)[0], ratio=0.5, samples=9)
    assert view.sigma_max == 0.0 and view.sigma_mean == 0.0
