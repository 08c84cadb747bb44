"""The fused (compiled) 3DGS path against its pure-torch twin and the float64 brute force.

Three levels: the fused compositor on the SAME fragments as the reference compositor (its
values and its gradients); the compiled projection against the torch projection; whole
renders of `GaussianRenderer` (prepared `SplatView`, fused) against the pure-torch renderer,
extremes included, and the gradients of a whole render with respect to the model.
"""

from __future__ import annotations

import math
import threading

import pytest
import torch

from phd_core.renderers.composite import COMPOSITORS
from phd_core.renderers.gs2d import rasterize_surfels
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.gs3d.kernels import project_splats
from phd_core.renderers.gs3d.render import DILATION, NEAR_PLANE, project, rasterize, splat_alpha
from phd_core.renderers.splats import fragments, intersect
from renderers.test_gaussian_render import assert_close, camera, random_scene, reference
from renderers.test_surfel_render import random_surfels

TOL = 1e-5


def masks(n: int, g: int, drop: float, seed: int) -> torch.Tensor:
    return torch.rand(n, g, generator=torch.Generator().manual_seed(seed)) >= drop


def renderers(model: GaussianModel, background=(1.0, 1.0, 1.0)):
    return (GaussianRenderer(model, background, compositor="fused"),
            GaussianRenderer(model, background, compositor="reference"))


def assert_twins(model: GaussianModel, cam, keep) -> torch.Tensor:
    fused, pure = renderers(model)
    a, b = fused.render_full(cam, keep), pure.render_full(cam, keep)
    for name in ("rgb", "alpha", "depth"):
        diff = (getattr(a, name) - getattr(b, name)).abs().max().item()
        assert diff <= TOL, f"{name}: fused and pure torch differ by {diff:.3g}"
    return a.rgb


@pytest.mark.parametrize("tile", [1, 4, 16])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_compositor_matches_reference_on_the_same_fragments(tile: int, seed: int) -> None:
    model = random_scene(120, 1, seed=seed)
    cam = camera(37, 23)
    proj, _, _ = project(model, cam)
    pairs = intersect(proj.means2d, proj.extents, cam.width, cam.height, tile)
    frags = fragments(splat_alpha(proj, pairs, tile), pairs)
    splat = pairs.splat[frags.pair]
    unit = proj.ids[splat]                                               # [E] the splat of each entry
    values = torch.cat([proj.colors.float(), proj.depths.float()[:, None]], dim=-1)[splat]
    num_pixels = pairs.tiles_x * pairs.tiles_y * tile * tile
    units = model.num_splats
    for keep in (None, masks(7, units, 0.4, seed), torch.zeros(2, units, dtype=torch.bool)):
        ref_v, ref_a = COMPOSITORS["reference"](frags, values, keep, unit, num_pixels)
        fus_v, fus_a = COMPOSITORS["fused"](frags, values, keep, unit, num_pixels)
        assert fus_v.shape == ref_v.shape and fus_a.shape == ref_a.shape
        assert (fus_v - ref_v).abs().max() <= TOL and (fus_a - ref_a).abs().max() <= TOL
    assert ref_a.max() == 0 and fus_a.max() == 0                # the all-dropped batch
    full_a = COMPOSITORS["fused"](frags, values, None, unit, num_pixels)[1]
    assert full_a.max() > 0.9, "the scene must cover pixels for the comparison to mean anything"


def assert_same_gradients(ours: list[torch.Tensor], theirs: list[torch.Tensor], names: list[str]) -> None:
    for name, a, b in zip(names, ours, theirs):
        scale = b.abs().max().item()
        diff = (a.double() - b.double()).abs().max().item()
        assert diff <= 1e-4 * scale + 1e-6, f"d/d{name}: fused and reference differ by {diff:.3g} (scale {scale:.3g})"


