"""Strategies tried on the active-learning benchmark and not shipped (docs/nbv.md, "Also tried").

Each is one `Strategy` registered from here, which is all a new strategy takes; importing
this module (bench_nbv.py does) makes them selectable by name in that process only.

- kmedian, kmedian_sigma: greedy weighted k-median over the candidate pool: the gain of
  a candidate is how much closer it brings every candidate q to its nearest captured
  pose, weighted by 1 or by q's sigma_mean (facility location: representative views).
- kmedian_sq: the same on squared distances (between k-median and FVS).
- sigma_top, sigma_area: other aggregations of zeta than the max: the mean of the top 10 %
  of pixels, and the share of pixels above 0.05 (phd_core.uq.uncertainty).
- fvs_top: fvs_sigma_floor with sigma_top in place of sigma_mean.
- fvs_prefilter: among the candidates at least as far from the captured poses as the
  median candidate, the highest sigma_mean (a coverage prefilter, then uncertainty).
- visibility_sigma_angle0.25: visibility_sigma with a sharper direction kernel (`near` falls
  to 1/e at 41 degrees, not 60): a part's value follows its nearest captured direction more
  than the sum over all of them.
- visibility_fvs: the default without the fragility weighting (visibility times the distance
  factor), tried told the target views to measure what fragility adds to the target gain.
- visibility_sigma_fvs_angle0.25: the default with that sharper kernel, tried told the
  target views (`+targets`): with the default kernel the captured views cover most of what
  the targets show after 4 views, so the distance factor decides.
- visibility_sigma_fvs_support0.5: the default where one view removes at most half of an
  element's novelty (`support`), so a part seen once is only partly covered and a second view
  near the first still gains (multi-view support: depth from one view is unconstrained);
  _sqrt: the same with the square root of the distance factor, which otherwise outweighs that
  gain (a neighbour at 0.5 units against a lone frame at 3 is a factor of 6); visibility_sigma_fvs_sqrt:
  the square root alone. Tried told the targets on cup_colmap's holdout folds, where random
  capture, whose picks stand closer together, is level with the default: support 0.5 is +0.13 dB
  over random there and gives up the default's lead over FVS on chain_200 and donut_200.
- tkmedian, tlogmedian (told the target views only): greedy facility location over the target
  views' centres, how much a candidate lowers the targets' distance (or log distance) to their
  nearest captured centre, so picks follow where the targets crowd, as random capture follows a
  hand-held path's density on cup_colmap; visibility_tkmedian, visibility_tlogmedian: the target
  gain (no fragility) times that value in place of the distance factor; visibility_tlogstands:
  visibility_tlogmedian over the targets and every pose the camera can stand at (candidates and
  captured views, each centre once), which fills sparse targets in and is the same set on
  cup_colmap, whose targets are those poses. visibility_tlogmedian beats random on cup_colmap's
  folds (+0.60 dB) and is behind FVS on every Blender scene (docs/nbv.md); the default now makes
  its computation when the targets are the capture's own frames (`targets.walked`).
- visibility_sigma_fvs_far: the default with the distance factor whatever the targets, as it was
  before it followed the density of targets that are the capture's own path (`targets.walked`);
  runs stored as the default told the targets on such scenes before that change carry this name.
- sfm_coverage (issue 47, "the SfM points' coverage"): the candidate that sees most of the capture's SfM points
  (points3D) the captured views see least: each point a view sees counts 2 if no captured view sees it, 1 if one
  does, 0 from two on (two views fix a point's depth); greedy, each pick's points counted as seen before the next
  (ties to the candidate farther from the captured poses). A view sees a point in its frustum, in front of it, and
  not hidden by the other points: occlusion by a z-buffer of the points themselves (`seen_points`), not the model's
  render, so it needs nothing trained and works for a pose not yet photographed. The benchmark gives it the points
  (`with_points`): the whole reconstruction's, as the 3DGS training starts from them.
- splat_coverage: sfm_coverage's rule on the trained model's splat centres instead of the SfM points (`points_for`),
  what a ranking of any uploaded splat model could use: no SfM points needed.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable

import torch
from torch import Tensor

from phd_core.scene import Camera
from phd_core.uq.strategies import STRATEGIES, Evidence, Selection, Strategy
from phd_core.uq.strategies.base import by_score, centres, greedy
from phd_core.uq.strategies.targets import TargetDensity, TargetGain
from phd_core.uq.strategies.visibility import coverage_select


def _k_median(evidence: Evidence, k: int, demand: Tensor, power: int) -> Selection:
    cand = centres(evidence.candidates)
    dist = torch.cdist(cand, cand).pow(power)                      # [C, C]

    def gain(nearest: Tensor) -> Tensor:
        reach = nearest.pow(power)[:, None]                        # [C, 1] each q's current distance
        return (demand[:, None] * (reach - torch.minimum(reach, dist))).sum(0)
    return greedy(evidence, k, gain)


def _uniform(evidence: Evidence) -> Tensor:
    return torch.ones(len(evidence.candidates), dtype=torch.float64)


def _prefilter(evidence: Evidence, k: int, seed: int) -> Selection:
    sigma = evidence.sigma_mean

    def gain(nearest: Tensor) -> Tensor:
        far = nearest >= nearest.median()
        return torch.where(far, sigma, sigma - sigma.max() - 1)     # near ones rank after every far one
    return greedy(evidence, k, gain)


def _fvs_top(evidence: Evidence, k: int, seed: int) -> Selection:
    weight = evidence.sigma_top + evidence.sigma_top.mean()
    return greedy(evidence, k, lambda nearest: weight * nearest)


def _k_median_strategy(demand: Callable[[Evidence], Tensor], power: int) -> Callable[[Evidence, int, int], Selection]:
    return lambda evidence, k, seed: _k_median(evidence, k, demand(evidence), power)


EXPERIMENTS = ("kmedian", "kmedian_sigma", "kmedian_sq", "fvs_prefilter", "sigma_top", "sigma_area", "fvs_top",
               "visibility_sigma_angle0.25", "visibility_sigma_fvs_angle0.25", "visibility_fvs", "tkmedian",
               "tlogmedian", "visibility_tkmedian", "visibility_tlogmedian", "visibility_sigma_fvs_support0.5",
               "visibility_sigma_fvs_support0.5_sqrt", "visibility_sigma_fvs_sqrt", "visibility_tlogstands",
               "visibility_sigma_fvs_far", "sfm_coverage", "splat_coverage")
USES_POINTS = ("sfm_coverage", "splat_coverage")    # strategies the benchmark gives points (`points_for`)


def _coverage(**options: Any) -> Callable[[Evidence, int, int], Selection]:
    """`coverage_select` with other options than the shipped coverage strategies' (bench only), and
    the distance factor whatever the targets, as these were measured (`follow_walk` False)."""
    return lambda evidence, k, seed: coverage_select(evidence, k, follow_walk=False, **options)


def _target_distance(evidence: Evidence, log: bool, stands: bool) -> TargetDensity:
    """`TargetDensity` over the target views' centres, or with `stands` over them and every pose the
    camera can stand at (the candidates and captured views, each centre once)."""
    assert evidence.target_views is not None
    targets = centres([view.camera for view in evidence.target_views])                  # [T, 3]
    if stands:
        targets = torch.unique(torch.cat([targets, centres(evidence.candidates + evidence.captured)]), dim=0)
    return TargetDensity(targets, centres(evidence.candidates), centres(evidence.captured), log)


def _full_scan(count: int, k: int, value: Callable[[int], float], capture: Callable[[int], None]) -> Selection:
    """Greedy by a full scan of every value at each pick (ties to the lower index); the rest by value."""
    order, scores, left = [], [0.0] * count, list(range(count))
    for _ in range(min(k, count)):
        best = max(left, key=lambda i: (value(i), -i))
        scores[best] = value(best)
        order.append(best)
        left.remove(best)
        capture(best)
    rest = sorted(((value(i), i) for i in left), key=lambda item: (-item[0], item[1]))
    for v, i in rest:
        scores[i] = v
    return Selection(order + [i for _, i in rest], scores)


def _target_density(coverage: bool, log: bool, stands: bool = False) -> Callable[[Evidence, int, int], Selection]:
    """The target distance's facility location alone, or times the target gain (no fragility)."""
    def select(evidence: Evidence, k: int, seed: int) -> Selection:
        spread = _target_distance(evidence, log, stands)
        if not coverage:
            return _full_scan(len(evidence.candidates), k, spread.value, spread.capture)
        assert evidence.candidate_views is not None and evidence.captured_views is not None
        gain = TargetGain(evidence.candidate_views, evidence.target_views, fragility=False)
        gain.capture(*evidence.captured_views)

        def capture(i: int) -> None:
            gain.capture(evidence.candidate_views[i])
            spread.capture(i)
        return _full_scan(len(evidence.candidates), k, lambda i: gain.value(i) * spread.value(i), capture)
    return select


