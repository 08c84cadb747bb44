"""Next-best-view strategies: each one's behaviour, on hand-made evidence and on toy renderers."""

from __future__ import annotations

import math

import pytest
import torch

from phd_core import uq as phd
from phd_core.errors import InputError
from phd_core.scene import look_at
from phd_core.uq.strategies import DEFAULT_STRATEGY, STRATEGIES, Evidence, Strategy, get_strategy
from phd_core.uq.strategies.base import by_score
from support.toy_renderers import BlobRenderer, ring_cameras

BATCH_DIVERSE = ("fvs", "fvs_sigma", "fvs_sigma_floor")


def evidence(candidates, captured, sigma_mean=None, sigma_max=None) -> Evidence:
    count = len(candidates)
    as_tensor = lambda v: torch.as_tensor(v if v is not None else [1.0] * count, dtype=torch.float64)  # noqa: E731
    return Evidence(candidates, captured, as_tensor(sigma_max), as_tensor(sigma_mean))


def test_default_is_registered_and_every_name_matches_its_entry() -> None:
    assert DEFAULT_STRATEGY in STRATEGIES
    assert all(name == strategy.name for name, strategy in STRATEGIES.items())


@pytest.mark.parametrize("name", sorted(BATCH_DIVERSE))
def test_identical_candidates_are_never_both_in_a_batch(name: str) -> None:
    ring = ring_cameras(8)
    # The duplicated pose is opposite the captured one and the most uncertain: the best single pick.
    candidates = [ring[4], ring[1], ring[4], ring[7]]
    ranked = get_strategy(name).select(evidence(candidates, [ring[0]], sigma_mean=[2.0, 1.0, 2.0, 1.0]), 2, 0)
    assert ranked.order[0] in (0, 2)
    assert not {0, 2} <= set(ranked.order[:2])


def test_the_papers_rules_rank_by_their_statistic_alone() -> None:
    ring = ring_cameras(4)
    ev = evidence(ring, [], sigma_mean=[0.1, 0.3, 0.3, 0.2], sigma_max=[0.5, 0.2, 0.9, 0.9])
    assert get_strategy("sigma_max").select(ev, 2, 0).order == [2, 3, 0, 1]   # ties: lower index first
    assert get_strategy("sigma_mean").select(ev, 2, 0).order == [1, 2, 3, 0]


def test_fvs_is_greedy_farthest_point_sampling() -> None:
    ring = ring_cameras(12)
    captured, candidates = [ring[0]], ring[1:]
    order = get_strategy("fvs").select(evidence(candidates, captured), 3, 0).order
    chosen = [c.center for c in captured]
    for pick in order[:3]:   # brute force: each pick maximises the distance to everything chosen before it
        nearest = [min(float((c.center - x).norm()) for x in chosen) for c in candidates]
        assert nearest[pick] == pytest.approx(max(nearest))
        chosen.append(candidates[pick].center)


def test_random_and_fvs_reproduce_for_a_seed() -> None:
    ring = ring_cameras(10)
    ev = evidence(ring[1:], ring[:1])
    for name in ("random", "fvs"):
        strategy = get_strategy(name)
        assert strategy.select(ev, 3, 7) == strategy.select(ev, 3, 7)
    assert get_strategy("random").select(ev, 3, 7).order != get_strategy("random").select(ev, 3, 8).order


def test_uncertainty_breaks_the_tie_between_equally_far_views() -> None:
    ring = ring_cameras(8)
    candidates = [ring[2], ring[6]]          # both 90 degrees from the captured pose
    ev = evidence(candidates, [ring[0]], sigma_mean=[0.01, 0.02])
    for name in ("fvs_sigma", "fvs_sigma_floor"):
        assert get_strategy(name).select(ev, 1, 0).order[0] == 1


