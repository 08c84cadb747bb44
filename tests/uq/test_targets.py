"""Target views: where the model will be looked at from weights what the coverage strategies value.

On hand-built splat scenes (the open box of test_visibility_strategy: walls around a cluster
that only a view from above sees), checked against a per-element float64 evaluation of the
documented formula and through `rank_views`."""

from __future__ import annotations

import math
from typing import Sequence

import pytest
import torch
from uq.test_visibility_strategy import camera, open_box

from phd_core.errors import InputError
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.visibility import Seen, Visibility
from phd_core.scene import Camera
from phd_core.uq import rank_views
from phd_core.uq.rank import visibility_evidence
from phd_core.uq.strategies import Evidence, get_strategy
from phd_core.uq.strategies.visibility import ANGLE_SCALE, EMPTY_WEIGHT, SEEN_SHARE
from support.toy_renderers import BlobRenderer, ring_cameras

COVERAGE = ["visibility", "visibility_sigma", "visibility_sigma_fvs"]
CAPTURED = [camera((5.0, 0.0, 0.2))]
BACK, TOP = camera((-5.0, 0.2, 0.2)), camera((0.0, 0.3, 5.0))      # sees the far wall | into the box
ABOVE = [camera((0.4, 0.0, 6.0)), camera((-0.3, 0.4, 5.5))]         # targets: the inside, from above
BEHIND = [camera((-6.0, -0.5, 0.5)), camera((-5.5, 0.6, 0.1))]      # targets: the far wall


def best(name: str, renderer: GaussianRenderer, targets: list | None) -> int:
    return get_strategy(name).select(visibility_evidence(renderer, [BACK, TOP], CAPTURED, targets), 1, 0).order[0]


@pytest.mark.parametrize("name", COVERAGE)
def test_targets_behind_an_occluder_make_the_candidate_that_sees_them_win(name: str) -> None:
    renderer = open_box()
    assert best(name, renderer, None) == 0              # without targets: the large unseen far wall
    assert best(name, renderer, ABOVE) == 1             # told the model is looked at from above: the inside
    assert best(name, renderer, BEHIND) == 0            # told it is looked at from behind: the far wall


def test_a_part_no_target_shows_is_worth_nothing() -> None:
    renderer = open_box()
    far_away = [camera((0.0, 0.0, 5.0), (0.0, 0.0, 12.0))]         # looks up, away from the box: shows nothing
    scores = get_strategy("visibility").select(visibility_evidence(renderer, [BACK, TOP], CAPTURED, far_away),
                                                0, 0).scores
    # What is left is the empty-box term alone (both candidates still look into the scene box).
    plain = visibility_evidence(renderer, [BACK, TOP], CAPTURED)
    assert plain.candidate_views is not None
    for c, vis in enumerate(plain.candidate_views):
        axis_novelty = reference_axis_novelty(vis, plain.captured_views or [])
        assert scores[c] == pytest.approx(EMPTY_WEIGHT * vis.empty * axis_novelty, rel=1e-12)


def seen(vis: Visibility) -> dict[int, tuple[float, torch.Tensor]]:
    """Element id -> (min(1, visible share / SEEN_SHARE), its point), one dict entry at a time."""
    share = (vis.weight / vis.footprint.clamp_min(1e-300)).clamp(0, 1)
    return {int(e): (min(1.0, float(s) / SEEN_SHARE), p) for e, s, p in zip(vis.elements, share, vis.points)}


def near(point: torch.Tensor, a: Camera, b: Camera) -> float:
    da, db = a.center - point, b.center - point
    cos = float(da @ db) / max(float(da.norm() * db.norm()), 1e-300)
    return math.exp(-(1.0 - cos) / ANGLE_SCALE)


def reference_axis_novelty(vis: Visibility, captured: Sequence[Visibility | Seen]) -> float:
    axis = -vis.camera.c2w[:3, 2]
    return math.prod(1.0 - math.exp(-(1.0 - float(axis @ -v.camera.c2w[:3, 2])) / ANGLE_SCALE) for v in captured)


