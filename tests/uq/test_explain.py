"""Per-splat coverage, fragility and novelty (`phd_core.uq.explain`) against a brute-force
float64 computation: the per-pixel reference renderer run once per view for the weights and
once per dropout mask for zeta, with the sums of the module docstring written out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference.gaussians import render_reference

from phd_core.errors import InputError
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.scene import Camera, look_at
from phd_core.uq import dropout_uniforms, keep_masks
from phd_core.uq.explain import explain
from support.toy_renderers import ConstantRenderer

RATIO, SAMPLES, SEED = 0.3, 5, 2


def tiny_scene() -> GaussianModel:
    """40 splats in a box, some hiding others; behind it (as the captured views see it) an
    opaque wall of 6 wide splats, and behind the wall a pair only the pick sees."""
    gen = torch.Generator().manual_seed(3)
    means = (torch.rand(40, 3, generator=gen) * 2 - 1) * 0.6
    log_scales = torch.rand(40, 3, generator=gen) * 1.2 - 3.0
    opacity_logits = torch.randn(40, generator=gen) * 1.5 + 1.5
    means[:2] = torch.tensor([[0.0, 1.6, 0.0], [0.15, 1.7, 0.1]])
    means[2:8] = torch.tensor([[x, 1.1, z] for x in (-0.5, 0.0, 0.5) for z in (-0.3, 0.4)])
    log_scales[2:8] = torch.tensor([math.log(0.3), math.log(0.02), math.log(0.3)])
    opacity_logits[2:8] = 6.0
    return GaussianModel(means=means, log_scales=log_scales, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(40, 1),
                         opacity_logits=opacity_logits, sh=torch.randn(40, 1, 3, generator=gen) * 0.4)


def cameras() -> tuple[list[Camera], Camera]:
    captured = [look_at((3.0 * math.sin(a), -3.0 * math.cos(a), 0.8), (0, 0, 0), width=18, height=14, fov_x=0.8)
                for a in (-0.3, 0.0, 0.3)]
    pick = look_at((0.2, 3.5, 0.6), (0, 0, 0), width=18, height=14, fov_x=0.8)
    return captured, pick


def by_hand(model: GaussianModel, camera: Camera, keep: np.ndarray) -> tuple[np.ndarray, ...]:
    """(weight, footprint, valued) [G] of one view in float64: zeta's channel max from the
    reference renders under each mask (ddof 1), then the full model's weights times it."""
    args = (model.means, model.log_scales, model.quats, model.opacity_logits, model.sh, camera.c2w.numpy(),
            camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, (1.0, 1.0, 1.0))
    renders = np.stack([render_reference(*args, keep=k)[0] for k in keep])       # [N, H, W, 3]
    zeta = renders.std(axis=0, ddof=1).max(axis=-1)                               # [H, W]
    sums: dict = {}
    render_reference(*args, per_splat=sums, pixel_values=zeta)
    return sums["weight"], sums["footprint"], sums["valued"]


def test_explanation_equals_a_brute_force_float64_computation() -> None:
    model = tiny_scene()
    captured, pick = cameras()
    result = explain(GaussianRenderer(model), captured, ratio=RATIO, samples=SAMPLES, seed=SEED, pick=pick)
    keep = keep_masks(dropout_uniforms(40, SAMPLES, SEED), RATIO).numpy()
    views = [by_hand(model, camera, keep) for camera in captured + [pick]]
    share = [np.clip(w / np.maximum(f, 1e-300), 0.0, 1.0) for w, f, _ in views]
    coverage = sum(share[:3])
    fragility_num, fragility_den = sum(v for _, _, v in views), sum(w for w, _, _ in views)
    novelty = share[3] * np.prod([1.0 - s for s in share[:3]], axis=0)

    np.testing.assert_allclose(result.coverage.numpy(), coverage, rtol=1e-4, atol=1e-5)
    seen = fragility_den > 0
    assert np.array_equal(~torch.isnan(result.fragility).numpy(), seen)
    np.testing.assert_allclose(result.fragility.numpy()[seen], fragility_num[seen] / fragility_den[seen],
                               rtol=1e-3, atol=1e-5)
    assert result.novelty is not None
    np.testing.assert_allclose(result.novelty.numpy(), novelty, rtol=1e-4, atol=1e-5)
    # The scene is not trivial: some splats are hidden from the captured views, the pair behind
    # the object is what the pick newly sees, and zeta varies between splats.
    assert np.all(coverage[:2] < 0.1) and (coverage > 1.5).sum() >= 5
    assert set(np.argsort(-novelty)[:2]) == {0, 1}
    assert np.nanstd(result.fragility.numpy()) > 0.1 * np.nanmean(result.fragility.numpy())
    assert (result.views, result.samples, result.ratio) == (3, SAMPLES, RATIO)


def test_no_pick_no_novelty_and_identical_masks_mean_no_fragility() -> None:
    model = tiny_scene()
    captured, _ = cameras()
    result = explain(GaussianRenderer(model), captured, ratio=0.0, samples=3)
    assert result.novelty is None
    seen = ~torch.isnan(result.fragility)
    assert seen.sum() > 10 and torch.all(result.fragility[seen] == 0)     # ratio 0: every mask keeps all


def test_refuses_what_it_cannot_explain() -> None:
    captured, _ = cameras()
    with pytest.raises(InputError) as err:
        explain(GaussianRenderer(tiny_scene()), [], ratio=0.1, samples=3)
    assert err.value.field == "captured"
    with pytest.raises(InputError) as err:
        explain(ConstantRenderer(), captured, ratio=0.1, samples=3)      # a family without visibility
    assert err.value.field == "model"
