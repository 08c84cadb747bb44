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
from phd_core.uq.strategies import STRATEGIES


@pytest.fixture
def bench_nbv():
    """bench.bench_nbv for one test: importing it registers the strategies the benchmark tried
    (bench/nbv_experiments.py), which the tests after this one must not find registered (the CLI
    offers every registered strategy)."""
    shipped = dict(STRATEGIES)
    yield importlib.import_module("bench.bench_nbv")
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
