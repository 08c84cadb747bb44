"""The 2DGS rasteriser against an independent float64 per-pixel renderer (ray-plane
intersection in world space), on random scenes with edge-on, degenerate and near-plane
surfels, plus keep-masks, gradients and the renderer protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference.surfels import render_surfels_reference

from phd_core.errors import InputError
from phd_core.renderers.gs2d import SurfelModel, SurfelRenderer, rasterize_surfels
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.scene import Camera, look_at
from support.calls import count_calls

WHITE = torch.ones(3)
EYE = (0.3, -3.0, 1.0)


def random_surfels(g: int, degree: int, seed: int, spread: float = 0.8) -> SurfelModel:
    gen = torch.Generator().manual_seed(seed)
    return SurfelModel(
        means=(torch.rand(g, 3, generator=gen) * 2 - 1) * spread,
        log_scales=torch.rand(g, 2, generator=gen) * 1.5 - 3.0,
        quats=torch.randn(g, 4, generator=gen),
        opacity_logits=torch.randn(g, generator=gen) * 2,
        sh=torch.randn(g, (degree + 1) ** 2, 3, generator=gen) * 0.4,
    )


def camera(width: int = 20, height: int = 14, eye=EYE, fov: float = 0.7) -> Camera:
    return look_at(eye, (0, 0, 0), width=width, height=height, fov_x=fov)


def quaternion(rot: np.ndarray) -> torch.Tensor:
    """wxyz quaternion of a rotation matrix (columns t_u, t_v, normal)."""
    w = math.sqrt(max(0.0, 1 + np.trace(rot))) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + rot[0, 0] - rot[1, 1] - rot[2, 2])) / 2, rot[2, 1] - rot[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - rot[0, 0] + rot[1, 1] - rot[2, 2])) / 2, rot[0, 2] - rot[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - rot[0, 0] - rot[1, 1] + rot[2, 2])) / 2, rot[1, 0] - rot[0, 1])
    return torch.tensor([w, x, y, z], dtype=torch.float32)


def edge_on(model: SurfelModel, i: int, eye=EYE, tilt: float = 0.0) -> None:
    """Turn surfel i so that its plane contains the eye (tilted by `tilt` radians off it)."""
    view = model.means[i].double().numpy() - np.asarray(eye)
    view /= np.linalg.norm(view)
    side = np.cross(view, [0.3, 0.2, 1.0])
    side /= np.linalg.norm(side)
    normal = math.cos(tilt) * side + math.sin(tilt) * view
    t_u = view - (view @ normal) * normal
    t_u /= np.linalg.norm(t_u)
    model.quats[i] = quaternion(np.stack([t_u, np.cross(normal, t_u), normal], axis=1))
    assert torch.isfinite(model.quats[i]).all()


def reference(model: SurfelModel, cam: Camera, keep=None, background=(1.0, 1.0, 1.0)):
    return render_surfels_reference(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                                    cam.c2w.numpy(), cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                                    background, keep)


def psnr(ours: torch.Tensor, ref: np.ndarray) -> float:
    mse = float(((ours.double().numpy() - ref) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def assert_matches(model: SurfelModel, cam: Camera, keep=None, min_alpha: float = 0.5) -> None:
    """RGB at PSNR >= 50 dB, and alpha, depth, normals, distortion within 1e-3 of the reference."""
    out = rasterize_surfels(model, cam, WHITE, None if keep is None else torch.as_tensor(keep)[None],
                            geometry=True)
    rgb, alpha, depth, normal, distortion = reference(model, cam, keep)
    assert psnr(out.rgb[0], rgb) >= 50.0, f"PSNR {psnr(out.rgb[0], rgb):.1f} dB"
    for name, ours, ref in [("alpha", out.alpha, alpha), ("depth", out.depth, depth),
                            ("normal", out.normal, normal), ("distortion", out.distortion, distortion)]:
        diff = np.abs(ours[0].double().numpy() - ref)
        assert diff.max() <= 1e-3, f"{name}: max abs diff {diff.max():.3g}"
    assert alpha.max() > min_alpha, "the scene must cover pixels for the test to mean anything"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("tile", [1, 4, 16])
def test_matches_brute_force(seed: int, tile: int) -> None:
    model = random_surfels(40, seed % 4, seed=seed)
    cam = camera()
    out = rasterize_surfels(model, cam, WHITE, tile=tile)
    rgb, alpha, depth, _, _ = reference(model, cam)
    assert psnr(out.rgb[0], rgb) >= 50.0
    assert np.abs(out.alpha[0].numpy() - alpha).max() <= 1e-3 and np.abs(out.depth[0].numpy() - depth).max() <= 1e-3
    if tile == 4:
        assert_matches(model, cam)


@pytest.mark.parametrize("tilt", [0.0, 1e-4, 1e-2])
def test_edge_on_surfels_match_and_fall_back_to_the_low_pass(tilt: float) -> None:
    model = random_surfels(30, 1, seed=3)
    model.log_scales[:10] = -1.0                      # large, so seen edge-on they are long lines
    for i in range(10):
        edge_on(model, i, tilt=tilt)
    cam = camera()
    assert_matches(model, cam)
    # A lone edge-on surfel still shows at its centre through the low-pass filter.
    alone = model.subset(torch.tensor([0]))
    alone.opacity_logits[:] = 4.0
    out = rasterize_surfels(alone, cam, WHITE)
    centre = cam.project(alone.means.double())[0][0]
    assert out.alpha[0, int(centre[1]), int(centre[0])] > 0.05


def test_degenerate_surfels_match() -> None:
    model = random_surfels(30, 2, seed=4)
    model.log_scales[0] = -30.0                       # a point: only the low-pass shows it
    model.log_scales[1, 0] = -30.0                    # a line
    model.log_scales[2] = 3.0                         # huge: crosses the near plane, box is the screen
    model.quats[3] = 0.0                              # zero quaternion = identity rotation
    model.means[4] = torch.tensor([0.3, -2.9, 1.0])   # centre nearer than the near plane: culled
    model.means[5] = torch.tensor([0.0, -3.6, 1.0])   # behind the eye
    model.opacity_logits[6] = -30.0                   # transparent
    cam = camera()
    assert_matches(model, cam)
    out = rasterize_surfels(model, cam, WHITE)
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert not out.visible[4] and not out.visible[5] and not out.visible[6] and out.visible[2]


def test_a_surfel_crossing_the_near_plane_matches() -> None:
    model = random_surfels(20, 0, seed=5)
    model.means[0] = torch.tensor([0.2, -2.5, 0.9])   # 0.5 in front of the eye, 2 units wide
    model.log_scales[0] = math.log(1.0)
    model.opacity_logits[0] = 2.0
    assert_matches(model, camera())


def test_keep_masks_match_brute_force_and_single_renders() -> None:
    model = random_surfels(40, 1, seed=6)
    edge_on(model, 0)
    cam = camera()
    keep = torch.rand(4, model.num_splats, generator=torch.Generator().manual_seed(0)) >= 0.4
    batched = rasterize_surfels(model, cam, WHITE, keep).rgb
    assert batched.shape == (4, cam.height, cam.width, 3)
    for n in range(4):
        assert psnr(batched[n], reference(model, cam, keep[n].numpy())[0]) >= 50.0
        single = rasterize_surfels(model.subset(keep[n]), cam, WHITE).rgb[0]
        assert (single - batched[n]).abs().max() < 1e-5
    assert (batched[0] - batched[1]).abs().max() > 1e-3, "different masks must give different images"


def test_a_fronto_parallel_surfel_has_the_analytic_footprint_depth_and_normal() -> None:
    cam = look_at((0, -4, 0), (0, 0, 0), width=33, height=33, fov_x=0.6)
    # Tangents along world x and z, normal along y: facing the camera, at depth 4.
    model = SurfelModel(means=torch.zeros(1, 3), log_scales=torch.log(torch.tensor([[0.3, 0.15]])),
                        quats=quaternion(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]))[None],
                        opacity_logits=torch.tensor([3.0]), sh=torch.zeros(1, 1, 3))
    out = rasterize_surfels(model, cam, WHITE, geometry=True)
    opacity = 1 / (1 + math.exp(-3.0))
    # Pixel (16, 16) is the centre; pixel (16 + k, 16) sits k / fx * 4 / 0.3 sigmas away along u.
    for k in (0, 3, 6):
        u = k / cam.fx * 4.0 / 0.3
        expected = min(0.99, opacity * max(math.exp(-0.5 * u * u), math.exp(-k * k)))
        assert out.alpha[0, 16, 16 + k].item() == pytest.approx(expected if expected >= 1 / 255 else 0.0, abs=1e-5)
    covered = out.alpha[0] > 0
    assert torch.allclose(out.depth[0][covered] / out.alpha[0][covered], torch.tensor(4.0), atol=1e-5)
    normal = out.normal[0][covered] / out.alpha[0][covered][:, None]
    assert torch.allclose(normal, torch.tensor([0.0, 0.0, -1.0]), atol=1e-5)   # towards the camera (OpenCV)
    assert out.distortion[0].abs().max() < 1e-6                                  # one surfel: no spread


def test_masks_share_one_projection(monkeypatch) -> None:
    import phd_core.renderers.gs2d.render as sr
    calls = {"project": 0, "intersect": 0, "splat_alpha": 0, "fragments": 0}
    for name in calls:
        original = getattr(sr, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)
        monkeypatch.setattr(sr, name, counted)
    sr.rasterize_surfels(random_surfels(30, 0, seed=7), camera(), WHITE, torch.rand(16, 30) > 0.5)
    assert calls == {"project": 1, "intersect": 1, "splat_alpha": 1, "fragments": 1}


def test_gradients_flow_to_every_parameter() -> None:
    model = random_surfels(20, 1, seed=8)
    edge_on(model, 0)
    params = [model.means, model.log_scales, model.quats, model.opacity_logits, model.sh]
    for p in params:
        p.requires_grad_(True)
    out = rasterize_surfels(model, camera(), WHITE, geometry=True)
    out.means2d.retain_grad()
    ((out.rgb - 0.3).square().mean() + out.distortion.mean() + out.normal.sum() * 1e-3).backward()
    for p in params:
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    assert out.means2d.grad[out.visible].abs().sum() > 0


def test_every_surfel_masked_or_none_gives_background() -> None:
    bg = torch.tensor([0.2, 0.5, 0.9])
    out = rasterize_surfels(random_surfels(30, 1, seed=9), camera(), bg, torch.zeros(2, 30, dtype=torch.bool))
    assert torch.allclose(out.rgb, bg.expand_as(out.rgb)) and torch.equal(out.alpha, torch.zeros_like(out.alpha))
    empty = rasterize_surfels(random_surfels(0, 0, seed=0), camera(), bg)
    assert empty.rgb.shape == (1, 14, 20, 3) and torch.allclose(empty.rgb, bg.expand_as(empty.rgb))


def test_renderer_protocol_and_model_kinds() -> None:
    from phd_core.renderers import Renderer
    renderer = SurfelRenderer(random_surfels(25, 2, seed=10))
    assert isinstance(renderer, Renderer) and renderer.num_units == 25
    images = renderer.render(camera(), torch.ones(3, 25, dtype=torch.bool))
    assert images.shape == (3, 14, 20, 3) and images.dtype == torch.float32
    info = renderer.describe()
    assert info["kind"] == "2dgs" and info["sh_degree"] == 2
    gaussians = GaussianModel(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, 4), torch.zeros(2),
                              torch.zeros(2, 1, 3))
    with pytest.raises(InputError, match="SurfelModel"):
        SurfelRenderer(gaussians)
    with pytest.raises(InputError, match="GaussianModel"):
        GaussianRenderer(random_surfels(3, 0, seed=0))
    with pytest.raises(InputError, match=r"log_scales.*\[G, 2\]"):
        SurfelModel(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, 4), torch.zeros(2),
                    torch.zeros(2, 1, 3)).validate()


@pytest.mark.parametrize("compositor", ["fused", "reference"])
def test_a_prepared_view_renders_what_the_rasteriser_does_from_one_projection(compositor: str, monkeypatch) -> None:
    model = random_surfels(40, 1, seed=11)
    edge_on(model, 0)
    cam = camera()
    renderer = SurfelRenderer(model, compositor=compositor)
    keep = torch.rand(6, model.num_splats, generator=torch.Generator().manual_seed(1)) >= 0.4
    expected = rasterize_surfels(model, cam, WHITE, keep, compositor=compositor)     # a fresh projection per call
    full = renderer.render(cam)
    import phd_core.renderers.gs2d.render as surfel_render
    calls = count_calls(monkeypatch, surfel_render, "project")         # stage 1, wherever the renderer makes it
    view = renderer.prepare(cam)
    # Batches of masks over one view: the same images, bit for bit, as one rasteriser call.
    color = torch.cat([view.render(keep[:2], "premultiplied"), view.render(keep[2:], "premultiplied")])
    assert torch.equal(color[..., :3], expected.color) and torch.equal(color[..., 3], expected.alpha)
    assert torch.equal(view.render(keep[3:4]), expected.rgb[3:4])
    assert torch.equal(view.render(None), full)
    renderer.visibility(view)
    assert calls["calls"] == 1, "the renders and the visibility pass share the view's projection"
    for n in (0, 5):                                                    # and the float64 brute force's
        rgb = color[n, ..., :3] + (1 - color[n, ..., 3:]) * WHITE
        assert psnr(rgb, reference(model, cam, keep[n].numpy())[0]) >= 50.0
    assert (color[0] - color[1]).abs().max() > 1e-3, "different masks must give different images"
    assert view.nbytes > 0


def test_the_visibility_of_a_prepared_view_is_the_pass_of_a_fresh_projection() -> None:
    from phd_core.renderers import CameraView
    model = random_surfels(60, 1, seed=12)
    cam = camera(24, 18)
    renderer = SurfelRenderer(model)
    values = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(2))
    prepared = renderer.visibility(renderer.prepare(cam), values)
    fresh = renderer.visibility(CameraView(renderer, cam), values)        # projects, lists and rasterises anew
    assert len(prepared.elements) >= 10
    for name in ("elements", "points", "weight", "footprint", "valued"):
        assert torch.equal(getattr(prepared, name), getattr(fresh, name)), name
    assert (prepared.empty, prepared.in_box) == (fresh.empty, fresh.in_box)
    # 18 rows are not a whole number of 4-pixel tiles: the weights still add up to the image's
    # alpha (an independent route: the compositor), with nothing counted past the last row.
    assert cam.height % renderer.tile != 0
    assert float(prepared.weight.sum()) == pytest.approx(float(renderer.render_full(cam).alpha.sum()), rel=1e-5)
