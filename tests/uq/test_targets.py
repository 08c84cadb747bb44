"""Target views: told where the model will be looked at from, a candidate is worth what it fixes in those views.

On hand-built splat scenes (the open box of test_visibility_strategy: walls around a cluster
that only a view from above sees; a ring around a splat cluster; a wall along a path), checked
against a per-element float64 evaluation of the documented formula, a full-scan greedy and
through `rank_views`."""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import pytest
import torch
from uq.test_visibility_strategy import SIZE, camera, open_box, splats

from phd_core.errors import InputError
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.visibility import Seen, Visibility
from phd_core.scene import Camera, look_at
from phd_core.uq import rank_views
from phd_core.uq.rank import candidate_evidence, visibility_evidence
from phd_core.uq.strategies import Evidence, get_strategy
from phd_core.uq.strategies.coverage import ANGLE_SCALE, EMPTY_WEIGHT, SEEN_SHARE
from phd_core.uq.strategies.targets import walked
from phd_core.uq.strategies.visibility import SPREAD_FLOOR, coverage_select
from support.fixtures import svc_random_gaussians
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
    for name in COVERAGE:
        scores = get_strategy(name).select(visibility_evidence(renderer, [BACK, TOP], CAPTURED, far_away), 0, 0).scores
        assert scores == [0.0, 0.0]      # nothing to fix in the targets (empty space does not count with targets)


def seen(vis: Visibility) -> dict[int, tuple[float, torch.Tensor]]:
    """Element id -> (min(1, visible share / SEEN_SHARE), its point), one dict entry at a time."""
    share = (vis.weight / vis.footprint.clamp_min(1e-300)).clamp(0, 1)
    return {e: (min(1.0, s / SEEN_SHARE), tuple(p))
            for e, s, p in zip(vis.elements.tolist(), share.tolist(), vis.points.tolist())}


Point = tuple[float, ...]


def centre(camera: Camera) -> Point:
    return tuple(camera.center.tolist())


def near(point: Point, a: Point, b: Point) -> float:
    """exp(-(1 - cos angle(point; a, b)) / ANGLE_SCALE) for camera centres a and b, in Python floats
    (float64, element by element: fast enough to rescore every candidate after every pick)."""
    da, db = [x - p for x, p in zip(a, point)], [x - p for x, p in zip(b, point)]
    cos = sum(x * y for x, y in zip(da, db)) / max(math.hypot(*da) * math.hypot(*db), 1e-300)
    return math.exp(-(1.0 - cos) / ANGLE_SCALE)


def reference_axis_novelty(vis: Visibility, captured: Sequence[Visibility | Seen]) -> float:
    axis = -vis.camera.c2w[:3, 2]
    return math.prod(1.0 - math.exp(-(1.0 - float(axis @ -v.camera.c2w[:3, 2])) / ANGLE_SCALE) for v in captured)


def reference_fragility(evidence: Evidence, fragility: bool) -> list[dict[int, float]]:
    """Per candidate, element id -> 1 + mean zeta on its pixels / that mean over every candidate (1 without)."""
    views = evidence.candidate_views or []
    valued = [v for v in views if v.valued is not None]
    scale = sum(float(v.valued.sum()) for v in valued) / max(sum(float(v.weight.sum()) for v in valued), 1e-300)
    return [{e: 1.0 + (z / max(w, 1e-300) / scale if fragility and v.valued is not None else 0.0)
             for e, w, z in zip(v.elements.tolist(), v.weight.tolist(),
                                (v.valued if v.valued is not None else v.weight).tolist())}
            for v in views]


