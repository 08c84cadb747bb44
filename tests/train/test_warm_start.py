"""Warm starts (issue 49): a splat run continues from a model of its family, adds splats where only
new photos' SfM points are, reports every step, stops when its callback raises, trains on an explicit
split and views, and refuses an init of another family or background by name."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from phd_cli import main
from phd_core.data import Dataset, load_blender, load_dataset
from phd_core.errors import InputError
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import read_sidecar
from phd_core.renderers.outputs import base as outputs_base
from phd_core.renderers.outputs.base import nearest_distances
from phd_core.renderers.splats import SH_C0
from phd_core.train import gs2d, gs3d, nerf
from phd_core.train.clock import TrainStep
from phd_core.train.seeding import initial_model, neighbour_spacing, with_new_points
from phd_core.train.splats import TrainConfig
from support.fixtures import LEGO

STILL = {name: 0.0 for name in ("lr_means", "lr_sh_dc", "lr_sh_rest", "lr_opacity", "lr_scales", "lr_quats")}


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    """A 3DGS model trained 30 steps on 4 views of lego at 25 px: the round before new photos."""
    out = tmp_path_factory.mktemp("warm") / "first.ply"
    gs3d.train_gaussians(LEGO, views=[0, 10, 20, 30], downscale=8, iterations=30, out=out, progress=False)
    return out


def test_a_step_with_nothing_to_learn_gives_back_the_initial_splats(first) -> None:
    """With every learning rate 0 the run's output is its init to the bit: it started from those
    splats (a cold start would give the seeded ones) and skipped the opacity reset (10 steps: a
    cold run's schedule resets the opacities at step 3)."""
    data = load_blender(LEGO, "train", downscale=8, views=[0, 10, 20, 30, 40, 50])
    init = load_model(first).model
    model, _ = gs3d.splats.fit(data, TrainConfig(iterations=10, **STILL), gs3d.GAUSSIANS, progress=False, init=init)
    assert model.num_splats == init.num_splats
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(model, name), getattr(init, name)), name
    cold, _ = gs3d.splats.fit(data, TrainConfig(iterations=10, **STILL), gs3d.GAUSSIANS, progress=False)
    assert cold.num_splats != init.num_splats or not torch.equal(cold.means, init.means)


def test_a_warm_run_writes_what_it_continued_from_and_learns(first, tmp_path) -> None:
    out = tmp_path / "warm.ply"
    steps: list[TrainStep] = []
    gs3d.train_gaussians(LEGO, views=[0, 10, 20, 30, 40, 50], downscale=8, iterations=20, out=out, progress=False,
                         init=first, on_step=steps.append)
    assert [(at.step, at.total) for at in steps] == [(step, 20) for step in range(1, 21)]
    assert steps[-1].seconds_left == 0 and all(0 <= at.seconds_left <= at.seconds_left_max for at in steps)
    sidecar = read_sidecar(out)
    assert sidecar["init"]["file"] == "first.ply" and sidecar["init"]["num_splats"] == load_model(first).num_units
    assert len(sidecar["training_cameras"]) == 6
    warm, start = load_model(out).model, load_model(first).model
    assert not torch.equal(warm.means[: start.num_splats], start.means)       # it trained


def test_raising_from_the_step_callback_stops_the_run(tmp_path) -> None:
    class Stop(Exception):
        pass

    seen = []

    def stop_at_5(at: TrainStep) -> None:
        seen.append(at.step)
        if at.step == 5:
            raise Stop

    with pytest.raises(Stop):
        gs3d.train_gaussians(LEGO, views=4, downscale=8, iterations=50, out=tmp_path / "m.ply", progress=False,
                             on_step=stop_at_5)
    assert seen == list(range(1, 6)) and not (tmp_path / "m.ply").exists()


def test_a_split_with_views_trains_on_exactly_those_cameras(tmp_path) -> None:
    out = tmp_path / "m.ply"
    gs3d.train_gaussians(LEGO, split="test", views=[1, 50, 150], downscale=8, iterations=2, out=out, progress=False)
    expected = load_dataset(LEGO, "test", views=[1, 50, 150], downscale=8, with_images=False).cameras
    assert read_sidecar(out)["training_cameras"] == [c.to_frame() for c in expected]
    assert read_sidecar(out)["split"] == "test"


