"""Uncertainty-quality statistics and heat maps against hand-written references (and
scipy when it happens to be installed; it is not a project dependency)."""

from __future__ import annotations

import itertools
import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from phd_core.errors import InputError
from phd_core.eval import uq as m
from phd_core.io.heatmap import ANCHORS, apply_colormap, colorize, write_heatmap

RNG = np.random.default_rng(0)


def tied(n: int, levels: int) -> np.ndarray:
    return RNG.integers(0, levels, n).astype(np.float64)


# ---------------------------------------------------------------------------------------- correlations

def hand_ranks(x: np.ndarray) -> np.ndarray:
    """Average ranks by counting: rank = #smaller + (#equal + 1) / 2."""
    return np.array([(x < v).sum() + ((x == v).sum() + 1) / 2 for v in x])


def hand_pearson(x: np.ndarray, y: np.ndarray) -> float:
    xc, yc = x - x.mean(), y - y.mean()
    return float((xc * yc).sum() / math.sqrt((xc ** 2).sum() * (yc ** 2).sum()))


def hand_kendall_b(x: np.ndarray, y: np.ndarray) -> float:
    concordant = discordant = tx = ty = 0
    for i, j in itertools.combinations(range(len(x)), 2):
        dx, dy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
        tx += dx == 0
        ty += dy == 0
        concordant += dx * dy > 0
        discordant += dx * dy < 0
    pairs = len(x) * (len(x) - 1) / 2
    return (concordant - discordant) / math.sqrt((pairs - tx) * (pairs - ty))


def test_ranks_average_ties() -> None:
    x = tied(200, 7)
    np.testing.assert_array_equal(m.rankdata(x).numpy(), hand_ranks(x))
    assert m.rankdata([3.0, 1.0, 2.0, 2.0]).tolist() == [4.0, 1.0, 2.5, 2.5]


@pytest.mark.parametrize("levels", [5, 1000])
def test_correlations_match_hand_computation(levels: int) -> None:
    x = tied(300, levels)
    y = x + tied(300, levels) * 0.7
    assert m.pearson(x, y) == pytest.approx(hand_pearson(x, y), abs=1e-12)
    assert m.spearman(x, y) == pytest.approx(hand_pearson(hand_ranks(x), hand_ranks(y)), abs=1e-12)
    small_x, small_y = x[:60], y[:60]
    assert m.kendall_tau_b(small_x, small_y, chunk=7) == pytest.approx(hand_kendall_b(small_x, small_y), abs=1e-12)


def test_correlations_match_scipy() -> None:
    stats = pytest.importorskip("scipy.stats")
    x, y = tied(400, 9), tied(400, 4) + tied(400, 9)
    assert m.spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic, abs=1e-12)
    assert m.pearson(x, y) == pytest.approx(stats.pearsonr(x, y).statistic, abs=1e-12)
    assert m.kendall_tau_b(x, y) == pytest.approx(stats.kendalltau(x, y).statistic, abs=1e-12)


def test_perfect_and_reversed_orders() -> None:
    x = np.arange(10.0)
    assert m.spearman(x, x ** 3) == pytest.approx(1.0)
    assert m.kendall_tau_b(x, -x) == pytest.approx(-1.0)
    assert m.pearson(x, 2 * x + 1) == pytest.approx(1.0)


@pytest.mark.parametrize("fn", [m.spearman, m.pearson, m.kendall_tau_b])
def test_undefined_correlations_are_none(fn) -> None:
    assert fn(np.zeros(20), np.arange(20.0)) is None
    assert fn(np.arange(20.0), np.full(20, 0.3)) is None
    assert fn([1.0], [2.0]) is None
    assert json.dumps({"rho": fn(np.ones(5), np.arange(5.0))}) == '{"rho": null}'