def blob_scene() -> tuple[BlobRenderer, list]:
    """Blobs only on the +x side of the bounds, observed by cameras on an arc around +x."""
    g = torch.Generator().manual_seed(0)
    count = 30
    means = torch.rand(count, 3, generator=g, dtype=torch.float64) * 0.6 + torch.tensor([0.3, -0.3, -0.3])
    training = [look_at((4 * math.cos(a), 4 * math.sin(a), 1.0), (0.6, 0, 0), (0, 0, 1), width=16, height=16,
                        fov_x=0.7) for a in (-0.6, -0.3, 0.0, 0.3, 0.6)]
    renderer = BlobRenderer(means, torch.rand(count, 3, generator=g), torch.full((count,), 0.6),
                            torch.full((count,), 0.15), training_cameras=training)
    return renderer, training


def test_default_ranks_a_view_of_empty_unobserved_space_above_observed_surface() -> None:
    renderer, training = blob_scene()
    # Looks across the empty -x half of the bounds, away from the blobs: the model has nothing there.
    empty = look_at((-1.5, 3.5, 1.0), (-1.5, -1.0, 0.0), (0, 0, 1), width=16, height=16, fov_x=0.5)
    # Next to a training camera, seeing the well-observed blobs.
    observed = look_at((4.0, 0.2, 1.0), (0.6, 0, 0), (0, 0, 1), width=16, height=16, fov_x=0.7)
    ranked = phd.rank_views(renderer, [observed, empty], ratio=0.3, samples=8, top_k=1)
    assert ranked[0].index == 1
    assert ranked[0].sigma_max == 0.0                        # dropout alone cannot see it
    sigma_only = phd.rank_views(renderer, [observed, empty], ratio=0.3, samples=8, strategy="sigma_mean")
    assert sigma_only[0].index == 0


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_every_ranked_candidate_carries_sigma_and_the_strategys_score(name: str) -> None:
    renderer, training = blob_scene()
    candidates = ring_cameras(6, size=16)
    ranked = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name)
    views = phd.uncertainty(renderer, candidates, ratio=0.3, samples=6, seed=2)
    assert sorted(r.index for r in ranked) == list(range(6))
    assert [r.rank for r in ranked] == list(range(1, 7))
    for r in ranked:
        assert r.sigma_max == views[r.index].sigma_max and r.sigma_mean == views[r.index].sigma_mean
        assert math.isfinite(r.score)
    top = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name, top_k=2)
    assert [r.index for r in top] == [r.index for r in ranked[:2]]


def test_unknown_strategy_is_a_clear_input_error() -> None:
    with pytest.raises(InputError) as info:
        get_strategy("sharpest")
    assert info.value.field == "strategy" and "fvs" in info.value.reason
    renderer, _ = blob_scene()
    with pytest.raises(InputError):
        phd.rank_views(renderer, ring_cameras(2), ratio=0.3, samples=2, strategy="sharpest")


def test_a_new_strategy_is_one_registry_entry() -> None:
    def lowest_index_last(ev: Evidence, k: int, seed: int):
        return by_score(torch.arange(len(ev.candidates), dtype=torch.float64))

    STRATEGIES.register(Strategy("test_last_first", "test only", lowest_index_last, uses_dropout=False))
    try:
        renderer, _ = blob_scene()
        ranked = phd.rank_views(renderer, ring_cameras(3), ratio=0.3, samples=2, strategy="test_last_first")
        assert [r.index for r in ranked] == [2, 1, 0]
        with pytest.raises(ValueError):
            STRATEGIES.register(Strategy("test_last_first", "again", lowest_index_last))
    finally:
        del STRATEGIES["test_last_first"]


# ---------------------------------------------------------------------------------------- selection

@pytest.mark.parametrize("rule", ["distance_sigma", "coverage_checked"])
def test_selection_prefers_the_model_trained_near_the_view(rule: str) -> None:
    renderer, _ = blob_scene()
    ring = ring_cameras(8, size=16)
    near_a = BlobRenderer(renderer.means, renderer.colors, renderer.opacities, renderer.scales,
                          training_cameras=ring[:2])
    near_b = BlobRenderer(renderer.means, renderer.colors, renderer.opacities, renderer.scales,
                          training_cameras=ring[4:6])
    result = phd.select_models(near_a, near_b, [ring[0], ring[5]], ratio_a=0.3, ratio_b=0.3, samples=6, rule=rule)
    assert [v.choice for v in result.views] == ["a", "b"]
    assert result.views[0].score_a == 0.0                     # the view is a training camera of a


