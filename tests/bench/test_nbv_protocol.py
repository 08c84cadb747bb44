"""The real-capture next-best-view benchmark's protocol (bench/bench_nbv.py --family real): the same views
and seed train the same model bit for bit, so every strategy starts from one round-0 model and a
difference between strategies is theirs, not the training's."""

from __future__ import annotations

import argparse
import importlib

import numba
import pytest
import torch

from bench._harness import capture_path, pin_determinism, train
from phd_core.scene import look_at
from phd_core.uq.strategies import STRATEGIES, Evidence


@pytest.fixture
def bench_nbv():
    """bench.bench_nbv for one test: importing it registers the strategies the benchmark tried
    (bench/nbv_experiments.py), which the tests after this one must not find registered (the CLI
    offers every registered strategy)."""
    shipped = dict(STRATEGIES)
    module = importlib.import_module("bench.bench_nbv")
    if not set(module.nbv_experiments.EXPERIMENTS) <= set(STRATEGIES):     # imported before, its entries cleared
        importlib.reload(module.nbv_experiments)
    yield module
    STRATEGIES.clear()
    STRATEGIES.update(shipped)


@pytest.fixture
def pinned():
    """pin_determinism for one test, then the process's settings as they were."""
    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    deterministic = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(2)
    pin_determinism()
    yield
    torch.set_num_threads(threads)
    numba.set_num_threads(numba_threads)
    torch.use_deterministic_algorithms(deterministic)


def test_the_same_views_and_seed_train_the_same_model_bit_for_bit(pinned, bench_nbv) -> None:
    assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
    assert torch.are_deterministic_algorithms_enabled()
    args = argparse.Namespace(family="real", data=capture_path("cup_colmap").parent, resolution=16,
                              captures={"cup_colmap": capture_path("cup_colmap")})
    views = bench_nbv.load_split(args, "cup_colmap", "train")
    assert max(c.width for c in views.cameras) == 16 and views.cameras[0].height == 12      # its own 4:3 aspect
    first, again = (train(views, [0, 9, 18, 27], 8, seed=3).model for _ in range(2))
    other = train(views, [0, 9, 18, 27], 8, seed=4).model
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(first, name), getattr(again, name)), name
    assert not torch.equal(first.means, other.means)          # the seed does reach the model


def test_a_view_sees_the_sfm_points_in_its_frame_in_front_of_it_and_not_hidden_by_nearer_ones(bench_nbv) -> None:
    camera = look_at((0, -5, 0), (0, 0, 0), width=40, height=30, fov_x=1.0)
    points = torch.tensor([[0, 0, 0],       # at the centre, 5 ahead
                           [0, 3, 0],       # behind it on the same ray: hidden
                           [0, -6, 0],      # behind the camera
                           [50, 0, 0],      # outside the frame
                           [0, 0.2, 0]],    # behind it by 4 % of its depth: within the slack, seen
                          dtype=torch.float64)
    seen = bench_nbv.nbv_experiments.seen_points(camera, points)
    assert seen.tolist() == [True, False, False, False, True]


def test_sfm_coverage_picks_the_views_that_see_points_seen_by_fewer_than_two(bench_nbv) -> None:
    experiments = bench_nbv.nbv_experiments
    grid = torch.tensor([[x, 0.0, z] for x in (-1.0, -0.5, 0.0, 0.5, 1.0) for z in (-0.5, 0.5)],
                        dtype=torch.float64)                                          # [10, 3] a wall at y = 0
    points = torch.cat([grid, grid[:8] + torch.tensor([100.0, 0, 0], dtype=torch.float64)])  # 10 here, 8 at x = 100

    def view(x: float):
        return look_at((x, -5, 0), (x, 0, 0), width=40, height=30, fov_x=1.0)
    candidates = [view(0), view(0), view(100)]      # two see the 10 points, one the 8
    empty = torch.zeros(3, dtype=torch.float64)
    evidence = experiments.with_points(Evidence(candidates, [], empty, empty), points)
    chosen = STRATEGIES["sfm_coverage"].select(evidence, 3, 0)
    # 10 points unseen count 2 each (20), then the twin adds only a second view of each (10) against 8 x 2 = 16
    assert chosen.order == [0, 2, 1] and chosen.scores == [20.0, 10.0, 16.0]
    with pytest.raises(ValueError, match="SfM points"):
        STRATEGIES["sfm_coverage"].select(Evidence(candidates, [], empty, empty), 1, 0)


def test_cover_starts_from_the_fewest_views_that_see_enough_of_what_the_test_views_see(bench_nbv) -> None:
    args = argparse.Namespace(family="real", data=capture_path("cup_colmap").parent, resolution=16,
                              captures={"cup_colmap": capture_path("cup_colmap")})
    train_data, test = (bench_nbv.load_split(args, "cup_colmap", split, with_images=False)
                        for split in ("train", "test"))
    seen_points = bench_nbv.nbv_experiments.seen_points
    points = train_data.points.double()

    def covered(views: list[int]) -> float:     # point by point, test view by test view
        seen = [seen_points(train_data.cameras[i], points).tolist() for i in views]
        shares = []
        for camera in test.cameras:
            shown = [p for p, s in enumerate(seen_points(camera, points).tolist()) if s]
            if shown:
                shares.append(sum(any(row[p] for row in seen) for p in shown) / len(shown))
        return sum(shares) / len(shares)
    assert bench_nbv.covering_views(train_data, test, 4, None, 1) == bench_nbv.initial_views(train_data.cameras, 4, 1)
    for cover in (0.5, 0.999):                  # cup_colmap's first 4 views see 99 % (docs/nbv.md)
        views = bench_nbv.covering_views(train_data, test, 4, cover, 1)
        assert views == bench_nbv.initial_views(train_data.cameras, len(views), 1)     # farthest-view order
        assert covered(views) >= cover and (len(views) == 4 or covered(views[:-1]) < cover)
        assert (len(views) > 4) == (cover == 0.999)