def reference_values(evidence: Evidence, fragility: bool = False, picked: Sequence[int] = (),
                     support: float = 1.0) -> list[float]:
    """Each candidate's value element by element in float64, with the candidates `picked` counted as
    captured. Without targets (`visibility`, before any pick): sum over u of the pixels u fills in c
    times prod over captured v (1 - seen(u, v) near(u; c, v)), plus the empty term. With targets:
    sum over u that c sees and targets t that show u of pixels(u, t) * n_t(u) * seen(u, c) *
    near(u; t, c) * fragility(u, c), n_t(u) = prod over captured v (1 - seen(u, v) near(u; t, v)).
    support: every seen(u, v) (of a captured view or the candidate) times it."""
    # The captured views come as the library stores them (`Seen`: ids and visible shares).
    captured = [(centre(v.camera), {e: support * min(1.0, s / SEEN_SHARE)
                                    for e, s in zip(v.elements.tolist(), v.visible_share.tolist())})
                for v in evidence.captured_views or []]
    candidates = evidence.candidate_views or []
    captured += [(centre(candidates[c].camera), {e: support * share for e, (share, _) in seen(candidates[c]).items()})
                 for c in picked]
    # Per target t: element id -> (pixels it fills in t, its point, n_t(u)).
    targets = []
    for t in evidence.target_views or []:
        at_t = centre(t.camera)
        targets.append((at_t, {e: (w, tuple(p), math.prod(1.0 - by[e] * near(tuple(p), at_t, cam)
                                                          for cam, by in captured if e in by))
                               for e, w, p in zip(t.elements.tolist(), t.weight.tolist(), t.points.tolist())}))
    scale = reference_fragility(evidence, fragility)
    values = []
    for c, vis in enumerate(candidates):
        fills = dict(zip(vis.elements.tolist(), vis.weight.tolist()))
        total = 0.0
        at_c = centre(vis.camera)
        for element, (share, point) in seen(vis).items():
            if evidence.target_views is None:
                novelty = math.prod(1.0 - by[element] * near(point, at_c, cam)
                                    for cam, by in captured if element in by)
                total += fills[element] * novelty
                continue
            for target, shows in targets:
                if element in shows:
                    pixels, at, novelty = shows[element]
                    total += pixels * novelty * support * share * near(at, target, at_c) * scale[c][element]
        if evidence.target_views is None:
            total += EMPTY_WEIGHT * vis.empty * reference_axis_novelty(vis, evidence.captured_views or [])
        values.append(total)
    return values


