"""Each family's RenderMemory bounds what its renders really build: the fragment bound holds
the fragments the rasterisers keep, the tile/splat pairs are the ones they list, and a 3DGS
prepared view keeps no more than `kept` says, from few splats per pixel to hundreds."""

from __future__ import annotations

import pytest
import torch

from phd_core.renderers import FAMILIES
from phd_core.renderers.gs2d import SurfelModel, SurfelRenderer
from phd_core.renderers.gs2d.render import project as project_surfels
from phd_core.renderers.gs2d.render import splat_alpha as surfel_alpha
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.gs3d.render import project, splat_alpha, splat_counts
from phd_core.renderers.protocol import MEMORY_PROBE_UNITS
from phd_core.renderers.splats import box_counts, intersect
from phd_core.scene import look_at


def cloud(model_type, count: int, scale: float, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return model_type(means=(torch.rand(count, 3, generator=g) - 0.5) * 1.2,
                      log_scales=torch.log(scale * (0.5 + torch.rand(count, model_type.scale_axes, generator=g))),
                      quats=torch.randn(count, 4, generator=g), opacity_logits=torch.rand(count, generator=g) * 4 - 1,
                      sh=torch.randn(count, 4, 3, generator=g) * 0.5)


CAMERA = look_at((0.4, -2.5, 0.9), (0, 0, 0), width=48, height=40, fov_x=0.8)


@pytest.mark.parametrize("count, scale", [(400, 0.004), (400, 0.08), (3000, 0.2)])
def test_gaussian_bounds_hold_the_view_prepare_builds(count, scale):
    renderer = GaussianRenderer(cloud(GaussianModel, count, scale))
    view = renderer.prepare(CAMERA)
    memory = FAMILIES["3dgs"].memory(renderer, CAMERA)
    visible, pairs, fragments = splat_counts(renderer, CAMERA)
    with torch.no_grad():
        proj, _, _ = project(renderer.model, CAMERA)
        listed = intersect(proj.means2d, proj.extents, CAMERA.width, CAMERA.height, renderer.tile)
        kept = int((splat_alpha(proj, listed, renderer.tile) > 0).sum())
    assert (visible, pairs) == (len(view.units), len(listed.tile))
    assert kept == len(view.alpha) <= fragments
    assert view.nbytes <= memory.kept <= memory.fixed
    assert memory.per_mask >= renderer.num_units             # each mask's flags by splat, at least


def test_gaussian_counts_do_not_depend_on_the_probe_chunks():
    renderer = GaussianRenderer(cloud(GaussianModel, MEMORY_PROBE_UNITS + 500, 0.01))
    with torch.no_grad():
        proj, _, _ = project(renderer.model, CAMERA)
    whole = (len(proj.ids), *box_counts(proj.means2d, proj.extents, CAMERA.width, CAMERA.height, renderer.tile))
    assert splat_counts(renderer, CAMERA) == whole


@pytest.mark.parametrize("count, scale", [(300, 0.004), (300, 0.1), (2000, 0.2)])
def test_surfel_bounds_hold_the_fragments_a_render_builds(count, scale):
    renderer = SurfelRenderer(cloud(SurfelModel, count, scale))
    with torch.no_grad():
        proj, _, _ = project_surfels(renderer.model, CAMERA)
        listed = intersect(proj.box_centres, proj.extents, CAMERA.width, CAMERA.height, renderer.tile)
        alpha, _ = surfel_alpha(proj, listed, renderer.tile, CAMERA.width, CAMERA.height)
    pairs, fragments = box_counts(proj.box_centres, proj.extents, CAMERA.width, CAMERA.height, renderer.tile)
    assert pairs == len(listed.tile) and int((alpha > 0).sum()) <= fragments
    memory = FAMILIES["2dgs"].memory(renderer, CAMERA)
    assert memory.kept >= renderer.prepare(CAMERA).nbytes > 0      # what the prepared view keeps
    assert memory.per_mask >= fragments                         # each mask's flag for every fragment


def test_bounds_grow_with_overlap_not_with_the_request():
    """The same request costs more where more splats cover each pixel: the plan cannot be
    made from the request alone."""
    few = FAMILIES["3dgs"].memory(GaussianRenderer(cloud(GaussianModel, 2000, 0.004)), CAMERA)
    many = FAMILIES["3dgs"].memory(GaussianRenderer(cloud(GaussianModel, 2000, 0.2)), CAMERA)
    assert many.kept > 20 * few.kept and many.fixed > 10 * few.fixed
    assert many.per_mask == few.per_mask                        # the masks' part does not depend on it