def test_an_init_of_another_family_or_background_is_refused_by_name(first, tmp_path) -> None:
    with pytest.raises(InputError) as family:
        gs2d.train_surfels(LEGO, views=4, downscale=8, iterations=2, out=tmp_path / "s.ply", progress=False,
                           init=first)
    assert family.value.field == "init" and "3dgs" in family.value.reason
    with pytest.raises(InputError) as background:
        gs3d.train_gaussians(LEGO, views=4, downscale=8, iterations=2, out=tmp_path / "b.ply", progress=False,
                             init=first, background=[0, 0, 0])
    assert background.value.field == "init" and "background" in background.value.reason
    with pytest.raises(InputError) as network:
        nerf.train_nerf(LEGO, views=4, downscale=8, iterations=2, out=None, progress=False, init=first)
    assert network.value.field == "init"


def test_phd_train_continues_from_init(first, tmp_path, capsys) -> None:
    out = tmp_path / "cli.ply"
    assert main(["train", "--data", str(LEGO), "--views", "6", "--downscale", "8", "--iterations", "5", "--init",
                 str(first), "--out", str(out), "--quiet"]) == 0
    assert json.loads(out.with_suffix(".json").read_text())["init"]["file"] == "first.ply"
    assert main(["train", "--model", "2dgs", "--data", str(LEGO), "--views", "6", "--downscale", "8",
                 "--iterations", "5", "--init", str(first), "--out", str(tmp_path / "s.ply"), "--quiet"]) == 2
    assert "init" in capsys.readouterr().err


def test_phd_train_on_all_frames_trains_on_exactly_the_views_given(tmp_path) -> None:
    """--split all with indices (the service's capture less its held-out photos): frames 0 and 8
    are test frames of cup_colmap's train/test split, so a run that ignored --split would train on
    other photos (or refuse index 70 of the 67 training frames)."""
    cup = LEGO.parent / "cup_colmap"
    out = tmp_path / "all.ply"
    assert main(["train", "--data", str(cup), "--split", "all", "--views", "0,8,70", "--downscale", "16",
                 "--iterations", "2", "--out", str(out), "--quiet"]) == 0
    sidecar = read_sidecar(out)
    held_out = load_dataset(cup, "test", views=[0, 1], downscale=16, with_images=False).cameras
    assert sidecar["split"] == "all" and sidecar["view_indices"] == [0, 8, 70]
    assert sidecar["training_cameras"][:2] == [c.to_frame() for c in held_out]


def test_a_warm_start_adds_a_splat_at_each_sfm_point_no_splat_comes_near() -> None:
    """The capture loop's next round: the photos added see parts the last model has no splat near.
    Their SfM points are seeded as a cold start seeds them; the points the model already covers add
    nothing, and the model's own splats are kept to the bit."""
    gen = torch.Generator().manual_seed(0)
    here = torch.rand(200, 3, generator=gen, dtype=torch.float64)                    # what the model covers
    there = torch.rand(30, 3, generator=gen, dtype=torch.float64) + torch.tensor([5.0, 0, 0], dtype=torch.float64)
    init = initial_model(here.float(), torch.full((200, 3), 0.5), 1, 1.0, gen, gs3d.GAUSSIANS)
    points = torch.cat([here + 0.001, there])                                        # [230, 3]
    colours = torch.rand(230, 3, generator=gen)
    data = Dataset(cameras=[], images=None, alphas=None, indices=[], root=LEGO, split="train",
                   background=(0.0, 0.0, 0.0), near=None, far=None, points=points, point_colors=colours)
    model = with_new_points(init, data, 1.0, gen, gs3d.GAUSSIANS)
    assert model.num_splats == 230
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(model, name)[:200], getattr(init, name)), name
    assert torch.equal(model.means[200:], there.float())
    assert torch.allclose(model.sh[200:, 0] * SH_C0 + 0.5, colours[200:], atol=1e-6)
    assert torch.allclose(model.log_scales[200:, 0], (neighbour_spacing(points)[200:] / 2).log().float())
    assert torch.equal(with_new_points(init, dataclasses.replace(data, points=here + 0.001), 1.0, gen,
                                       gs3d.GAUSSIANS).means, init.means)            # nothing new: nothing added


def test_the_nearest_splat_is_found_in_chunks_as_in_one_block(monkeypatch) -> None:
    """`with_new_points` measures each SfM point's distance to the splats with the project's chunked
    `nearest_distances` (millions of splats fit): against brute force, one point a chunk and all at once."""
    gen = torch.Generator().manual_seed(1)
    points, means = torch.randn(300, 3, generator=gen, dtype=torch.float64), torch.randn(70, 3, generator=gen)
    brute = torch.tensor([min(float((p - m.double()).norm()) for m in means) for p in points], dtype=torch.float64)
    assert torch.allclose(nearest_distances(points, means), brute, rtol=0, atol=1e-12)
    monkeypatch.setattr(outputs_base, "DISTANCE_CHUNK", 100)                        # 1 row a chunk
    assert torch.allclose(nearest_distances(points, means), brute, rtol=0, atol=1e-12)
