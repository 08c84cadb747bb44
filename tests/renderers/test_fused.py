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
from renderers.test_gaussian_render import assert_close, camera, random_scene, reference
from renderers.test_surfel_render import random_surfels

from phd_core.renderers.composite import COMPOSITORS
from phd_core.renderers.gs2d import rasterize_surfels
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.gs3d.kernels import project_splats, splat_fragments, splat_values
from phd_core.renderers.gs3d.render import (
    DILATION,
    NEAR_PLANE,
    cut_lengths,
    prepare_view,
    project,
    rasterize,
    splat_alpha,
    splat_colors,
)
from phd_core.renderers.splats import ALPHA_MIN, fragments, intersect

TOL = 1e-5
WHITE = torch.ones(3)


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


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compiled_sh_colours_match_torch(degree: int) -> None:
    """The compiled SH stage of the visible splats against `splat_colors` (its pure-torch twin):
    every basis function alone and random mixtures, a splat at the camera centre, clamped colours."""
    cam = camera()
    k = (degree + 1) ** 2
    gen = torch.Generator().manual_seed(degree)
    dirs = torch.nn.functional.normalize(torch.randn(40, 3, generator=gen, dtype=torch.float64), dim=-1)
    means = torch.cat([cam.center + 2.0 * dirs, cam.center[None]]).float()      # the last one: no direction
    g = len(means)
    single = torch.eye(k).repeat_interleave(3, 0)[:, :, None].expand(-1, -1, 3)  # basis j alone, 3 splats each
    sh = torch.cat([single[:g], torch.randn(g, k, 3, generator=gen)])[:g].contiguous() * 1.5
    model = GaussianModel(means, torch.zeros(g, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(g, 1), torch.zeros(g), sh)
    ids = torch.randperm(g, generator=gen)[:g - 3]
    ids = torch.cat([ids[ids != g - 1], torch.tensor([g - 1])])
    depths = torch.rand(g, generator=gen, dtype=torch.float64) * 5
    values = splat_values(model.means, model.sh, ids, cam, depths)
    expected = splat_colors(model, ids, cam)
    assert (values[:, :3] - expected).abs().max() <= TOL
    assert (expected == 0).any() and (expected > 0.5).any()                     # clamped and bright ones
    assert torch.equal(values[:, 3], depths[ids].float())


def fragment_lists(row_ptr: torch.Tensor, alpha: torch.Tensor, splat: torch.Tensor, pixel: torch.Tensor) -> dict:
    """{pixel: [(splat, alpha), ...] front to back}, fragments within 1e-5 of ALPHA_MIN left out
    (float32 and float64 may decide those either way)."""
    out = {}
    for s, q in enumerate(pixel.tolist()):
        rows = [(int(splat[e]), float(alpha[e])) for e in range(int(row_ptr[s]), int(row_ptr[s + 1]))]
        rows = [r for r in rows if r[1] >= ALPHA_MIN + TOL]
        if rows:
            out[q] = rows
    return out


@pytest.mark.parametrize("tile", [1, 4, 16])
def test_compiled_fragments_match_torch(tile: int) -> None:
    """Stages 2-3 compiled against the torch stages: the same fragments of every pixel, in the
    same order; alpha at 1e-5 of the float64 formula (the torch stage evaluates it in float32,
    off by 2e-5 at tile 16)."""
    model = random_scene(150, 0, seed=5, spread=1.2)
    model.log_scales[:10] = math.log(1e-4)                                      # sub-pixel splats
    model.log_scales[10:20, 0] = 0.3                                            # long thin ones
    model.log_scales[10:20, 1:] = -4.0
    model.opacity_logits[20:30] = -5.3                                          # alpha about 1/255 at the centre
    cam = camera(37, 23)
    proj, _, _ = project(model, cam)
    pairs = intersect(proj.means2d, proj.extents, cam.width, cam.height, tile)
    frags = fragments(splat_alpha(proj, pairs, tile), pairs)
    expected = fragment_lists(frags.row_ptr, frags.alpha, pairs.splat[frags.pair], frags.pixel)
    q = torch.tensor(list(expected))
    t, p = q.div(tile * tile, rounding_mode="floor"), q % (tile * tile)
    x, y = (t % pairs.tiles_x) * tile + p % tile, (t // pairs.tiles_x) * tile + p // tile
    inside = ((x < cam.width) & (y < cam.height)).tolist()          # the torch stage also lists pixels past the edge
    expected = {q: rows for q, keep in zip(list(expected), inside) if keep for rows in [expected[q]]}
    row_ptr, alpha, index, _, _ = splat_fragments(proj.means2d, proj.conics, proj.opacities, proj.extents,
                                                 cam.width, cam.height, tile)
    ours = fragment_lists(row_ptr, alpha, index, torch.arange(len(row_ptr) - 1))
    assert ours.keys() == expected.keys() and len(ours) > 100
    for q, rows, x_, y_ in zip(expected, expected.values(), x[inside].tolist(), y[inside].tolist()):
        assert [v for v, _ in ours[q]] == [v for v, _ in rows], f"pixel {q}: other splats or order"
        for v, a in ours[q]:
            d = torch.tensor([x_ + 0.5, y_ + 0.5], dtype=torch.float64) - proj.means2d[v]
            con = proj.conics[v]
            power = -0.5 * (con[0] * d[0] ** 2 + con[2] * d[1] ** 2) - con[1] * d[0] * d[1]
            assert abs(a - min(0.99, float(proj.opacities[v] * power.exp()))) <= TOL


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


def deep_scene(seed: int) -> GaussianModel:
    """Opaque splats packed in front of the camera: most pixels are spent long before their last fragment."""
    model = random_scene(200, 1, seed=seed, spread=0.5)
    model.opacity_logits.add_(4.0)
    model.log_scales.add_(1.0)
    return model


@pytest.mark.parametrize("tile", [1, 4, 16])
@pytest.mark.parametrize("drop", [None, 0.0, 0.5, 1.0])
def test_a_cut_view_lists_the_prefix_its_torch_twin_names_and_renders_the_same(tile: int, drop: float | None) -> None:
    """The compiled cut (`kernels._cut_log_alpha`) against its twin (`render.cut_lengths`) on the
    complete lists: the same length at every pixel, the same splats and alphas bit for bit; and
    the cut view composites its masks to the complete view's images bit for bit."""
    model = deep_scene(seed=tile)
    cam = camera(37, 23)
    keep = None if drop is None else masks(6, model.num_splats, drop, seed=tile)
    full = prepare_view(model, cam, WHITE, tile=tile)
    cut = prepare_view(model, cam, WHITE, tile=tile, cut=True, keep=keep)
    splats = full.units[full.index.long()]                                     # [E] model splat of each fragment
    lengths = cut_lengths(full.row_ptr, full.alpha, splats, keep)
    assert torch.equal(cut.row_ptr.diff(), lengths)
    counts = full.row_ptr.diff()
    row = torch.repeat_interleave(torch.arange(len(counts)), counts)
    listed = torch.arange(len(full.alpha)) - full.row_ptr[:-1][row] < lengths[row]
    assert torch.equal(cut.units[cut.index.long()], splats[listed]) and torch.equal(cut.alpha, full.alpha[listed])
    if drop == 1.0:
        assert torch.equal(lengths, counts), "masks that keep nothing are never spent"
    elif drop in (None, 0.0):
        assert lengths.sum() < 0.6 * counts.sum(), "the scene must be deep enough for the cut to matter"
    for name in ("rgb", "alpha", "depth"):
        assert torch.equal(getattr(cut.render_full(keep), name), getattr(full.render_full(keep), name)), name


def test_an_unmasked_render_is_cut_and_agrees_with_the_twins_and_brute_force(monkeypatch) -> None:
    import phd_core.renderers.gs3d.render as gr
    cuts = []
    original = gr.prepare_view

    def spied(*args, **kwargs):
        cuts.append(kwargs.get("cut", False))
        return original(*args, **kwargs)
    monkeypatch.setattr(gr, "prepare_view", spied)
    model = deep_scene(seed=7)
    cam = camera()
    fused, pure = renderers(model)
    out = fused.render_full(cam)
    assert cuts == [True]
    assert_twins(model, cam, None)
    rgb, alpha, depth = reference(model, cam)
    assert_close(out.rgb[0], rgb)
    assert_close(out.alpha[0], alpha)
    assert_close(out.depth[0], depth)
    assert torch.equal(out.rgb, fused.prepare(cam).render_full(None).rgb)
    fused.render_full(cam, masks(3, model.num_splats, 0.5, seed=7))
    assert cuts[-1] is False, "masked renders list every fragment"


def test_a_cut_view_renders_only_its_masks_and_visibility_counts_hidden_fragments() -> None:
    model = deep_scene(seed=8)
    cam = camera()
    fused, _ = renderers(model)
    complete, cut = fused.prepare(cam), prepare_view(model, cam, WHITE, cut=True)
    with pytest.raises(ValueError, match="cut for its keep-masks"):
        cut.render(masks(2, model.num_splats, 0.5, seed=8))
    assert len(cut.alpha) < len(complete.alpha)
    for a, b in zip(fused.fragment_rows(cut)[:3], fused.fragment_rows(complete)[:3]):
        assert torch.equal(a, b)
    seen, expected = fused.visibility(cut), fused.visibility(complete)
    assert torch.equal(seen.elements, expected.elements) and torch.equal(seen.footprint, expected.footprint)