@pytest.mark.parametrize("targets", [None, ABOVE, ABOVE + BEHIND], ids=["no targets", "above", "above and behind"])
def test_coverage_values_follow_the_formula_element_by_element(targets: list | None) -> None:
    renderer = open_box()
    candidates = [BACK, TOP, camera((3.0, 3.5, 1.5)), camera((0.5, -4.0, 3.0))]
    captured = CAPTURED + [camera((0.0, 5.0, 0.5))]
    evidence = visibility_evidence(renderer, candidates, captured, targets)
    scores = get_strategy("visibility").select(evidence, 0, 0).scores       # k = 0: every value before a pick
    assert scores == pytest.approx(reference_values(evidence), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("targets", [None, ABOVE + BEHIND], ids=["no targets", "above and behind"])
def test_a_view_removes_only_its_support_of_what_it_saw(targets: list | None) -> None:
    """support < 1 (bench/nbv_experiments.py's multi-view support): every seen(u, v) times it, in the
    captured views' factors and, with targets, in the candidate's own; without targets a part seen
    before is then worth more than with support 1, never less."""
    renderer = open_box()
    candidates = [BACK, TOP, camera((3.0, 3.5, 1.5)), camera((0.5, -4.0, 3.0))]
    captured = CAPTURED + [camera((0.0, 5.0, 0.5))]
    evidence = visibility_evidence(renderer, candidates, captured, targets)
    half = coverage_select(evidence, 0, fragility=False, support=0.5).scores
    whole = coverage_select(evidence, 0, fragility=False).scores
    assert half == pytest.approx(reference_values(evidence, support=0.5), rel=1e-9, abs=1e-9)
    assert half != pytest.approx(whole, rel=1e-3)
    if targets is None:
        assert all(h >= w for h, w in zip(half, whole))


def ring_evidence() -> Evidence:
    """Ring candidates (and two twins above) around a cluster of splats, three captured views below,
    targets on a lower ring; with PH-Dropout statistics, so fragility has its zeta."""
    renderer = GaussianRenderer(svc_random_gaussians(400, seed=3))
    candidates = ring_cameras(8, size=20, radius=3.0, height=0.8)
    candidates += [look_at((0.3, 0.2, 3.5), (0, 0, 0), (0, 1, 0), width=20, height=20, fov_x=0.7)] * 2
    captured = ring_cameras(3, size=20, radius=3.5, height=-0.5)
    targets = [look_at((2.5 * math.cos(a), 2.5 * math.sin(a), 0.3), (0, 0, 0), (0, 0, 1), width=20, height=20,
                       fov_x=0.7) for a in (0.3, 1.1, 1.9, 4.0)]
    return candidate_evidence(renderer, candidates, ratio=0.4, samples=4, captured=captured, visibility=True,
                              targets=targets)[0]


@pytest.mark.parametrize("name", ["visibility", "visibility_sigma"])
def test_target_gains_follow_the_formula_with_and_without_fragility(name: str) -> None:
    evidence = ring_evidence()
    scores = get_strategy(name).select(evidence, 0, 0).scores
    expected = reference_values(evidence, fragility=name == "visibility_sigma")
    assert min(expected) >= 0 and max(expected) > 0
    assert scores == pytest.approx(expected, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("name, power", [(name, 1.0) for name in COVERAGE] + [("visibility_sigma_fvs", 0.5)])
def test_the_lazy_greedy_on_targets_picks_what_a_full_scan_greedy_does(name: str, power: float) -> None:
    """Every candidate rescored from scratch (the reference formula) after every pick, the best
    (lowest index on ties) counted as captured, against the strategy's lazy greedy (power: the
    distance factor's exponent, `spread_power`, tried in bench/nbv_experiments.py)."""
    evidence = ring_evidence()
    fragility, spread = name != "visibility", name == "visibility_sigma_fvs"
    centre = torch.stack([c.center for c in evidence.candidates])
    nearest = [min(float((c - o.center).norm()) for o in evidence.captured) if spread else 1.0 for c in centre]
    floor = SPREAD_FLOOR * sum(nearest) / len(nearest)

    def values(picked: list[int]) -> list[float]:
        return [v * max(d, floor) ** power for v, d in zip(reference_values(evidence, fragility, picked), nearest)]
    picks = 5
    order: list[int] = []
    for _ in range(picks):
        now = values(order)
        best = max((c for c in range(len(now)) if c not in order), key=lambda c: (now[c], -c))
        order.append(best)
        if spread:
            nearest = [min(d, float((c - centre[best]).norm())) for d, c in zip(nearest, centre)]
    lazy = (get_strategy(name).select(evidence, picks, 0) if power == 1.0
            else coverage_select(evidence, picks, fragility, spread=spread, spread_power=power))
    assert lazy.order[:picks] == order
    assert not {8, 9} <= set(order[:2])                        # the twins above never share a batch
    after = values(order)
    rest = lazy.order[picks:]
    assert [lazy.scores[c] for c in rest] == pytest.approx([after[c] for c in rest], rel=1e-9, abs=1e-12)


def test_targets_are_the_captures_own_path_when_most_stand_where_the_camera_stands() -> None:
    stands = torch.tensor([[3.0, 0.0, 1.0], [0.0, 3.0, 1.0], [-3.0, 0.0, 1.0], [0.0, -3.0, 1.0]], dtype=torch.float64)
    elsewhere = torch.tensor([[2.0, 2.0, 2.0], [-2.0, 2.0, 2.0]], dtype=torch.float64)
    assert walked(stands, stands)                                        # the capture's own frames
    assert walked(stands[:2] + 1e-9, stands)                             # parsed again: rounding apart
    assert walked(torch.cat([stands[:2], elsewhere]), stands)            # half of them: a path with detours
    assert not walked(torch.cat([stands[:1], elsewhere]), stands)        # a third
    assert not walked(stands + 1e-4, stands)                             # beside the path, not on it
    assert not walked(elsewhere, stands) and not walked(stands[:0], stands) and not walked(stands, stands[:0])


def walk_evidence() -> Evidence:
    """ring_evidence's scene and candidates, told as targets every pose the camera stands at (the
    candidates and the captured views): a capture told its own frames."""
    evidence = ring_evidence()
    assert evidence.candidate_views is not None
    stands = [view.camera for view in evidence.candidate_views] + list(evidence.captured)
    renderer = GaussianRenderer(svc_random_gaussians(400, seed=3))
    return dataclasses.replace(evidence, target_views=[renderer.visibility(renderer.prepare(c)) for c in stands])


def test_told_its_own_frames_the_default_follows_the_targets_density_as_a_full_scan_greedy_does() -> None:
    """The default told the capture's own frames: each candidate's target gain (no fragility) times
    how much it lowers the targets' log distance to their nearest captured centre (eps the median
    distance from a target to its nearest other target), rescored from scratch in float64 after
    every pick, against the lazy greedy; and the order is not the distance factor's."""
    evidence = walk_evidence()
    assert evidence.target_views is not None
    aimed = [view.camera.center for view in evidence.target_views]
    centre = [c.center for c in evidence.candidates]
    apart = sorted(min(float((a - b).norm()) for j, b in enumerate(aimed) if j != i and float((a - b).norm()) > 0)
                   for i, a in enumerate(aimed))
    eps = (apart[(len(apart) - 1) // 2])                      # torch's median: the lower middle value

    def density(picked: list[int]) -> list[float]:
        nearest = [min(float((t - o).norm()) for o in [c.center for c in evidence.captured]
                       + [centre[p] for p in picked]) for t in aimed]
        return [sum(math.log(n + eps) - math.log(min(n, float((t - c).norm())) + eps) for n, t in zip(nearest, aimed))
                for c in centre]

    def values(picked: list[int]) -> list[float]:
        return [g * d for g, d in zip(reference_values(evidence, False, picked), density(picked))]
    picks = 5
    order: list[int] = []
    for _ in range(picks):
        now = values(order)
        order.append(max((c for c in range(len(now)) if c not in order), key=lambda c: (now[c], -c)))
    lazy = get_strategy("visibility_sigma_fvs").select(evidence, picks, 0)
    assert lazy.order[:picks] == order
    after = values(order)
    rest = lazy.order[picks:]
    assert [lazy.scores[c] for c in rest] == pytest.approx([after[c] for c in rest], rel=1e-9, abs=1e-12)
    spread = dataclasses.replace(evidence, target_views=evidence.target_views[:1])   # one target: not the path
    assert get_strategy("visibility_sigma_fvs").select(spread, picks, 0).order[:picks] != order


def wall() -> GaussianRenderer:
    """A long wall of splats along x (y = 0), 2 high."""
    x, z = torch.meshgrid(torch.linspace(-10, 10, 81, dtype=torch.float64),
                          torch.linspace(-1, 1, 9, dtype=torch.float64), indexing="ij")
    return GaussianRenderer(splats([torch.stack([x.reshape(-1), torch.zeros(x.numel(), dtype=torch.float64),
                                                 z.reshape(-1)], 1)], 0.15))


def along(x: float, y: float = -5.0, look: float | None = None) -> Camera:
    """A camera on the path y = const, looking at the wall at x (or at `look`)."""
    return look_at((x, y, 0.0), (x if look is None else look, 0.0, 0.0), width=SIZE, height=SIZE, fov_x=0.8)


@pytest.mark.parametrize("name", COVERAGE)
def test_the_candidate_that_fixes_the_target_views_wins_over_one_that_sees_their_parts_anew(name: str) -> None:
    """Targets along one side of a path: a dense run over a stretch the captured views already show
    from the targets' direction, and one target where nothing was captured. The path's end
    looking obliquely at the dense run sees much of what the targets show, from a direction no
    captured view took; the candidate in front of the lone target fixes what the targets lack.
    Counting novelty from the candidate's direction (the design before, `target_weights`) took
    the path's end; counting it from the targets' directions takes the one that fixes them."""
    renderer = wall()
    captured = [along(1.0), along(3.0)]
    targets = [along(0.25 * i, -4.0) for i in range(17)] + [along(7.0, -4.0)]
    candidates = [along(-2.0, look=2.0), along(7.0), along(6.0, look=2.0)]
    evidence = visibility_evidence(renderer, candidates, captured, targets)
    selection = get_strategy(name).select(evidence, 0, 0)
    assert selection.order[0] == 1
    values = reference_values(evidence)
    assert values[1] > 3 * max(values[0], values[2])      # by a wide margin: the covered stretch is fixed already


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