def test_distance_sigma_selection_needs_training_cameras() -> None:
    renderer, _ = blob_scene()
    bare = BlobRenderer(renderer.means, renderer.colors, renderer.opacities, renderer.scales)
    with pytest.raises(InputError) as info:
        phd.select_models(renderer, bare, ring_cameras(2), ratio_a=0.3, ratio_b=0.3, samples=4)
    assert info.value.field == "model_b"
    paper = phd.select_models(renderer, bare, ring_cameras(2), ratio_a=0.3, ratio_b=0.3, samples=4,
                              rule="sigma_mean")
    assert len(paper.views) == 2
    with pytest.raises(InputError) as info:
        phd.select_models(renderer, bare, ring_cameras(2), ratio_a=0.3, ratio_b=0.3, rule="best")
    assert info.value.field == "rule"


@pytest.mark.parametrize("name", ["sigma_max", DEFAULT_STRATEGY])
def test_coarse_to_fine_ranks_the_best_again_at_full_size(name: str) -> None:
    """Coarse to fine: all candidates ranked at the coarse size, the best m again at full size
    (first, with their full-size statistics), the rest after them in their coarse order."""
    renderer, _ = blob_scene()
    candidates = ring_cameras(10, size=16)
    coarse = phd.coarse_cameras(candidates, 0.5)
    assert [(c.width, c.height) for c in coarse[:1]] == [(8, 8)] and coarse[0].fx == candidates[0].fx / 2
    first = phd.rank_views(renderer, coarse, ratio=0.3, samples=6, seed=2, strategy=name)
    ranked = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name, coarse=0.5, refine=4)
    best = [v.index for v in first[:4]]
    fine = phd.rank_views(renderer, [candidates[i] for i in best], ratio=0.3, samples=6, seed=2, strategy=name)
    assert [v.index for v in ranked] == [best[v.index] for v in fine] + [v.index for v in first[4:]]
    assert [v.rank for v in ranked] == list(range(1, 11))
    assert [v.refined for v in ranked] == [True] * 4 + [False] * 6
    full = phd.uncertainty(renderer, candidates, ratio=0.3, samples=6, seed=2)
    small = phd.uncertainty(renderer, coarse, ratio=0.3, samples=6, seed=2)
    for v in ranked:
        assert v.sigma_max == (full if v.refined else small)[v.index].sigma_max
    assert full[ranked[0].index].sigma_max != small[ranked[0].index].sigma_max   # the sizes do differ
    # Re-scoring every candidate is the full-size ranking (distinct statistics: no ties to break).
    every = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name, coarse=0.5, refine=10)
    plain = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name)
    assert [v.index for v in every] == [v.index for v in plain] and all(v.refined for v in every)
    # The default m is 20 % of the candidates, at least top_k; top_k keeps the first k.
    top = phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name, coarse=0.5, top_k=3)
    assert len(top) == 3 and all(v.refined for v in top)
    assert [v.refined for v in phd.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, strategy=name,
                                              coarse=0.5)] == [True] * 2 + [False] * 8


@pytest.mark.parametrize("coarse, refine, field", [
    (0.0, None, "coarse"), (1.0, None, "coarse"), (float("nan"), None, "coarse"), (0.5, 0, "refine"),
    (None, 3, "refine"),
])
def test_bad_coarse_settings_name_the_field(coarse, refine, field: str) -> None:
    renderer, _ = blob_scene()
    with pytest.raises(InputError) as info:
        phd.rank_views(renderer, ring_cameras(3), ratio=0.3, samples=2, coarse=coarse, refine=refine)
    assert info.value.field == field
