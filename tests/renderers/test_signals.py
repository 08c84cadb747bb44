"""The signals a render returns (phd_core.renderers.signals): colour over the background, or
colour over black plus alpha, for every family from one render."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference.gaussians import render_reference

from phd_core.errors import InputError
from phd_core.renderers.gs2d import SurfelRenderer
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField
from phd_core.scene import look_at
from support.surfels import random_surfels

GREY = (0.5, 0.4, 0.3)
CAMERA = look_at((0.3, -3.0, 1.0), (0, 0, 0), width=20, height=14, fov_x=0.7)


def random_gaussians(g: int = 40, seed: int = 3) -> GaussianModel:
    gen = torch.Generator().manual_seed(seed)
    return GaussianModel(means=(torch.rand(g, 3, generator=gen) * 2 - 1) * 0.8,
                         log_scales=torch.rand(g, 3, generator=gen) * 1.5 - 3.5,
                         quats=torch.randn(g, 4, generator=gen), opacity_logits=torch.randn(g, generator=gen) * 2,
                         sh=torch.randn(g, 4, 3, generator=gen) * 0.4)


def random_nerf(background: str) -> RadianceField:
    config = NeRFConfig(depth=3, width=16, color_width=8, pos_freqs=3, dir_freqs=2, samples=24, near=1.0, far=7.0,
                        bounds=[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], grid_resolution=8, background=background)
    model = RadianceField(config)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():       # random weights scaled up, so that the field has visible structure
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * (1.0 if p.dim() == 1 else 1.5 / math.sqrt(p.shape[-1])))
    return model


def renderers(background: tuple[float, float, float]) -> dict:
    """One renderer of each family (and 3DGS through both compositing paths) over `background`."""
    nerf = random_nerf(list(background))   # type: ignore[arg-type]
    return {"3dgs": GaussianRenderer(random_gaussians(), background),
            "3dgs-reference": GaussianRenderer(random_gaussians(), background, compositor="reference"),
            "2dgs": SurfelRenderer(random_surfels(60, seed=2), background),
            "nerf": NeRFRenderer(nerf)}


def masks(units: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(7)
    keep = torch.rand(3, units, generator=gen) >= 0.3
    keep[0] = True                                   # the full model too
    return keep


def test_premultiplied_matches_a_float64_brute_force_per_pixel() -> None:
    model = random_gaussians()
    keep = masks(model.num_splats)
    for renderer in (GaussianRenderer(model, GREY), GaussianRenderer(model, GREY, compositor="reference")):
        image = renderer.prepare(CAMERA).render(keep, "premultiplied")                       # [3, H, W, 4]
        assert image.shape == (3, CAMERA.height, CAMERA.width, 4)
        for i in range(3):
            # The colour over black is the brute force's render on a black background.
            rgb, alpha, _ = render_reference(model.means, model.log_scales, model.quats, model.opacity_logits,
                                             model.sh, CAMERA.c2w.numpy(), CAMERA.fx, CAMERA.fy, CAMERA.cx,
                                             CAMERA.cy, CAMERA.width, CAMERA.height, (0.0, 0.0, 0.0),
                                             keep[i].numpy())
            expected = np.concatenate([np.clip(rgb, 0, 1), alpha[..., None]], -1)
            diff = np.abs(image[i].double().numpy() - expected)
            assert diff.mean() <= 1e-4 and diff.max() <= 1e-3
        assert float(image[0, ..., 3].max()) > 0.5 and float(image[0, ..., 3].min()) < 0.01   # object and empty


@pytest.mark.parametrize("family", ["3dgs", "3dgs-reference", "2dgs", "nerf"])
def test_composited_is_premultiplied_plus_the_background_behind_alpha(family: str) -> None:
    renderer = renderers(GREY)[family]
    keep = masks(renderer.num_units)
    composited = renderer.render(CAMERA, keep, "composited")
    premultiplied = renderer.prepare(CAMERA).render(keep, "premultiplied")
    color, alpha = premultiplied[..., :3].double(), premultiplied[..., 3:].double()
    expected = (color + (1 - alpha) * torch.tensor(GREY, dtype=torch.float64)).clamp(0, 1)
    assert (composited.double() - expected).abs().max() <= 1e-6
    assert 0.05 < float(alpha.mean()) < 0.95          # both the model and the background are in view
    # The default is the paper's: the composited image.
    assert torch.equal(renderer.render(CAMERA, keep), composited)


@pytest.mark.parametrize("family", ["3dgs", "3dgs-reference", "2dgs", "nerf"])
def test_premultiplied_does_not_see_the_background(family: str) -> None:
    over = {colour: renderers(colour)[family] for colour in ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0), GREY)}
    keep = masks(over[GREY].num_units)
    images = {colour: r.render(CAMERA, keep, "premultiplied") for colour, r in over.items()}
    composited = {colour: r.render(CAMERA, keep, "composited") for colour, r in over.items()}
    assert all(torch.equal(image, images[GREY]) for image in images.values())
    assert not torch.equal(composited[(1.0, 1.0, 1.0)], composited[(0.0, 0.0, 0.0)])


def test_an_unknown_signal_names_the_field() -> None:
    renderer = renderers(GREY)["3dgs"]
    with pytest.raises(InputError) as info:
        renderer.render(CAMERA, None, "straight")
    assert info.value.field == "signal" and "premultiplied" in info.value.reason
