"""2DGS training with the shared splat loop: the regularisers' maths, that training fits,
and what `train_surfels` writes."""

from __future__ import annotations

import math

import pytest
import torch

from phd_core.data import load_blender
from phd_core.errors import InputError
from phd_core.eval import psnr
from phd_core.renderers import load_model
from phd_core.renderers.gs2d import SurfelModel, rasterize_surfels, read_surfel_ply
from phd_core.renderers.gs3d import read_sidecar
from phd_core.scene import look_at
from phd_core.train import gs2d
from phd_core.train.seeding import initial_model
from phd_core.train.splats import Splats, TrainConfig, densify, fit
from support.fixtures import LEGO


@pytest.fixture(scope="module")
def tiny() -> object:
    return load_blender(LEGO, "train", downscale=8, views=6)


def test_depth_normals_of_a_tilted_plane() -> None:
    cam = look_at((0, -4, 0), (0, 0, 0), width=24, height=20, fov_x=0.8)
    normal = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    normal = normal / normal.norm()                     # camera frame, towards the camera
    offset = -2.5                                       # plane n . p = offset, in front of the camera
    xs = (torch.arange(24, dtype=torch.float64) + 0.5 - cam.cx) / cam.fx
    ys = (torch.arange(20, dtype=torch.float64) + 0.5 - cam.cy) / cam.fy
    rays = torch.stack([xs[None, :].expand(20, 24), ys[:, None].expand(20, 24), torch.ones(20, 24,
                                                                                           dtype=torch.float64)], -1)
    depth = offset / (rays @ normal)                    # [H, W]: where each ray meets the plane
    assert (depth > 0).all()
    got = gs2d.depth_normals(depth, cam)
    assert got.shape == (18, 22, 3) and torch.allclose(got, normal.expand_as(got), atol=1e-9)


def test_normal_consistency_is_zero_for_an_opaque_surfel_facing_the_camera_and_positive_when_tilted() -> None:
    cam = look_at((0, -4, 0), (0, 0, 0), width=16, height=16, fov_x=0.5)

    def loss(quat) -> float:
        model = SurfelModel(torch.zeros(1, 3), torch.full((1, 2), math.log(20.0)), torch.tensor([quat]),
                            torch.tensor([8.0]), torch.zeros(1, 1, 3))
        out = rasterize_surfels(model, cam, torch.ones(3), geometry=True)
        return gs2d.regulariser(out, cam, 1.0, 1.0, distortion_weight=0.0, normal_weight=1.0).item()

    facing = [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]   # normal along world -y: at the camera
    assert loss(facing) == pytest.approx(0.0, abs=1e-5)
    # A surfel's normal that disagrees with the plane its depth describes costs 1 - cos(angle).
    tilted = SurfelModel(torch.zeros(1, 3), torch.full((1, 2), math.log(20.0)), torch.tensor([facing]),
                         torch.tensor([8.0]), torch.zeros(1, 1, 3))
    out = rasterize_surfels(tilted, cam, torch.ones(3), geometry=True)
    out.normal = out.normal @ torch.tensor([[1.0, 0, 0], [0, math.cos(0.5), -math.sin(0.5)],
                                            [0, math.sin(0.5), math.cos(0.5)]]).T
    value = gs2d.regulariser(out, cam, 1.0, 1.0, distortion_weight=0.0, normal_weight=1.0).item()
    assert value == pytest.approx(0.99 * (1 - math.cos(0.5)), rel=1e-3)


def test_the_regularisers_start_at_their_fraction_of_the_run() -> None:
    cam = look_at((0.3, -3, 1), (0, 0, 0), width=12, height=10, fov_x=0.7)
    g = torch.Generator().manual_seed(0)
    model = SurfelModel((torch.rand(20, 3, generator=g) - 0.5), torch.full((20, 2), -1.5),
                        torch.randn(20, 4, generator=g), torch.full((20,), 1.0), torch.zeros(20, 1, 3))
    out = rasterize_surfels(model, cam, torch.ones(3), geometry=True)
    assert out.distortion.sum() > 0
    early = gs2d.regulariser(out, cam, 0.05, 1.0, distortion_weight=1.0, normal_weight=1.0)
    late = gs2d.regulariser(out, cam, 0.5, 1.0, distortion_weight=1.0, normal_weight=1.0)
    assert early.item() == 0.0 and late.item() > 0


def test_surfel_splats_densify_in_their_plane() -> None:
    gen = torch.Generator().manual_seed(0)
    model = initial_model(torch.randn(6, 3), torch.full((6, 3), 0.5), 0, extent=1.0, gen=gen, recipe=gs2d.recipe())
    assert type(model) is SurfelModel and model.log_scales.shape == (6, 2)
    assert not torch.allclose(model.quats, model.quats[:1].expand_as(model.quats))   # random orientations
    model.log_scales[:] = math.log(0.5)                                            # large: split
    splats = Splats(model, TrainConfig(), extent=1.0)
    normals = torch.nn.functional.normalize(model.quats, dim=-1)
    from phd_core.scene.rotations import quaternion_to_rotation
    axes = quaternion_to_rotation(normals)[:, :, 2]
    means = model.means.clone()
    densify(splats, torch.ones(6), TrainConfig(), extent=1.0, budget=100, gen=gen)
    assert splats.count == 12 and type(splats.model()) is SurfelModel
    children = splats.params["means"].detach()
    offsets = children - means.repeat(2, 1)
    assert (offsets * axes.repeat(2, 1)).sum(-1).abs().max() < 1e-5, "children stay in the parent's plane"


def test_training_fits_and_regularisers_run(tiny) -> None:
    def train_psnr(model) -> float:
        renders = torch.cat([rasterize_surfels(model, c, torch.ones(3)).rgb for c in tiny.cameras])
        return psnr(renders.clamp(0, 1), torch.stack(tiny.images))

    config = TrainConfig(iterations=100, init_points=800, seed=3)
    plain = gs2d.recipe(depth_distortion=0.0, normal_consistency=0.0)
    assert plain.regulariser is None and gs2d.recipe().regulariser is not None   # on by default
    trained, _ = fit(tiny, config, progress=False, recipe=plain)
    untrained, _ = fit(tiny, TrainConfig(iterations=1, init_points=800, seed=3), progress=False, recipe=plain)
    assert type(trained) is SurfelModel
    assert train_psnr(trained) > train_psnr(untrained) + 2.0
    regularised, history = fit(tiny, TrainConfig(iterations=30, init_points=500, seed=3), progress=False,
                               recipe=gs2d.recipe(depth_distortion=1.0, normal_consistency=0.05))
    assert all(math.isfinite(v) for v in history) and torch.isfinite(regularised.means).all()


def test_train_surfels_writes_the_reference_layout_and_sidecar(tmp_path) -> None:
    out = tmp_path / "s.ply"
    renderer = gs2d.train_surfels(LEGO, views=[0, 10, 20], downscale=8, iterations=10, out=out, progress=False,
                                  init_points=200)
    header = out.read_bytes().split(b"end_header")[0]
    assert b"scale_1" in header and b"scale_2" not in header
    assert read_surfel_ply(out).num_splats == renderer.num_units
    assert read_sidecar(out)["model"] == "2dgs"
    loaded = load_model(out)
    assert loaded.kind == "2dgs" and len(loaded.training_cameras) == 3
    with pytest.raises(InputError, match="depth_distortion"):
        gs2d.train_surfels(LEGO, out=tmp_path / "x.ply", depth_distortion=-1.0)
