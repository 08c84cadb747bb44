"""A splat model as the points the page's 3D view draws (`phd_core.renderers.points`)."""

from __future__ import annotations

import pytest
import torch

from phd_core.errors import InputError
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.points import importance, point_subset, scene_points
from support.fixtures import svc_random_gaussians
from support.toy_renderers import ConstantRenderer


def test_the_draw_is_seeded_and_favours_important_splats() -> None:
    weights = torch.cat([torch.full((500,), 0.01), torch.full((500,), 1.0)])
    first, again = point_subset(weights, 100), point_subset(weights, 100)
    assert torch.equal(first, again) and len(first) == 100 and len(torch.unique(first)) == 100
    assert torch.all(first[1:] > first[:-1])                        # ascending ids
    heavy = int((first >= 500).sum())
    assert heavy >= 90                     # expected 99 of 100 (weights 100:1, half the splats each)
    assert not torch.equal(point_subset(weights, 100, seed=1), first)
    assert torch.equal(point_subset(weights, 2000), torch.arange(1000))     # under the cap: every splat
    with pytest.raises(InputError):
        point_subset(weights, 0)


def test_points_carry_the_models_colour_opacity_and_size() -> None:
    model = svc_random_gaussians(300)
    points = scene_points(GaussianRenderer(model), cap=120)
    assert points.total == 300 and len(points.ids) == 120
    assert torch.equal(points.ids, point_subset(importance(model), 120))
    ids = points.ids
    assert torch.equal(points.positions, model.means[ids])
    expected_rgb = (model.base_colours()[ids] * 255).round()
    assert torch.equal(points.colours[:, :3].double(), expected_rgb)
    opacity = torch.sigmoid(model.opacity_logits.double()[ids])
    assert torch.allclose(points.colours[:, 3].double() / 255, opacity, atol=0.5 / 255)
    sigma = model.log_scales.double()[ids].exp().prod(dim=1) ** (1 / 3)        # geometric mean of the scales
    assert torch.allclose(points.sigma.double(), sigma, rtol=1e-5)
    with pytest.raises(InputError) as err:
        scene_points(ConstantRenderer())
    assert err.value.field == "model"
