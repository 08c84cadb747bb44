"""What a camera sees of a model (`Renderer.visibility`) against a float64 per-pixel count."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference.gaussians import render_reference

from phd_core.renderers.gs2d import SurfelRenderer
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField
from phd_core.renderers.visibility import fragment_visibility, fragment_visibility_reference
from phd_core.scene import look_at
from support.surfels import random_surfels


def random_scene(g: int, seed: int) -> GaussianModel:
    gen = torch.Generator().manual_seed(seed)
    return GaussianModel(means=(torch.rand(g, 3, generator=gen) * 2 - 1) * 0.8,
                         log_scales=torch.rand(g, 3, generator=gen) * 1.5 - 3.0,
                         quats=torch.randn(g, 4, generator=gen),
                         opacity_logits=torch.randn(g, generator=gen) * 2 + 2,
                         sh=torch.randn(g, 1, 3, generator=gen) * 0.4)


@pytest.mark.parametrize("seed", [0, 1])
def test_splat_weights_equal_a_float64_count_by_hand(seed: int) -> None:
    model = random_scene(40, seed)
    camera = look_at((0.3, -3.0, 1.0), (0, 0, 0), width=20, height=14, fov_x=0.7)
    renderer = GaussianRenderer(model)
    values = torch.rand(camera.height, camera.width, generator=torch.Generator().manual_seed(seed))
    vis = renderer.visibility(renderer.prepare(camera), values)
    by_hand: dict = {}
    _, alpha, _ = render_reference(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                                   camera.c2w.numpy(), camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                                   camera.height, (1.0, 1.0, 1.0), per_splat=by_hand)
    weight = np.zeros(40)
    weight[vis.elements.numpy()] = vis.weight.numpy()
    assert (by_hand["weight"] > 0.5).sum() >= 5          # the scene is not trivially empty or hidden
    assert (by_hand["weight"] < 0.5 * by_hand["footprint"]).sum() >= 3   # and some splats are mostly hidden
    np.testing.assert_allclose(weight, by_hand["weight"], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(vis.footprint.numpy(), by_hand["footprint"][vis.elements.numpy()], rtol=1e-4, atol=1e-5)
    # The elements' weights add up to the image's accumulated alpha; valued weighs them by pixel.
    assert float(vis.weight.sum()) == pytest.approx(float(alpha.sum()), rel=1e-5)
    assert torch.equal(vis.elements, torch.tensor(np.flatnonzero(by_hand["weight"])))
    assert torch.all(vis.visible_share <= 1.0) and torch.all(vis.visible_share >= 0.0)
    assert float(vis.valued.sum()) < float(vis.weight.sum())        # values in [0, 1)


@pytest.mark.parametrize("sums_of", [fragment_visibility, fragment_visibility_reference])
def test_fragment_sums_follow_the_compositors_stop_rule(sums_of) -> None:
    # One pixel, three opaque fragments: the third would bring T below 1e-4 and is not used.
    row_ptr = torch.tensor([0, 3, 3])                       # a second pixel with nothing on it
    alpha = torch.tensor([0.99, 0.98, 0.99])
    # Fragments name their element through a view's unit list: units[index] = [2, 0, 1].
    sums = sums_of(row_ptr, alpha, torch.tensor([0, 2, 1], dtype=torch.int32), torch.tensor([2, 1, 0]), 3,
                   torch.tensor([2.0, 5.0]))
    np.testing.assert_allclose(sums.weight.numpy(), [0.98 * 0.01, 0.0, 0.99], rtol=1e-6)
    np.testing.assert_allclose(sums.footprint.numpy(), [0.98, 0.99, 0.99], rtol=1e-6)
    np.testing.assert_allclose(sums.valued.numpy(), [2 * 0.98 * 0.01, 0.0, 2 * 0.99], rtol=1e-6)
    np.testing.assert_allclose(sums.left.numpy(), [0.01 * 0.02, 1.0], rtol=1e-5)


@pytest.mark.parametrize("with_values", [True, False])
def test_compiled_fragment_sums_match_the_torch_twin(with_values: bool) -> None:
    # Random rows of 0-60 fragments, dense enough that many rows stop before their end, and
    # elements shared between rows (the sums gather across pixels).
    g = torch.Generator().manual_seed(4)
    counts = torch.randint(0, 61, (300,), generator=g)
    row_ptr = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    alpha = (torch.rand(int(counts.sum()), generator=g) * 0.99).float()
    units = torch.randperm(500, generator=g)[:400]                 # the visible elements of a view
    index = torch.randint(0, 400, (len(alpha),), generator=g, dtype=torch.int32)
    values = torch.rand(300, generator=g, dtype=torch.float64) if with_values else None
    fast = fragment_visibility(row_ptr, alpha, index, units, 500, values)
    slow = fragment_visibility_reference(row_ptr, alpha, index, units, 500, values)
    assert (slow.left < 1e-3).sum() > 50                   # many rows reach the stop rule
    for a, b in [(fast.weight, slow.weight), (fast.footprint, slow.footprint), (fast.left, slow.left)]:
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-9, atol=1e-12)
    if with_values:
        np.testing.assert_allclose(fast.valued.numpy(), slow.valued.numpy(), rtol=1e-9, atol=1e-12)
    else:
        assert fast.valued is None and slow.valued is None


def test_surfel_weights_add_up_to_the_rendered_alpha_and_empty_space_is_counted() -> None:
    renderer = SurfelRenderer(random_surfels(200, seed=3))
    camera = look_at((0.0, -4.0, 1.0), (0, 0, 0), width=24, height=18, fov_x=0.8)
    vis = renderer.visibility(renderer.prepare(camera))
    alpha = renderer.render_full(camera).alpha
    assert float(vis.weight.sum()) == pytest.approx(float(alpha.sum()), rel=1e-4)
    assert 0 < vis.in_box <= camera.width * camera.height
    assert 0.0 <= vis.empty <= vis.in_box
    # A camera looking away from the model sees none of it, and no box.
    away = look_at((0.0, -4.0, 1.0), (0, -8, 1), width=24, height=18, fov_x=0.8)
    nothing = renderer.visibility(renderer.prepare(away))
    assert len(nothing.elements) == 0 and nothing.in_box == 0 and nothing.empty == 0.0


def test_nerf_cell_weights_add_up_to_the_rendered_alpha_and_follow_the_samples() -> None:
    model = RadianceField(NeRFConfig(depth=3, width=16, color_width=8, pos_freqs=3, dir_freqs=2, samples=24, near=1.0,
                                     far=7.0, bounds=[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], grid_resolution=8))
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():                                  # a field with structure, not a flat fog
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * (1.0 if p.dim() == 1 else 1.5 / p.shape[-1] ** 0.5))
    renderer = NeRFRenderer(model)
    camera = look_at((2.5, -3.0, 2.0), (0.0, 0.0, 0.0), width=12, height=10, fov_x=0.8)
    vis = renderer.visibility(renderer.prepare(camera), torch.ones(10, 12))
    alpha = renderer.render_full(camera).alpha
    assert float(vis.weight.sum()) == pytest.approx(float(alpha.sum()), rel=1e-4)
    assert float(vis.valued.sum()) == pytest.approx(float(vis.weight.sum()), rel=1e-9)   # values of 1
    assert torch.all(vis.weight <= vis.footprint + 1e-12)
    # Cells are the occupancy grid's; their points lie inside the scene box.
    assert int(vis.elements.max()) < 8 ** 3 and bool((vis.points.abs() < 1.0).all())
    # Empty the grid: nothing is seen, and every ray through the box keeps its light.
    model.grid.set_density(torch.zeros(8 ** 3))
    empty = renderer.visibility(renderer.prepare(camera))
    assert len(empty.elements) == 0 and empty.empty == pytest.approx(empty.in_box) and empty.in_box > 0
