"""What a camera sees of a model (`Renderer.visibility`) against a float64 per-pixel count."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference.gaussians import render_reference

from phd_core.renderers import FAMILIES
from phd_core.renderers.gs2d import SurfelRenderer
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField
from phd_core.renderers.nerf.config import CHUNK_SAMPLES
from phd_core.renderers.nerf.volume import camera_rays, ray_box, ray_samples, render_rays, segment_weights
from phd_core.renderers.visibility import fragment_visibility, fragment_visibility_reference, prepare_seeing
from phd_core.scene import look_at
from support.calls import count_calls
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


def structured_field(seed: int = 1) -> RadianceField:
    """A small NeRF whose density has structure (not a flat fog), on an 8^3 occupancy grid."""
    model = RadianceField(NeRFConfig(depth=3, width=16, color_width=8, pos_freqs=3, dir_freqs=2, samples=24, near=1.0,
                                     far=7.0, bounds=[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], grid_resolution=8))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * (1.0 if p.dim() == 1 else 1.5 / p.shape[-1] ** 0.5))
    return model


def test_nerf_cell_weights_add_up_to_the_rendered_alpha_and_follow_the_samples() -> None:
    model = structured_field()
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


def nerf_visibility_by_a_full_render(renderer: NeRFRenderer, camera, values: torch.Tensor) -> dict:
    """The cell sums as the visibility pass made them before it read the masked renders' view: one
    unmasked render per ray chunk (colour branch and compositing included), its densities summed."""
    model, grid = renderer.model, renderer.model.grid
    origins, dirs = camera_rays(camera)
    sums = {name: torch.zeros(grid.resolution ** 3, dtype=torch.float64) for name in ("weight", "footprint", "valued")}
    chunk = max(1, CHUNK_SAMPLES // model.config.samples)
    for start in range(0, len(origins), chunk):
        o, d = origins[start:start + chunk], dirs[start:start + chunk]
        _, delta, points, valid = ray_samples(model, o, d, use_grid=renderer.use_grid)
        sigma = render_rays(model, o, d, use_grid=renderer.use_grid, with_sigma=True).sigma[0]
        tau = (sigma * delta).double() * valid
        w, _ = segment_weights(tau)
        cell = grid.cells(points.reshape(-1, 3))
        sums["weight"].index_add_(0, cell, w.reshape(-1))
        sums["footprint"].index_add_(0, cell, -torch.expm1(-tau).reshape(-1))
        sums["valued"].index_add_(0, cell, (w * values.reshape(-1).double()[start:start + chunk, None]).reshape(-1))
    return sums


@pytest.mark.parametrize("use_grid", [True, False])
def test_nerf_visibility_from_the_masked_renders_is_the_full_renders_bit_for_bit(use_grid: bool, monkeypatch) -> None:
    model = structured_field(seed=2)
    density = model.cell_density()
    model.grid.set_density(torch.where(density > density.median(), density, torch.zeros_like(density)))
    assert 0.2 < model.grid.fraction < 0.8                 # samples in empty cells are skipped
    renderer = NeRFRenderer(model, use_grid=use_grid)
    camera = look_at((2.5, -3.0, 2.0), (0.0, 0.0, 0.0), width=12, height=10, fov_x=0.8)
    values = torch.rand(10, 12, generator=torch.Generator().manual_seed(3))
    keep = torch.rand(5, renderer.num_units, generator=torch.Generator().manual_seed(4)) >= 0.5
    plain = renderer.prepare(camera)
    renders = plain.render(keep)
    # A view prepared to be seen renders the same images, and keeps the full model's densities.
    seeing = prepare_seeing(renderer, camera)
    assert torch.equal(seeing.render(keep[:2]), renders[:2]) and seeing.nbytes > 0
    assert torch.equal(seeing.render(keep[2:]), renders[2:])
    assert seeing.nbytes <= FAMILIES["nerf"].memory(renderer, camera).seen     # what a plan counts for it
    encoded = count_calls(monkeypatch, model, "encode")
    gathered = renderer.visibility(seeing, values)
    assert encoded["calls"] == 0, "the visibility of a seen view runs no network"
    by_itself = renderer.visibility(plain, values)           # no densities kept: the density network alone
    assert encoded["calls"] > 0
    expected = nerf_visibility_by_a_full_render(renderer, camera, values)
    seen = expected["weight"] > 0
    assert int(seen.sum()) >= 10
    for vis in (gathered, by_itself):
        assert torch.equal(vis.elements, seen.nonzero().squeeze(1))
        for name in ("weight", "footprint", "valued"):
            assert torch.equal(getattr(vis, name), expected[name][vis.elements]), name
    assert (gathered.empty, gathered.in_box) == (by_itself.empty, by_itself.in_box)
    origins, dirs = camera_rays(camera)
    t_in, t_out = ray_box(origins, dirs, model.grid.lo, model.grid.lo + model.grid.size)
    in_box = ((t_out > t_in) & (t_out > 0)).view(10, 12)
    light = 1 - renderer.render_full(camera).alpha[0]       # transmittance left, by the compositing of a render
    assert gathered.in_box == int(in_box.sum())
    assert gathered.empty == pytest.approx(float(light[in_box].sum()), abs=1e-4)