@pytest.mark.parametrize("tile", [1, 4])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_compositor_gradients_match_the_reference(tile: int, seed: int) -> None:
    """d(accumulated values, alpha)/d(alpha, values) of the compiled backward against torch's
    autograd through the reference, for any keep-masks; opaque splats make pixels stop early."""
    model = random_scene(120, 1, seed=seed)
    model.opacity_logits[::4] = 30.0
    cam = camera(37, 23)
    proj, _, _ = project(model, cam)
    pairs = intersect(proj.means2d, proj.extents, cam.width, cam.height, tile)
    frags = fragments(splat_alpha(proj, pairs, tile), pairs)
    splat = pairs.splat[frags.pair]
    unit = proj.ids[splat]
    values = torch.cat([proj.colors.float(), proj.depths.float()[:, None]], dim=-1)[splat].detach()
    num_pixels = pairs.tiles_x * pairs.tiles_y * tile * tile
    gen = torch.Generator().manual_seed(seed)
    for keep in (None, masks(5, model.num_splats, 0.4, seed)):
        n = 1 if keep is None else len(keep)
        grad_v, grad_a = torch.randn(n, num_pixels, 4, generator=gen), torch.randn(n, num_pixels, generator=gen)
        grads = []
        for name in ("fused", "reference"):
            alpha, vals = frags.alpha.detach().clone().requires_grad_(), values.clone().requires_grad_()
            acc_v, acc_a = COMPOSITORS[name](type(frags)(**{**vars(frags), "alpha": alpha}), vals, keep, unit,
                                             num_pixels)
            grads.append(torch.autograd.grad((acc_v * grad_v).sum() + (acc_a * grad_a).sum(), (alpha, vals)))
        assert_same_gradients(list(grads[0]), list(grads[1]), ["alpha", "values"])
        assert grads[0][0].abs().max() > 0


def render_gradients(case: str, compositor: str) -> list[torch.Tensor]:
    """d(an image loss)/d(every model tensor, screen positions) of one render."""
    if case == "2dgs":
        model = random_surfels(40, 1, seed=31)
    else:
        model = random_scene(60, 2, seed=30)
        if case == "3dgs opaque":
            model.opacity_logits[:] = 30.0
    params = list(model.tensors())                   # in field order: the names below
    for p in params:
        p.requires_grad_(True)
    if case == "2dgs":      # colour, depth, normals and the depth distortion: 8 channels and alpha
        out = rasterize_surfels(model, camera(24, 18), torch.ones(3), compositor=compositor, geometry=True)
        extra = out.distortion.mean() + out.normal.sum() * 1e-3
    else:
        out = rasterize(model, camera(24, 18), torch.ones(3), compositor=compositor)
        extra = out.depth.mean() * 1e-2
    out.means2d.retain_grad()
    ((out.rgb - 0.3).square().mean() + extra).backward()
    return [p.grad for p in params] + [out.means2d.grad]


@pytest.mark.parametrize("case", ["3dgs", "3dgs opaque", "2dgs"])
def test_a_render_has_the_same_gradients_with_either_compositor(case: str) -> None:
    """What training sees: the gradient of an image loss with respect to every model tensor
    and to the screen positions (densification's statistic)."""
    fused, pure = render_gradients(case, "fused"), render_gradients(case, "reference")
    assert_same_gradients(fused, pure, ["means", "log_scales", "quats", "opacity_logits", "sh", "means2d"])
    assert all(g.abs().sum() > 0 for g in fused)


def test_fused_stops_each_mask_when_transmittance_is_spent() -> None:
    """Opaque splats stacked on one pixel: the full model stops early, a mask that drops the
    front ones reaches the back ones; both as the reference does."""
    g = 12
    model = GaussianModel(means=torch.stack([torch.zeros(g), torch.linspace(-0.5, 0.5, g), torch.zeros(g)], -1),
                          log_scales=torch.full((g, 3), -1.0), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(g, 1),
                          opacity_logits=torch.full((g,), 30.0), sh=torch.rand(g, 1, 3) * 2 - 1)
    keep = torch.ones(3, g, dtype=torch.bool)
    keep[1, :6] = False                                          # the front half dropped (camera at y = -3)
    keep[2, ::2] = False
    rgb = assert_twins(model, camera(), keep)
    assert (rgb[0] - rgb[1]).abs().max() > 0.05