@dataclass
class PointsEvidence(Evidence):
    """Evidence with the capture's SfM points, which only the experiments here read."""

    points: Tensor | None = None      # [P, 3] float64 the capture's SfM points (points3D)


def points_for(strategy: str, sfm_points: Tensor | None, model_means: Tensor) -> Tensor | None:
    """The points `strategy` (of USES_POINTS) is given: the capture's SfM points [P, 3], or for splat_coverage the
    model's splat centres [G, 3]."""
    return model_means.detach() if strategy == "splat_coverage" else sfm_points


def with_points(evidence: Evidence, points: Tensor | None) -> PointsEvidence:
    """`evidence` carrying `points`, for a strategy of USES_POINTS."""
    return PointsEvidence(**{f.name: getattr(evidence, f.name) for f in fields(Evidence)},
                          points=None if points is None else points.double())


OCCLUSION_CELLS = 32        # the z-buffer's cells across a view's wider side
OCCLUSION_SLACK = 0.1       # a point within 10 % of the nearest point's depth in its cell is seen
SEEN_ENOUGH = 2             # views that see a point before it counts as covered


def seen_points(camera: Camera, points: Tensor) -> Tensor:
    """[P] bool: the points [P, 3] `camera` sees: in its image, in front of it, and not behind the nearest point of
    their z-buffer cell (OCCLUSION_CELLS across the wider side) by more than OCCLUSION_SLACK of its depth."""
    pixels, depth = camera.project(points)                                        # [P, 2], [P]
    inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < camera.width)
              & (pixels[:, 1] >= 0) & (pixels[:, 1] < camera.height))
    size = max(camera.width, camera.height) / OCCLUSION_CELLS                    # pixels per cell
    columns = int(camera.width // size) + 1
    cell = (pixels[:, 1] // size).long() * columns + (pixels[:, 0] // size).long()    # [P]
    cell = torch.where(inside, cell, 0)
    far = torch.full((columns * (int(camera.height // size) + 1),), torch.inf, dtype=depth.dtype)
    nearest = far.scatter_reduce(0, cell[inside], depth[inside], "amin")          # [cells]
    return inside & (depth <= nearest[cell] * (1 + OCCLUSION_SLACK))


def _sfm_coverage(evidence: Evidence, k: int, seed: int) -> Selection:
    points = evidence.points if isinstance(evidence, PointsEvidence) else None
    if points is None or not len(points):
        raise ValueError("sfm_coverage needs the capture's SfM points, splat_coverage the model's splat centres "
                         "(bench.nbv_experiments.with_points)")
    seen = torch.stack([seen_points(c, points) for c in evidence.candidates]).double()     # [C, P]
    views = torch.zeros(len(points), dtype=torch.float64)                           # [P] captured views seeing it
    for camera in evidence.captured:
        views += seen_points(camera, points).double()
    cand = centres(evidence.candidates)                                                    # [C, 3]
    nearest = (torch.cdist(cand, centres(evidence.captured)).min(dim=1).values if evidence.captured
               else torch.zeros(len(cand), dtype=torch.float64))                           # [C]

    def ranked(values: Tensor, left: list[int]) -> list[int]:     # by value, then the farther from the captured
        return sorted(left, key=lambda i: (-float(values[i]), -float(nearest[i]), i))
    order: list[int] = []
    scores = [0.0] * len(cand)
    for _ in range(min(k, len(cand))):
        values = seen @ (SEEN_ENOUGH - views).clamp_min(0)                                 # [C] points still needed
        best = ranked(values, [i for i in range(len(cand)) if i not in order])[0]
        order.append(best)
        scores[best] = float(values[best])
        views += seen[best]
        nearest = torch.minimum(nearest, (cand - cand[best]).norm(dim=1))
    values = seen @ (SEEN_ENOUGH - views).clamp_min(0)
    rest = ranked(values, [i for i in range(len(cand)) if i not in order])
    for i in rest:
        scores[i] = float(values[i])
    return Selection(order + rest, scores)


for _strategy in (
        Strategy("sfm_coverage", "the candidate seeing most SfM points that fewer than two captured views see "
                 "(frustum, in front, occlusion by the points' z-buffer), greedy", _sfm_coverage, uses_dropout=False),
        Strategy("splat_coverage", "sfm_coverage on the model's splat centres", _sfm_coverage, uses_dropout=False),
        Strategy("kmedian", "greedy k-median over the candidate poses", _k_median_strategy(_uniform, 1),
                 uses_dropout=False),
        Strategy("kmedian_sigma", "greedy k-median weighted by sigma_mean",
                 _k_median_strategy(lambda ev: ev.sigma_mean, 1)),
        Strategy("kmedian_sq", "greedy k-median on squared distances", _k_median_strategy(_uniform, 2),
                 uses_dropout=False),
        Strategy("fvs_prefilter", "the most uncertain of the farther half of the candidates", _prefilter),
        Strategy("sigma_top", "highest mean of the top 10 % of pixels' zeta",
                 lambda ev, k, seed: by_score(ev.sigma_top)),
        Strategy("sigma_area", "largest share of pixels with zeta above 0.05", lambda ev, k, seed: by_score(ev.area)),
        Strategy("fvs_top", "distance times (sigma_top + its mean), greedy", _fvs_top),
        Strategy("visibility_sigma_angle0.25", "visibility_sigma with the direction kernel at 0.25",
                 _coverage(fragility=True, angle_scale=0.25), uses_visibility=True),
        Strategy("visibility_sigma_fvs_angle0.25", "visibility_sigma_fvs with the direction kernel at 0.25",
                 _coverage(fragility=True, angle_scale=0.25, spread=True), uses_visibility=True),
        Strategy("visibility_fvs", "visibility_sigma_fvs without the fragility weighting",
                 _coverage(fragility=False, spread=True), uses_dropout=False, uses_visibility=True),
        Strategy("visibility_sigma_fvs_support0.5", "visibility_sigma_fvs where one view removes at most half of "
                 "an element's novelty", _coverage(fragility=True, spread=True, support=0.5), uses_visibility=True),
        Strategy("visibility_sigma_fvs_support0.5_sqrt", "visibility_sigma_fvs_support0.5 times the square root of "
                 "the distance, not the distance",
                 _coverage(fragility=True, spread=True, support=0.5, spread_power=0.5), uses_visibility=True),
        Strategy("visibility_sigma_fvs_far", "visibility_sigma_fvs with the distance factor whatever the targets "
                 "(the default before it followed a walked path's density)",
                 _coverage(fragility=True, spread=True), uses_visibility=True),
        Strategy("visibility_sigma_fvs_sqrt", "visibility_sigma_fvs times the square root of the distance, not the "
                 "distance", _coverage(fragility=True, spread=True, spread_power=0.5), uses_visibility=True),
        Strategy("tkmedian", "k-median over the target views' centres", _target_density(False, False),
                 uses_dropout=False, uses_visibility=True),
        Strategy("tlogmedian", "k-median over the target views' centres on log distances",
                 _target_density(False, True), uses_dropout=False, uses_visibility=True),
        Strategy("visibility_tkmedian", "the target gain times tkmedian's value", _target_density(True, False),
                 uses_dropout=False, uses_visibility=True),
        Strategy("visibility_tlogmedian", "the target gain times tlogmedian's value", _target_density(True, True),
                 uses_dropout=False, uses_visibility=True),
        Strategy("visibility_tlogstands", "visibility_tlogmedian over the target views and every pose the camera "
                 "can stand at (candidates, captured)", _target_density(True, True, stands=True),
                 uses_dropout=False, uses_visibility=True)):
    STRATEGIES.register(_strategy)