def test_bad_correlation_input_is_rejected() -> None:
    with pytest.raises(InputError) as info:
        m.spearman([1.0, 2.0, 3.0], [1.0, 2.0])
    assert info.value.field == "y"
    with pytest.raises(InputError) as info:
        m.pearson([1.0, math.nan, 3.0], [1.0, 2.0, 3.0])
    assert info.value.field == "x"


def test_top_k_overlap() -> None:
    a = [0.9, 0.1, 0.5, 0.7, 0.3]
    b = [0.8, 0.7, 0.1, 0.2, 0.3]   # top-2: {0, 1} against a's {0, 3}
    assert m.top_k_overlap(a, b, 2) == 0.5
    assert m.top_k_overlap(a, a, 3) == 1.0
    assert m.order_by_score([0.2, 0.5, 0.5, 0.1]) == [1, 2, 0, 3]   # ties by index
    with pytest.raises(InputError) as info:
        m.top_k_overlap(a, b, 6)
    assert info.value.field == "k"


# ---------------------------------------------------------------------------------------- AUSE

def hand_ause(u: np.ndarray, e: np.ndarray, metric: str, steps: int) -> float:
    """Remove elements one fraction at a time, recomputing the metric from scratch."""
    e = np.abs(e)
    n = len(e)

    def value(rest: np.ndarray) -> float:
        if metric == "mae":
            return rest.mean()
        mse = (rest ** 2).mean()
        return math.sqrt(mse) if metric == "rmse" else mse

    by_u = np.argsort(-u, kind="stable")
    by_e = np.argsort(-e, kind="stable")
    fractions = np.arange(steps) / steps
    curve = np.array([value(e[by_u[int(math.floor(f * n + 1e-9)):]]) for f in fractions])
    oracle = np.array([value(e[by_e[int(math.floor(f * n + 1e-9)):]]) for f in fractions])
    gap = curve / curve[0] - oracle / oracle[0]
    return float(((gap[1:] + gap[:-1]) / 2 * np.diff(fractions)).sum())


@pytest.mark.parametrize("metric", m.AUSE_METRICS)
@pytest.mark.parametrize("steps", [20, 100])
def test_ause_matches_hand_computation(metric: str, steps: int) -> None:
    e = RNG.normal(size=997)
    u = np.abs(e) + RNG.uniform(0, 1.5, size=997)   # informative but noisy
    assert m.ause(u, e, metric, steps) == pytest.approx(hand_ause(u, e, metric, steps), abs=1e-12)


def test_ause_properties() -> None:
    e = RNG.normal(size=2000)
    assert m.ause(np.abs(e), e) == pytest.approx(0.0, abs=1e-12)       # uncertainty = error: the oracle
    informative = m.ause(np.abs(e) + RNG.uniform(0, 0.5, 2000), e)
    random = m.ause(RNG.uniform(size=2000), e)
    assert 0 < informative < random
    fractions, curve, oracle = m.sparsification_curves(RNG.uniform(size=2000), e, "mse", 50)
    assert fractions[0] == 0 and curve[0] == oracle[0] == 1.0
    assert (oracle <= curve + 1e-12).all()                             # the oracle is the best order
    assert (np.diff(oracle.numpy()) <= 1e-12).all()


def test_ause_undefined_cases_are_none() -> None:
    e = RNG.normal(size=50)
    assert m.ause(np.full(50, 0.2), e) is None       # constant uncertainty: no order
    assert m.ause(RNG.uniform(size=50), np.zeros(50)) is None   # no error to normalise by
    with pytest.raises(InputError) as info:
        m.ause(e, e, "psnr")
    assert info.value.field == "metric"