def reference_values(evidence: Evidence) -> list[float]:
    """`visibility`'s value of each candidate before any pick, element by element in float64:
    sum over u of weight(u, c) * prod over captured v (1 - seen(u, v) near(u; c, v)) plus the
    empty term; weight = the pixels u fills in c, or with targets seen(u, c) times the mean over
    targets t of the pixels u fills in t times near(u; c, t)."""
    # The captured views come as the library stores them (`Seen`: ids and visible shares).
    captured = [(v.camera, {int(e): min(1.0, float(s) / SEEN_SHARE) for e, s in zip(v.elements, v.visible_share)})
                for v in evidence.captured_views or []]
    targets = [(t.camera, {int(e): float(w) for e, w in zip(t.elements, t.weight)})
               for t in evidence.target_views or []]
    values = []
    for vis in evidence.candidate_views or []:
        fills = {int(e): float(w) for e, w in zip(vis.elements, vis.weight)}
        total = 0.0
        for element, (share, point) in seen(vis).items():
            if evidence.target_views is None:
                weight = fills[element]
            else:
                weight = share * sum(pixels.get(element, 0.0) * near(point, vis.camera, cam)
                                     for cam, pixels in targets) / len(targets)
            novelty = math.prod(1.0 - by[element] * near(point, vis.camera, cam)
                                for cam, by in captured if element in by)
            total += weight * novelty
        values.append(total + EMPTY_WEIGHT * vis.empty * reference_axis_novelty(vis, evidence.captured_views or []))
    return values


@pytest.mark.parametrize("targets", [None, ABOVE, ABOVE + BEHIND], ids=["no targets", "above", "above and behind"])
def test_coverage_values_follow_the_formula_element_by_element(targets: list | None) -> None:
    renderer = open_box()
    candidates = [BACK, TOP, camera((3.0, 3.5, 1.5)), camera((0.5, -4.0, 3.0))]
    captured = CAPTURED + [camera((0.0, 5.0, 0.5))]
    evidence = visibility_evidence(renderer, candidates, captured, targets)
    scores = get_strategy("visibility").select(evidence, 0, 0).scores       # k = 0: every value before a pick
    assert scores == pytest.approx(reference_values(evidence), rel=1e-9, abs=1e-9)


def test_without_targets_a_ranking_is_the_one_made_before_targets_existed() -> None:
    """targets=None leaves the evidence as it was (no target views) and every value equal to the
    pixels-weighted formula; an explicit target list changes them."""
    renderer = open_box()
    candidates = [BACK, TOP, camera((3.0, 3.5, 1.5))]
    plain = rank_views(renderer, candidates, ratio=0.3, samples=6, seed=1, captured=CAPTURED)
    again = rank_views(renderer, candidates, ratio=0.3, samples=6, seed=1, captured=CAPTURED, targets=None)
    told = rank_views(renderer, candidates, ratio=0.3, samples=6, seed=1, captured=CAPTURED, targets=ABOVE)
    assert [(r.index, r.score, r.sigma_max) for r in plain] == [(r.index, r.score, r.sigma_max) for r in again]
    assert [r.index for r in told][0] == 1 and [r.index for r in plain][0] == 0
    assert [r.sigma_max for r in sorted(told, key=lambda r: r.index)] == \
        [r.sigma_max for r in sorted(plain, key=lambda r: r.index)]      # the dropout statistics do not move


def test_targets_are_refused_where_they_cannot_count() -> None:
    renderer = open_box()
    with pytest.raises(InputError) as error:
        rank_views(renderer, [BACK, TOP], ratio=0.3, samples=4, captured=CAPTURED, strategy="fvs", targets=ABOVE)
    assert error.value.field == "targets" and "ignores target views" in str(error.value)
    with pytest.raises(InputError) as error:
        rank_views(renderer, [BACK, TOP], ratio=0.3, samples=4, captured=CAPTURED, targets=[])
    assert error.value.field == "targets"
    blobs = BlobRenderer.random(20, seed=1)                              # a family without visibility
    ring = ring_cameras(6)
    with pytest.raises(InputError) as error:
        rank_views(blobs, ring[1:], ratio=0.3, samples=4, captured=ring[:1], targets=ring[:2])
    assert error.value.field == "targets" and "cannot report" in str(error.value)