def test_compiled_projection_matches_torch() -> None:
    model = random_scene(200, 0, seed=3, spread=2.5)
    model.log_scales[:5] = math.log(1e-6)
    model.log_scales[5:10] = math.log(1e3)
    model.opacity_logits[10:15] = -30.0
    cam = camera(40, 30)
    proj, means2d_t, visible_t = project(model, cam, NEAR_PLANE)
    means2d, conics, opacities, extents, depths, visible = project_splats(
        model.means, model.quats, model.log_scales, model.opacity_logits, cam, NEAR_PLANE, DILATION)
    assert torch.equal(visible, visible_t) and 0 < int(visible.sum()) < 200
    assert torch.allclose(means2d, means2d_t, rtol=1e-12, atol=1e-9)
    ids = proj.ids
    for ours, theirs in ((conics[ids], proj.conics), (opacities[ids], proj.opacities),
                         (extents[ids], proj.extents), (depths[ids], proj.depths)):
        assert torch.allclose(ours, theirs, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 3])
def test_fused_render_matches_pure_torch_and_brute_force(degree: int) -> None:
    model = random_scene(60, degree, seed=10 + degree)
    cam = camera()
    keep = masks(6, 60, 0.3, degree)
    rgb = assert_twins(model, cam, keep)
    for n in (0, 3):
        assert_close(rgb[n], reference(model, cam, keep[n].numpy())[0])


@pytest.mark.parametrize("case", ["tiny", "huge", "transparent", "opaque", "one_splat", "mixed"])
def test_fused_render_extremes(case: str) -> None:
    model = random_scene(1 if case == "one_splat" else 50, 1, seed=20)
    if case == "tiny":
        model.log_scales[:] = math.log(1e-6)
    elif case == "huge":
        model.log_scales[:] = math.log(1e3)
    elif case == "transparent":
        model.opacity_logits[:] = torch.linspace(-8.0, -5.0, 50)    # opacity ~ 1/255 and below
    elif case == "opaque":
        model.opacity_logits[:] = 30.0
    elif case == "mixed":
        model.log_scales[::3] = math.log(1e-4)
        model.log_scales[1::3] = math.log(5.0)
        model.opacity_logits[::2] = 12.0
    if case == "one_splat":
        model.means[:] = 0.0
        model.log_scales[:] = -1.5
    keep = masks(5, model.num_splats, 0.5, 1)
    rgb = assert_twins(model, camera(), keep)
    assert torch.isfinite(rgb).all()


def test_all_masks_dropping_everything_and_empty_views_give_the_background() -> None:
    model = random_scene(40, 1, seed=4)
    background = (0.2, 0.5, 0.9)
    fused, _ = renderers(model, background)
    bg = torch.tensor(background)
    out = fused.render_full(camera(), torch.zeros(3, 40, dtype=torch.bool))
    assert torch.allclose(out.rgb, bg.expand_as(out.rgb)) and torch.equal(out.alpha, torch.zeros_like(out.alpha))
    away = camera(eye=(0.0, 3.0, 0.0))
    away = type(away)(c2w=away.c2w.clone(), fx=away.fx, fy=away.fy, cx=away.cx + 1e4, cy=away.cy,
                      width=away.width, height=away.height)              # principal point far off: nothing on screen
    empty = fused.render_full(away, masks(2, 40, 0.2, 0))
    assert torch.allclose(empty.rgb, bg.expand_as(empty.rgb)) and not empty.visible.any()
    none = GaussianRenderer(random_scene(0, 0, seed=0), background).render(camera())
    assert torch.allclose(none, bg.expand_as(none))


def test_a_prepared_view_renders_like_the_renderer_for_any_batch() -> None:
    model = random_scene(50, 2, seed=6)
    fused, _ = renderers(model)
    cam = camera()
    view = fused.prepare(cam)
    assert view.camera is cam and view.nbytes > 0
    for keep in (None, masks(1, 50, 0.5, 2), masks(9, 50, 0.2, 3)):
        assert torch.equal(view.render(keep), fused.render(cam, keep))


def test_threads_rendering_at_once_get_the_serial_results() -> None:
    """The service renders on several worker threads; compiled launches take turns."""
    model = random_scene(80, 1, seed=7)
    fused, _ = renderers(model)
    cams = [camera(eye=(0.3 * i, -3.0, 1.0)) for i in range(4)]
    keep = masks(8, 80, 0.3, 4)
    serial = [fused.render(c, keep) for c in cams]
    results: dict[int, torch.Tensor] = {}
    threads = [threading.Thread(target=lambda i=i: results.__setitem__(i, fused.render(cams[i], keep)))
               for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(torch.equal(results[i], serial[i]) for i in range(4))