def test_image_uq_metrics() -> None:
    g = torch.Generator().manual_seed(0)
    truth = torch.rand(10, 12, 3, generator=g)
    noise = torch.randn(10, 12, 3, generator=g) * 0.1
    render = truth + noise
    report = m.image_uq_metrics(noise.abs() + 0.01, render, truth)
    assert report["spearman"] == pytest.approx(1.0, abs=1e-9) and report["ause_mae"] == pytest.approx(0, abs=1e-9)
    assert report["rmse"] == pytest.approx(float(noise.double().square().mean().sqrt()), rel=1e-6)
    flat = m.image_uq_metrics(torch.zeros(10, 12, 3), render, truth)
    assert flat["spearman"] is None and flat["pearson"] is None and flat["ause_rmse"] is None
    json.dumps(flat, allow_nan=False)


# ---------------------------------------------------------------------------------------- trends, ensembles

def test_trend_correlations() -> None:
    trends = m.trend_correlations([8, 16, 100], [0.46, 0.42, 0.34], [0.36, 0.40, 0.46])
    assert trends == {"rho_u": pytest.approx(-1.0), "rho_r": pytest.approx(1.0)}
    assert m.trend_correlations([8, 16], [0.4, 0.4], [0.3, 0.5])["rho_u"] is None


def test_ensemble_efficiency() -> None:
    assert m.ensemble_efficiency([0.9, 0.8], [0.9, 0.6], [0.7, 0.8]) == pytest.approx(1.0)
    assert m.ensemble_efficiency([0.7, 0.6], [0.9, 0.6], [0.7, 0.8]) == pytest.approx((0.7 / 0.9 + 0.6 / 0.8) / 2)
    assert m.ensemble_efficiency([0.5, 0.0], [0.5, -0.1], [0.4, 0.0]) == pytest.approx(1.0)   # view 2 undefined
    assert m.ensemble_efficiency([0.0], [0.0], [-0.2]) is None
    assert m.mean_defined([None, 1.0, 3.0]) == 2.0 and m.mean_defined([None]) is None


# ---------------------------------------------------------------------------------------- heat maps

def test_colormap_anchors_and_interpolation() -> None:
    assert apply_colormap(np.array([0.0]))[0].tolist() == ANCHORS[0].tolist()
    assert apply_colormap(np.array([1.0]))[0].tolist() == ANCHORS[-1].tolist()
    midway = apply_colormap(np.array([0.5 / 9]))[0]
    assert midway.tolist() == np.rint((ANCHORS[0] + ANCHORS[1]) / 2).astype(int).tolist()
    luminance = (apply_colormap(np.linspace(0, 1, 200)) @ np.array([0.2126, 0.7152, 0.0722]))
    assert (np.diff(luminance) >= -1.0).all(), "the ramp must get brighter monotonically"


def test_heatmap_png_scale_and_atomic_write(tmp_path) -> None:
    zeta = torch.zeros(6, 8, 3)
    zeta[1, 2, 0] = 0.5
    zeta[3, 4, 2] = 0.125   # binary fractions: exact scaled values
    path = tmp_path / "maps" / "view.png"
    vmax = write_heatmap(path, zeta)
    assert vmax == 0.5
    image = iio.imread(path)
    assert image.shape == (6, 8, 3) and image.dtype == np.uint8
    assert image[1, 2].tolist() == ANCHORS[-1].tolist()          # the view's sigma_max
    assert image[0, 0].tolist() == ANCHORS[0].tolist()
    assert image[3, 4].tolist() == apply_colormap(np.array([0.25]))[0].tolist()
    fixed, used = colorize(zeta, vmax=0.25)
    assert used == 0.25 and fixed[1, 2].tolist() == ANCHORS[-1].tolist()   # clipped
    assert fixed[3, 4].tolist() == apply_colormap(np.array([0.5]))[0].tolist()
    blank, used = colorize(torch.zeros(4, 4))
    assert used == 0.0 and (blank == ANCHORS[0].astype(np.uint8)).all()
    assert sorted(p.name for p in path.parent.iterdir()) == ["view.png"]  # no temporary files left
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(InputError) as info:
            colorize(zeta, vmax=bad)
        assert info.value.field == "vmax"
    with pytest.raises(InputError):
        colorize(torch.full((2, 2), math.nan))
