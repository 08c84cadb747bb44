"""Next-best view from the model's visibility: orientation, occlusion and batches, on hand-built
splat scenes where camera centres alone cannot give the right answer."""

from __future__ import annotations

import math

import pytest
import torch

from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.renderers.visibility import Visibility
from phd_core.scene import look_at
from phd_core.uq import select_models
from phd_core.uq.rank import add_fisher, candidate_evidence, visibility_evidence
from phd_core.uq.strategies import Evidence, get_strategy
from phd_core.uq.strategies.coverage import (
    ANGLE_SCALE,
    EMPTY_WEIGHT,
    SEEN_SHARE,
    Coverage,
    mean_zeta,
    stable_order,
    viewing_axis,
)
from phd_core.uq.strategies.visibility import SPREAD_FLOOR, coverage_select
from support.fixtures import svc_random_gaussians
from support.toy_renderers import BlobRenderer, ring_cameras

SIZE = 32


def splats(points: list[torch.Tensor], scale: float) -> GaussianModel:
    """Opaque grey splats of one size at the given points ([P, 3] each)."""
    means = torch.cat(points).float()
    count = len(means)
    return GaussianModel(means=means, log_scales=torch.full((count, 3), math.log(scale)),
                         quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(count, 1),
                         opacity_logits=torch.full((count,), 4.0), sh=torch.full((count, 1, 3), 0.3))


def grid(corner: tuple[float, float, float], u: tuple[float, float, float], v: tuple[float, float, float],
         steps: int = 10) -> torch.Tensor:
    """[steps^2, 3] points of the parallelogram corner + s u + t v, s and t in [0, 1]."""
    s = torch.linspace(0, 1, steps, dtype=torch.float64)
    a, b = torch.meshgrid(s, s, indexing="ij")
    return (torch.tensor(corner, dtype=torch.float64) + a.reshape(-1, 1) * torch.tensor(u, dtype=torch.float64)
            + b.reshape(-1, 1) * torch.tensor(v, dtype=torch.float64))


def camera(eye, target=(0.0, 0.0, 0.0)):
    return look_at(eye, target, width=SIZE, height=SIZE, fov_x=0.8)


def open_box() -> GaussianRenderer:
    """Four walls and a floor around a small cluster on the floor; open at the top (+z)."""
    walls = [grid((-1, -1, -1), (2, 0, 0), (0, 0, 2)), grid((-1, 1, -1), (2, 0, 0), (0, 0, 2)),
             grid((-1, -1, -1), (0, 2, 0), (0, 0, 2)), grid((1, -1, -1), (0, 2, 0), (0, 0, 2)),
             grid((-1, -1, -1), (2, 0, 0), (0, 2, 0))]
    inside = grid((-0.3, -0.3, -0.8), (0.6, 0, 0), (0, 0.6, 0), steps=5)
    return GaussianRenderer(splats(walls + [inside], 0.12))


def ranking(name: str, renderer: GaussianRenderer, candidates: list, captured: list, k: int):
    return get_strategy(name).select(visibility_evidence(renderer, candidates, captured), k, 0)


@pytest.mark.parametrize("name", ["visibility", "visibility_sigma", "visibility_sigma_fvs"])
def test_a_part_hidden_behind_an_occluder_from_every_captured_view_ranks_its_view_first(name: str) -> None:
    renderer = open_box()
    # Captured: a ring at the height of the walls; the walls hide the inside from all of them.
    ring = [camera((5 * math.cos(a), 5 * math.sin(a), 0.2)) for a in torch.linspace(0, 2 * math.pi, 9)[:-1]]
    top = camera((0.0, 0.3, 5.0))                                      # looks into the box
    far = camera((15 * math.cos(0.1), 15 * math.sin(0.1), 0.6))       # farthest from every captured centre
    between = camera((5 * math.cos(0.4), 5 * math.sin(0.4), 0.2))     # between two captured poses
    candidates = [far, between, top]
    order = ranking(name, renderer, candidates, ring, 1).order
    assert order[0] == 2
    # The centres alone say the opposite: farthest-view sampling takes the far pose.
    assert ranking("fvs", renderer, candidates, ring, 1).order[0] == 0


