"""NeRF training on a tiny version of the lego scene (phd_core.train.nerf)."""

from __future__ import annotations

import pytest
import torch

from phd_core.data import load_blender
from phd_core.data.identity import fingerprint
from phd_core.errors import InputError
from phd_core.eval import psnr
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, camera_rays, load_nerf
from phd_core.renderers.provenance import measure_fit
from phd_core.scene import frustum_bounds
from phd_core.train.nerf import TrainSettings, fit, grid_hull, train_nerf
from phd_core.uq.candidates import hemisphere_cameras
from support.fixtures import LEGO

pytestmark = pytest.mark.skipif(not LEGO.is_dir(), reason="lego_200 data not available")
# Small enough for a few seconds of training on 2 busy cores.
TINY = dict(width=32, color_width=16, pos_freqs=6, samples=32, batch_rays=256, grid_resolution=16)


@pytest.fixture(scope="module")
def tiny_lego():
    return load_blender(LEGO, "train", downscale=8, views=6)            # 25 x 25 pixels


@pytest.fixture(scope="module")
def trained(tiny_lego, tmp_path_factory):
    out = tmp_path_factory.mktemp("nerf") / "lego.nerf"
    renderer = train_nerf(tiny_lego, iterations=150, seed=0, out=out, progress=False, **TINY)
    return renderer, out


def render_views(renderer, cameras) -> torch.Tensor:
    return torch.cat([renderer.render(camera) for camera in cameras])


def test_training_fits_the_training_views(tiny_lego, trained):
    renderer, _ = trained
    untrained = NeRFRenderer(RadianceField(renderer.config, seed=0))
    before = psnr(render_views(untrained, tiny_lego.cameras), torch.stack(tiny_lego.images))
    after = psnr(render_views(renderer, tiny_lego.cameras), torch.stack(tiny_lego.images))
    assert after > before + 7, (before, after)       # measured: 10.5 -> 21.5 dB (seed 0)
    assert after > 18, after


def test_occupancy_grid_skips_empty_space_without_changing_the_render(tiny_lego, trained):
    renderer, _ = trained
    info = renderer.describe()
    assert 0.0 < info["occupancy_grid"]["occupied_fraction"] < 0.5
    camera = load_blender(LEGO, "test", downscale=8, views=[7], with_images=False).cameras[0]
    with_grid = renderer.render(camera)
    renderer.use_grid = False
    try:
        without = renderer.render(camera)
    finally:
        renderer.use_grid = True
    # The grid probes each cell at 27 points, so a thin feature between them can still
    # be cut: allow a few changed pixels, not a changed image.
    assert psnr(with_grid, without) > 45, psnr(with_grid, without)   # measured: 65 dB
    assert (with_grid - without).abs().mean() < 0.002


def test_checkpoint_holds_the_model_and_its_training_cameras(tiny_lego, trained):
    renderer, out = trained
    loaded = load_nerf(out)
    assert loaded.describe() == renderer.describe()
    assert [c.to_frame() for c in loaded.training_cameras] == [c.to_frame() for c in tiny_lego.cameras]
    camera = tiny_lego.cameras[2]
    keep = torch.rand(3, loaded.num_units, generator=torch.Generator().manual_seed(1)) >= 0.2
    assert torch.equal(loaded.render(camera, keep), renderer.render(camera, keep))


def test_a_checkpoint_trained_from_a_capture_records_it_and_the_fit(tmp_path):
    """The capture's path, format and fingerprint and the fit on its training views ride in the
    checkpoint's header; a model trained from a Dataset in memory names no capture."""
    out = tmp_path / "lego.nerf"
    trained = train_nerf(LEGO, views=2, downscale=8, iterations=2, seed=0, out=out, progress=False, **TINY)
    loaded = load_nerf(out)
    assert loaded.trained_on == trained.trained_on and loaded.trained_on is not None
    assert (loaded.trained_on.path, loaded.trained_on.format) == (str(LEGO.resolve()), "blender")
    assert loaded.trained_on.fingerprint == fingerprint(load_blender(LEGO, "train", with_images=False))
    assert loaded.trained_on.fit == measure_fit(loaded, LEGO)
    assert train_nerf(load_blender(LEGO, "train", downscale=8, views=1), iterations=1, out=None, progress=False,
                      **TINY).trained_on is None


