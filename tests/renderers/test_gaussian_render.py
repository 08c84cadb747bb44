"""The 3DGS rasteriser against an independent float64 per-pixel renderer, plus extremes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference.gaussians import render_reference

from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer, rasterize
from phd_core.scene import Camera, look_at

WHITE = torch.ones(3)


def random_scene(g: int, degree: int, seed: int, spread: float = 0.8) -> GaussianModel:
    gen = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianModel(
        means=(torch.rand(g, 3, generator=gen) * 2 - 1) * spread,
        log_scales=torch.rand(g, 3, generator=gen) * 1.5 - 3.5,
        quats=torch.randn(g, 4, generator=gen),
        opacity_logits=torch.randn(g, generator=gen) * 2,
        sh=torch.randn(g, k, 3, generator=gen) * 0.4,
    )


def camera(width: int = 20, height: int = 14, eye=(0.3, -3.0, 1.0), fov: float = 0.7) -> Camera:
    return look_at(eye, (0, 0, 0), width=width, height=height, fov_x=fov)


def reference(model: GaussianModel, cam: Camera, keep=None, background=(1.0, 1.0, 1.0)):
    return render_reference(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                            cam.c2w.numpy(), cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                            background, keep)


def assert_close(ours: torch.Tensor, ref: np.ndarray) -> None:
    diff = (ours.double().numpy() - ref).__abs__()
    assert diff.mean() <= 1e-4, f"mean abs diff {diff.mean():.3g}"
    assert diff.max() <= 1e-3, f"max abs diff {diff.max():.3g}"


@pytest.mark.parametrize("degree", [0, 1, 3])
@pytest.mark.parametrize("tile", [1, 4, 16])
def test_matches_brute_force(degree: int, tile: int) -> None:
    model = random_scene(40, degree, seed=degree)
    cam = camera()
    out = rasterize(model, cam, WHITE, tile=tile)
    rgb, alpha, depth = reference(model, cam)
    assert_close(out.rgb[0], rgb)
    assert_close(out.alpha[0], alpha)
    assert_close(out.depth[0], depth)
    assert alpha.max() > 0.5, "scene must actually cover pixels for the test to mean anything"


def test_view_dependent_colour_changes_with_viewpoint() -> None:
    model = random_scene(30, 3, seed=5)
    for eye in [(0.3, -3.0, 1.0), (3.0, 0.2, -0.5)]:
        cam = camera(eye=eye)
        assert_close(rasterize(model, cam, WHITE).rgb[0], reference(model, cam)[0])
    flat = GaussianModel(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh[:, :1])
    view = camera()
    assert (rasterize(model, view, WHITE).rgb - rasterize(flat, view, WHITE).rgb).abs().max() > 1e-2


def test_partly_outside_and_behind_camera() -> None:
    model = random_scene(30, 2, seed=7, spread=2.5)
    model.means[0] = torch.tensor([0.0, -3.5, 1.0])     # behind the eye at y = -3
    model.means[1] = torch.tensor([0.3, -3.0, 1.0])     # at the camera centre
    model.means[2] = torch.tensor([1.2, 0.0, 0.0])      # near the image edge
    model.log_scales[2] = torch.tensor([-0.5, -0.5, -0.5])
    cam = camera()
    out = rasterize(model, cam, WHITE)
    assert_close(out.rgb[0], reference(model, cam)[0])
    assert not out.visible[0] and not out.visible[1]


def test_keep_masks_match_brute_force_and_single_renders() -> None:
    model = random_scene(40, 1, seed=11)
    cam = camera()
    gen = torch.Generator().manual_seed(0)
    keep = torch.rand(5, model.num_splats, generator=gen) >= 0.4
    batched = rasterize(model, cam, WHITE, keep).rgb
    assert batched.shape == (5, cam.height, cam.width, 3)
    for n in range(5):
        assert_close(batched[n], reference(model, cam, keep[n].numpy())[0])
        single = rasterize(model.subset(keep[n]), cam, WHITE).rgb[0]
        assert (single - batched[n]).abs().max() < 1e-5
    assert (batched[0] - batched[1]).abs().max() > 1e-3, "different masks must give different images"


def test_all_ones_mask_equals_unmasked_render() -> None:
    model = random_scene(30, 1, seed=2)
    cam = camera()
    full = rasterize(model, cam, WHITE).rgb
    ones = rasterize(model, cam, WHITE, torch.ones(3, model.num_splats, dtype=torch.bool)).rgb
    assert torch.equal(ones, full.expand_as(ones))


def test_masks_share_one_projection(monkeypatch) -> None:
    import phd_core.renderers.gs3d.render as gr
    calls = {"project": 0, "intersect": 0, "splat_alpha": 0, "fragments": 0}
    for name in calls:
        original = getattr(gr, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)
        monkeypatch.setattr(gr, name, counted)
    model = random_scene(30, 0, seed=3)
    gr.rasterize(model, camera(), WHITE, torch.rand(16, 30) > 0.5)
    assert calls == {"project": 1, "intersect": 1, "splat_alpha": 1, "fragments": 1}


def test_every_splat_masked_gives_background() -> None:
    model = random_scene(30, 1, seed=4)
    bg = torch.tensor([0.2, 0.5, 0.9])
    out = rasterize(model, camera(), bg, torch.zeros(2, 30, dtype=torch.bool))
    assert torch.isfinite(out.rgb).all()
    assert torch.allclose(out.rgb, bg.expand_as(out.rgb))
    assert torch.equal(out.alpha, torch.zeros_like(out.alpha))


def test_zero_splats_gives_background() -> None:
    model = random_scene(0, 0, seed=0)
    bg = torch.tensor([0.0, 0.0, 0.0])
    out = rasterize(model, camera(), bg)
    assert out.rgb.shape == (1, 14, 20, 3) and torch.equal(out.rgb, torch.zeros_like(out.rgb))


@pytest.mark.parametrize("log_scale", [math.log(1e-6), math.log(1e3)])
def test_extreme_scales_are_finite_and_correct(log_scale: float) -> None:
    model = random_scene(10, 1, seed=8)
    model.log_scales[:] = log_scale
    cam = camera()
    out = rasterize(model, cam, WHITE)
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert_close(out.rgb[0], reference(model, cam)[0])


@pytest.mark.parametrize("logit", [-30.0, 30.0])
def test_extreme_opacities(logit: float) -> None:
    model = random_scene(10, 0, seed=9)
    model.opacity_logits[:] = logit
    cam = camera()
    out = rasterize(model, cam, WHITE)
    assert torch.isfinite(out.rgb).all()
    assert_close(out.rgb[0], reference(model, cam)[0])
    if logit < 0:
        assert torch.equal(out.rgb, torch.ones_like(out.rgb))


def test_zero_quaternion_falls_back_to_identity_rotation() -> None:
    model = random_scene(10, 0, seed=10)
    model.quats[:3] = 0.0
    identity = GaussianModel(model.means, model.log_scales, model.quats.clone(), model.opacity_logits, model.sh)
    identity.quats[:3] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    cam = camera()
    out = rasterize(model, cam, WHITE).rgb
    assert torch.isfinite(out).all()
    assert torch.equal(out, rasterize(identity, cam, WHITE).rgb)


@pytest.mark.parametrize("size", [(1, 1), (640, 480)])
def test_extreme_image_sizes(size: tuple[int, int]) -> None:
    model = random_scene(50, 1, seed=12)
    cam = camera(*size)
    out = rasterize(model, cam, WHITE)
    assert out.rgb.shape == (1, size[1], size[0], 3)
    assert torch.isfinite(out.rgb).all()
    if size == (1, 1):
        assert_close(out.rgb[0], reference(model, cam)[0])


def test_gradients_flow_to_every_parameter() -> None:
    model = random_scene(20, 1, seed=13)
    params = [model.means, model.log_scales, model.quats, model.opacity_logits, model.sh]
    for p in params:
        p.requires_grad_(True)
    out = rasterize(model, camera(), WHITE)
    out.means2d.retain_grad()
    (out.rgb - 0.3).square().mean().backward()
    for p in params:
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    assert out.means2d.grad[out.visible].abs().sum() > 0


def test_renderer_protocol() -> None:
    from phd_core.renderers import Renderer
    renderer = GaussianRenderer(random_scene(25, 2, seed=14))
    assert isinstance(renderer, Renderer)
    assert renderer.num_units == 25
    images = renderer.render(camera(), torch.ones(4, 25, dtype=torch.bool))
    assert images.shape == (4, 14, 20, 3) and images.dtype == torch.float32
    info = renderer.describe()
    assert info["kind"] == "3dgs" and info["sh_degree"] == 2 and info["num_units"] == 25
    with pytest.raises(ValueError, match="keep"):
        renderer.render(camera(), torch.ones(4, 24, dtype=torch.bool))


def test_pixel_sums_backward_matches_finite_differences() -> None:
    from phd_core.renderers.composite.reference import PixelSums
    gen = torch.Generator().manual_seed(0)
    row = torch.tensor([0, 0, 0, 1, 2, 2, 3, 3, 3, 3])                  # 10 entries in 4 pixels
    row_ptr = torch.tensor([0, 3, 4, 6, 10])
    weight = torch.rand(10, 3, generator=gen, dtype=torch.float64, requires_grad=True)   # [E, N]
    values = torch.rand(10, 2, generator=gen, dtype=torch.float64, requires_grad=True)   # [E, C]
    assert torch.autograd.gradcheck(lambda w, v: PixelSums.apply(w, v, row, row_ptr), (weight, values))
    expected = torch.zeros(4, 3, 2, dtype=torch.float64).index_add_(0, row, weight[:, :, None] * values[:, None])
    assert torch.allclose(PixelSums.apply(weight, values, row, row_ptr), expected)