def test_cameras_at_one_centre_looking_different_ways_score_by_what_they_see() -> None:
    # Two clusters on either side of the origin; the captured camera at the origin saw +x only.
    east = grid((2.0, -0.5, -0.5), (0, 1, 0), (0, 0, 1))
    west = grid((-2.0, -0.5, -0.5), (0, 1, 0), (0, 0, 1))
    renderer = GaussianRenderer(splats([east, west], 0.1))
    captured = [camera((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))]
    candidates = [camera((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), camera((0.0, 0.0, 0.0), (-1.0, 0.0, 0.0)),
                  camera((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))]            # the last sees nothing
    for name in ("visibility", "visibility_sigma", "visibility_sigma_fvs"):
        selection = ranking(name, renderer, candidates, captured, 1)
        assert selection.order[0] == 1                                 # faces the unseen cluster
        # The seen side is worth little: only what the captured view saw less than a quarter of
        # (SEEN_SHARE) still counts, in part.
        assert selection.scores[1] > 5 * selection.scores[0]
    # All three stand at the captured centre: the centre distance cannot tell them apart.
    fvs = ranking("fvs", renderer, candidates, captured, 3)
    assert len(set(fvs.scores)) == 1


@pytest.mark.parametrize("name", ["visibility", "visibility_sigma", "visibility_sigma_fvs"])
def test_identical_candidates_never_share_a_batch(name: str) -> None:
    renderer = open_box()
    captured = [camera((5.0, 0.0, 0.2))]
    top, back = camera((0.0, 0.3, 5.0)), camera((-5.0, 0.2, 0.2))
    candidates = [back, top, back, camera((0.0, 5.0, 0.2))]
    order = ranking(name, renderer, candidates, captured, 2).order
    assert order[0] in (0, 2)                   # the side opposite the captured pose is the best single pick
    assert not {0, 2} <= set(order[:2])


def test_a_pick_lowers_the_value_of_candidates_that_see_the_same_parts() -> None:
    renderer = open_box()
    captured = [camera((5.0, 0.0, 0.2))]
    candidates = [camera((-5.0, 0.2, 0.2)), camera((-5.0, 0.5, 0.4)), camera((0.0, 0.3, 5.0))]
    evidence = visibility_evidence(renderer, candidates, captured)
    coverage = Coverage(evidence.candidate_views, fragility=False)
    for vis in evidence.captured_views:
        coverage.capture(vis)
    before = [coverage.value(c) for c in range(len(candidates))]
    coverage.capture(evidence.candidate_views[0])                       # pick the first
    after = [coverage.value(c) for c in range(len(candidates))]
    assert after[0] < 0.05 * before[0]                                  # nothing left to see from there
    assert after[1] < 0.3 * before[1]                                   # its near twin saw the same walls
    assert after[2] > 0.7 * before[2]                                   # the inside, seen from above, barely moved


def test_retired_candidates_leave_the_others_values_as_they_were() -> None:
    """Picked candidates leave Coverage's list once they hold half of it: the candidates still in
    play keep exactly the values they have when nobody is retired."""
    renderer = open_box()
    candidates = [camera((5.0 * math.cos(a), 5.0 * math.sin(a), 0.3 + 0.2 * math.sin(3 * a)))
                  for a in torch.linspace(0.0, 2 * math.pi, 9)[:-1].tolist()] + [camera((0.0, 0.3, 5.0))]
    evidence = visibility_evidence(renderer, candidates, [camera((5.0, 0.0, 0.2))])
    kept, retiring = (Coverage(evidence.candidate_views, fragility=False) for _ in range(2))
    for coverage in (kept, retiring):
        for vis in evidence.captured_views:
            coverage.capture(vis)
    picks = [0, 4, 2, 6, 8, 1]
    for step, i in enumerate(picks):
        for coverage in (kept, retiring):
            coverage.capture(evidence.candidate_views[i])
        retiring.retire(i)
        rest = [c for c in range(len(candidates)) if c not in picks[:step + 1]]
        assert [retiring.value(c) for c in rest] == [kept.value(c) for c in rest]
    assert len(retiring.ids) < len(candidates) and len(retiring.index) < len(kept.index)    # the list shrank


def test_families_without_visibility_get_the_camera_centre_order() -> None:
    renderer = BlobRenderer.random(20, seed=1)
    ring = ring_cameras(8)
    evidence = visibility_evidence(renderer, ring[1:], ring[:1])
    assert evidence.candidate_views is None
    assert (get_strategy("visibility").select(evidence, 3, 0).order
            == get_strategy("fvs_sigma_floor").select(evidence, 3, 0).order)


def test_coverage_selection_trusts_the_model_whose_training_views_saw_the_view_not_the_nearest_centre() -> None:
    renderer = open_box()
    # Model a's training views: a ring around the walls and one camera just below the test view
    # looking up, away from the box (nearest centre, sees nothing). Model b's: one camera looking in.
    ring = [camera((5 * math.cos(a), 5 * math.sin(a), 0.2)) for a in torch.linspace(0, 2 * math.pi, 7)[:-1]]
    training_a = ring + [camera((0.0, 0.3, 11.0), (0.0, 0.3, 20.0))]
    training_b = [camera((0.2, 0.3, 5.0))]
    view = camera((0.0, 0.3, 12.0))                                      # looks into the box from above
    choose = lambda rule: select_models(renderer, renderer, [view], ratio_a=0.1, ratio_b=0.1, samples=4,  # noqa: E731
                                        rule=rule, training_a=training_a, training_b=training_b).views[0]
    assert choose("distance_sigma").choice == "a"                        # fooled by the centre one unit away
    chosen = choose("coverage_sigma")
    assert chosen.choice == "b" and chosen.score_b < chosen.score_a


def test_checked_coverage_selection_finds_the_model_that_is_only_right_where_it_was_trained() -> None:
    # One ball of splats, two models. Model b's colour has a view-dependent error (an SH degree-1
    # term along x) that vanishes for views along z, where its training cameras are; model a is
    # the truth and was trained on a ring around the equator. Views from between see parts b's
    # cameras covered from a nearby direction, so coverage alone trusts b there.
    points = torch.randn(300, 3, generator=torch.Generator().manual_seed(0))
    ball = splats([0.8 * points / points.norm(dim=1, keepdim=True)], 0.15)

    def with_error(error: float) -> GaussianRenderer:
        sh = torch.zeros(len(ball.means), 4, 3)
        sh[:, 0] = torch.rand(len(ball.means), 3, generator=torch.Generator().manual_seed(1)) - 0.5
        sh[:, 3] = error                                                 # basis -C1 x of the view direction
        return GaussianRenderer(GaussianModel(ball.means, ball.log_scales, ball.quats, ball.opacity_logits, sh))

    truth, wrong = with_error(0.0), with_error(1.0)
    ring = [camera((4 * math.cos(t), 4 * math.sin(t), 0.3)) for t in torch.linspace(0, 2 * math.pi, 9)[:-1].tolist()]
    top = [camera((0.3 * math.cos(t), 0.3 * math.sin(t), 4.0)) for t in (0.0, 2.0, 4.0)]
    views = [camera((4 * math.sin(e) * math.cos(t), 4 * math.sin(e) * math.sin(t), 4 * math.cos(e)))
             for e in (0.35, 0.6, 0.9) for t in (0.3, 1.9, 3.5, 5.0)]

    def choices(rule: str) -> list[str]:
        result = select_models(truth, wrong, views, ratio_a=0.1, ratio_b=0.1, samples=8, rule=rule,
                               training_a=ring, training_b=top)
        return [view.choice for view in result.views]

    assert choices("coverage_sigma").count("b") >= 4                    # trusts b where its cameras looked
    # Checked against each other where each was trained: b's renders differ from a's on a's ring,
    # a's equal b's on b's cameras (b is right there), so a's error per unit of score is about 0.
    assert choices("coverage_checked") == ["a"] * len(views)


def test_fisher_diagonal_by_random_projections_matches_the_jacobian() -> None:
    east = grid((0.0, -0.3, -0.3), (0, 0.6, 0), (0, 0, 0.6), steps=2)     # 4 splats, partly overlapping
    renderer = GaussianRenderer(splats([east], 0.25))
    view = look_at((3.0, 0.2, 0.1), (0.0, 0.0, 0.0), width=7, height=6, fov_x=0.5)
    leaves = [t.detach().clone() for t in renderer.model.tensors()]

    def image(*tensors):
        return renderer.rasterizer(type(renderer.model)(*tensors), view, renderer.background).rgb[0].reshape(-1)

    jacobians = torch.autograd.functional.jacobian(image, tuple(leaves))   # per tensor [pixels, *shape]
    exact = torch.stack([j.double().square().sum(0).reshape(4, -1).sum(1) for j in jacobians], 1)   # [G, 5]
    estimate = renderer.fisher(view, probes=400, seed=1)         # relative error per entry about sqrt(2 / 400)
    assert exact.sum() > 0
    torch.testing.assert_close(estimate, exact, rtol=0.25, atol=1e-3 * float(exact.max()))


def test_fisher_prefers_the_view_that_informs_what_the_captured_views_left_unconstrained() -> None:
    east = grid((2.0, -0.5, -0.5), (0, 1, 0), (0, 0, 1), steps=6)
    west = grid((-2.0, -0.5, -0.5), (0, 1, 0), (0, 0, 1), steps=6)
    renderer = GaussianRenderer(splats([east, west], 0.1))
    captured = [camera((6.0, 0.0, 0.0))]                                   # sees the east cluster only
    candidates = [camera((6.0, 0.3, 0.2)), camera((-6.0, 0.0, 0.0))]
    evidence = add_fisher(visibility_evidence(renderer, candidates, captured), renderer)
    ranked = get_strategy("fisher").select(evidence, 2, 0)
    assert ranked.order[0] == 1
    assert ranked.scores[1] > 10 * ranked.scores[0]


def test_candidates_that_see_nothing_of_the_model_rank_without_error() -> None:
    renderer = open_box()
    captured = [camera((5.0, 0.0, 0.2))]
    away = [camera((5.0, 0.0, 0.2), (12.0, 0.0, 0.2)), camera((0.0, 5.0, 0.2), (0.0, 12.0, 0.2))]
    selection = get_strategy("visibility").select(visibility_evidence(renderer, away, captured), 2, 0)
    assert sorted(selection.order) == [0, 1] and selection.scores == [0.0, 0.0]


def test_the_default_takes_the_farther_of_two_candidates_that_see_the_same_unseen_parts() -> None:
    # Two candidates see the same element, unseen by the captured view, equally (hand-built
    # Visibility: same element, weight and direction), from centres 10 and 15 away from the
    # captured one. Coverage alone ties them (the lower index wins); the default weighs the
    # distance to the nearest captured centre and takes the farther one.
    def seen(cam, element: int) -> Visibility:
        one = torch.ones(1, dtype=torch.float64)
        return Visibility(camera=cam, elements=torch.tensor([element]), points=torch.zeros(1, 3, dtype=torch.float64),
                          weight=50 * one, footprint=50 * one, valued=None, empty=0.0, in_box=0)
    captured = camera((5.0, 0.0, 0.0))
    near_one, far_one = camera((-5.0, 0.0, 0.0)), camera((-10.0, 0.0, 0.0))
    zeros = torch.zeros(2, dtype=torch.float64)
    evidence = Evidence([near_one, far_one], [captured], zeros, zeros,
                        candidate_views=[seen(near_one, 1), seen(far_one, 1)], captured_views=[seen(captured, 0)])
    coverage_only = get_strategy("visibility_sigma").select(evidence, 0, 0)      # scores before any pick
    assert coverage_only.scores[0] == coverage_only.scores[1] and coverage_only.order[0] == 0
    default = get_strategy("visibility_sigma_fvs").select(evidence, 0, 0)
    assert default.order[0] == 1
    assert default.scores[1] == pytest.approx(1.5 * default.scores[0])        # 15 against 10 from the captured centre


def full_scan_coverage(evidence: Evidence, k: int, fragility: bool, spread: bool) -> tuple[list[int], list[float], int]:
    """The coverage order as a plain full greedy: every candidate's novelty recomputed from every
    view counted as captured, every value rescored at every pick. (order, scores, values computed)."""
    views, count = evidence.candidate_views, len(evidence.candidates)
    reference = mean_zeta(views) if fragility else 0.0
    weights = []
    for vis in views:
        weight = vis.weight.clone()
        if fragility and reference > 0 and vis.valued is not None:
            weight *= 1.0 + vis.valued / vis.weight.clamp_min(1e-300) / reference
        weights.append(weight)
    centre = torch.stack([c.center for c in evidence.candidates])
    nearest = (torch.cdist(centre, torch.stack([c.center for c in evidence.captured])).min(dim=1).values
               if spread else torch.ones(count, dtype=torch.float64))
    floor = SPREAD_FLOOR * float(nearest.mean()) or 1.0

    def value(c: int, seen_by: list) -> float:
        vis, novelty, axis = views[c], torch.ones(len(views[c].elements), dtype=torch.float64), 1.0
        for other in seen_by:
            mine = torch.isin(vis.elements, other.elements)
            theirs = torch.isin(other.elements, vis.elements)
            share = (other.visible_share[theirs] / SEEN_SHARE).clamp_max(1.0)
            points = vis.points[mine]
            toward = (other.camera.center - points) / (other.camera.center - points).norm(dim=-1, keepdim=True)
            mine_dirs = (vis.camera.center - vis.points[mine])
            mine_dirs = mine_dirs / mine_dirs.norm(dim=-1, keepdim=True)
            novelty[mine] *= 1.0 - share * torch.exp(-(1.0 - (mine_dirs * toward).sum(-1)) / ANGLE_SCALE)
            axis *= 1.0 - float(torch.exp(-(1.0 - (viewing_axis(vis) * viewing_axis(other)).sum()) / ANGLE_SCALE))
        total = float((weights[c] * novelty).sum()) + EMPTY_WEIGHT * vis.empty * axis
        return total * max(float(nearest[c]), floor)

    seen_by, order, scores, computed = list(evidence.captured_views), [], [0.0] * count, 0
    for _ in range(k):
        values = {c: value(c, seen_by) for c in range(count) if c not in order}
        computed += len(values)
        best = max(values, key=lambda c: (values[c], -c))
        order.append(best)
        scores[best] = values[best]
        seen_by.append(views[best])
        if spread:
            nearest = torch.minimum(nearest, (centre - centre[best]).norm(dim=1))
    rest = {c: value(c, seen_by) for c in range(count) if c not in order}
    scores = [rest.get(c, s) for c, s in enumerate(scores)]
    return order + sorted(rest, key=lambda c: (-rest[c], c)), scores, computed


@pytest.mark.parametrize("fragility, spread", [(False, False), (True, False), (True, True)])
def test_the_lazy_greedy_picks_and_scores_what_a_full_greedy_does_with_fewer_updates(fragility: bool,
                                                                                     spread: bool) -> None:
    # Ring candidates around a cluster of splats seen from two sides: many candidates share parts.
    renderer = GaussianRenderer(svc_random_gaussians(600, seed=3))
    candidates = ring_cameras(14, size=24, radius=3.0, height=0.8)
    candidates += [look_at((0.3, 0.2, 3.5), (0, 0, 0), (0, 1, 0), width=24, height=24, fov_x=0.7)] * 2
    captured = ring_cameras(3, size=24, radius=3.5, height=-0.5)
    evidence, _ = candidate_evidence(renderer, candidates, ratio=0.4, samples=4, captured=captured, visibility=True)
    counted = []
    original = Coverage._sum

    def counting(self: Coverage, c: int) -> float:
        counted.append(bool(self.changed[c]))
        return original(self, c)

    Coverage._sum = counting         # type: ignore[method-assign]
    try:
        lazy = coverage_select(evidence, len(candidates), fragility, spread=spread)
    finally:
        Coverage._sum = original     # type: ignore[method-assign]
    order, scores, computed = full_scan_coverage(evidence, len(candidates), fragility, spread)
    assert lazy.order == order
    assert lazy.scores == scores                            # bit for bit
    assert len(set(order[:2])) == 2 and {14, 15} & set(order[:2]) != {14, 15}   # the twins split
    assert sum(counted) < computed / 2                      # sums redone only for the candidates asked for


@pytest.mark.parametrize("size", [1, 7, 1000])
def test_the_counting_order_is_torchs_stable_argsort(size: int) -> None:
    keys = torch.randint(0, size, (5000,), generator=torch.Generator().manual_seed(size))
    assert torch.equal(stable_order(keys, size), torch.argsort(keys, stable=True))
    assert len(stable_order(torch.zeros(0, dtype=torch.long), size)) == 0