def test_training_is_seeded(tiny_lego):
    runs = [train_nerf(tiny_lego, iterations=4, seed=7, out=None, progress=False, **TINY) for _ in range(2)]
    camera = tiny_lego.cameras[0]
    assert torch.equal(runs[0].render(camera), runs[1].render(camera))


def test_scene_box_is_what_every_camera_sees():
    cameras = load_blender(LEGO, "train", downscale=2, views=16, with_images=False).cameras
    lo, hi = frustum_bounds(cameras, 2.0, 6.0)
    # The NeRF-synthetic scenes are known to fit in [-1.5, 1.5]^3 (data README).
    assert all(-1.8 < v < -1.3 for v in lo) and all(1.3 < v < 1.8 for v in hi), (lo, hi)


def test_visual_hull_never_carves_the_object():
    center, radius = torch.tensor([0.2, -0.1, 0.1], dtype=torch.float64), 0.45
    cameras = hemisphere_cameras(6, radius=4.0, width=24, height=20, fov_x=0.6, min_elevation=0.2,
                                 max_elevation=1.2)
    alphas = []
    for camera in cameras:                      # alpha = 1 where the pixel's ray hits the sphere
        origins, dirs = (x.double() for x in camera_rays(camera))
        oc = origins - center
        b = (oc * dirs).sum(-1)
        hits = b ** 2 - ((oc * oc).sum(-1) - radius ** 2) >= 0
        alphas.append(hits.float().view(camera.height, camera.width))
    model = RadianceField(NeRFConfig(bounds=[[-1, -1, -1], [1, 1, 1]], grid_resolution=10))
    hull = grid_hull(model, cameras, torch.stack(alphas))
    grid = model.grid
    lo = grid.cell_points(torch.zeros(1, 3)).double()
    hi = lo + grid.size.double() / grid.resolution
    nearest = torch.maximum(torch.minimum(center, hi), lo)           # closest point of each cell to the centre
    touches = (nearest - center).norm(dim=-1) <= radius
    assert hull[touches].all()
    assert hull.float().mean() < 0.5                                 # and it does carve empty space


@pytest.mark.parametrize("options, field", [(dict(encoding="fourier"), "encoding"), (dict(width=0), "width"),
                                            (dict(iterations=0), "iterations"), (dict(widht=64), "widht"),
                                            (dict(lr=-1.0), "lr"), (dict(freenerf="yes"), "freenerf"),
                                            (dict(background="black"), "background")])
def test_bad_training_options_name_the_field(tiny_lego, options, field):
    with pytest.raises(InputError) as err:
        train_nerf(tiny_lego, out=None, progress=False, **{"iterations": 1, **options})
    assert err.value.field == field


def test_freenerf_frequency_mask_hides_high_bands_at_the_start(tiny_lego):
    # One step with the mask: only the lowest band (and raw x) reaches the first layer, so
    # Adam leaves the weights of every other band exactly where they were.
    renderer = train_nerf(tiny_lego, iterations=1, seed=3, out=None, progress=False, freenerf=True, **TINY)
    start = RadianceField(renderer.config, seed=3)
    moved = (renderer.model.first.weight - start.first.weight).abs().sum(0)      # per input column
    assert renderer.describe()["freenerf"] == {"frequency_mask": True, "occlusion": True}
    assert (moved[:9] > 0).all()               # x and band 0 (3 sines, 3 cosines) learn
    assert torch.equal(moved[9:], torch.zeros_like(moved[9:]))


def test_freenerf_occlusion_penalty_enters_the_loss(tiny_lego):
    config = NeRFConfig(**{k: v for k, v in TINY.items() if k != "batch_rays"}, bounds=[[-1.5] * 3, [1.5] * 3],
                        freenerf_occlusion=True)
    losses = {}
    for weight in (0.0, 1000.0):
        model = RadianceField(config, seed=0)
        settings = TrainSettings(batch_rays=64, occlusion_weight=weight, occlusion_range=5).validate()
        losses[weight] = fit(model, tiny_lego, settings, iterations=1, seed=0, hull=None, progress=False)[0]
    # An untrained field has density ~softplus(-1) = 0.31 everywhere: the first 5 of 32
    # samples add about 1000 * 5 * 0.31 / 32 = 49 (rays that miss the box add nothing).
    assert 5 < losses[1000.0] - losses[0.0] < 60
