"""Next-best view from what the model can see, not from where the cameras stand.

One render of the full model per view says which coverage elements (splats; NeRF:
occupancy cells) the view shows and how much of the image each fills, occlusion included
(`phd_core.renderers.visibility.Visibility`). From the captured views, each element knows
from which directions it was seen unhidden. A candidate is worth the part of its image that
shows elements no captured view saw from a nearby direction:

    novelty(u, c) = prod over captured v of (1 - seen(u, v) * near(dir(u, c), dir(u, v)))
    value(c)      = sum over u of weight(u, c) * novelty(u, c) * fragility(u, c)
                    + EMPTY_WEIGHT * empty(c) * axis_novelty(c)

- seen(u, v) = min(1, visible share / SEEN_SHARE): an element half hidden from v still
  counts as seen by v, one hidden behind an occluder does not (times `support`, 1 in the
  product: below 1 a part seen once stays partly novel; docs/nbv.md measured 0.5 and kept 1);
- near(a, b) = exp(-(1 - cos angle(a, b)) / ANGLE_SCALE): directions from the element to
  the two cameras (1 for the same direction, 0.37 at 60 degrees, 0.14 at 90);
- weight(u, c): pixels of c's image that u fills (alpha times transmittance, summed);
- fragility (with dropout, `visibility_sigma`): 1 + mean zeta on u's pixels / the mean of
  that over every candidate, so a well-seen part the model holds fragilely still counts;
  1 without dropout (`visibility`);
- empty(c): transmittance left on the rays that cross the scene box, space the model has
  nothing in; its novelty compares viewing axes, as nothing there has a position.

`visibility_sigma_fvs` (the default) multiplies each candidate's value by the distance from
its centre to the nearest captured (or already picked) centre, as farthest-view sampling
ranks: on the benchmark (docs/nbv.md) the model's coverage alone was level with FVS on the
object scenes, where every part is seen from some direction early on and what is left is
how evenly the views surround it; the product is ahead of FVS on all four scenes.

Told the target views (where the model will be looked at from), a candidate is worth what it
fixes in those views instead: the novelty of each element from each target's direction, and
how much the candidate lowers it (`strategies.targets`). Told the capture's own path (targets
standing where the camera stands, `targets.walked`), the default weighs that gain by how much a
candidate brings the targets closer to a captured centre (`targets.TargetDensity`) in place of
the distance factor, without the fragility weighting, as measured (docs/nbv.md).

Batches are greedy with real conditioning: each pick is counted as captured (its own
visibility multiplies the novelty of every element it sees) before the next is scored, so
two identical candidates never share a batch. Families that cannot report visibility get the
`fvs_sigma_floor` order (camera centres), which every family supports.
"""

from __future__ import annotations

import dataclasses
import heapq
from typing import Sequence

import torch
from torch import Tensor

from ...renderers.visibility import Seen, Visibility
from .base import Evidence, Selection, Strategy, centres
from .coverage import ANGLE_SCALE, SUPPORT, Coverage
from .hybrid import FVS_SIGMA_FLOOR
from .targets import TargetDensity, TargetGain, walked

SPREAD_FLOOR = 1e-3      # the least distance factor, of the mean: over 10x below the closest two poses of any
                         # benchmark scene (lego_200), so the benchmark's picks never meet it


def coverage_select(evidence: Evidence, k: int, fragility: bool, angle_scale: float = ANGLE_SCALE,
                    spread: bool = False, support: float = SUPPORT, spread_power: float = 1.0,
                    follow_walk: bool = True) -> Selection:
    """Greedy batch by coverage (module docstring); the rest follow by their value after it.
    With the evidence's target views, a candidate's value is what it fixes in them (`strategies.targets`).
    spread: each value times the distance from the candidate's centre to the nearest captured
    (or picked) one, as farthest-view sampling weighs (`visibility_sigma_fvs`), at least
    SPREAD_FLOOR of the candidates' mean distance: cameras at a captured centre looking
    different ways still rank by what they see; raised to spread_power. Told the capture's own
    path as targets, the targets' density in its place (module docstring; not with follow_walk False).
    support: the share of an element's novelty one view that saw it from the same direction removes."""
    count = len(evidence.candidates)
    if evidence.candidate_views is None or evidence.captured_views is None:
        return dataclasses.replace(FVS_SIGMA_FLOOR.select(evidence, k, 0), rule=FALLBACK_RULE)
    cand, captured = centres(evidence.candidates), centres(evidence.captured)   # [C, 3], [V, 3]
    targets = evidence.target_views
    aimed = centres([view.camera for view in targets]) if targets is not None else None
    density = (TargetDensity(aimed, cand, captured)
               if spread and follow_walk and aimed is not None and walked(aimed, torch.cat([cand, captured]))
               else None)
    coverage: Coverage | TargetGain = (
        TargetGain(evidence.candidate_views, targets, fragility and density is None, angle_scale, support)
        if targets is not None else Coverage(evidence.candidate_views, fragility, angle_scale, support))
    coverage.capture(*evidence.captured_views)
    nearest = (torch.cdist(cand, captured).min(dim=1).values
               if spread and evidence.captured else torch.ones(count, dtype=torch.float64))
    floor = SPREAD_FLOOR * float(nearest.mean()) or 1.0                         # all at captured centres: 1

    def value(i: int) -> float:
        if density is not None:
            return coverage.value(i) * density.value(i)
        return coverage.value(i) * max(float(nearest[i]), floor) ** spread_power

    # Lazy greedy: a value can only fall as views are counted as captured (every novelty factor
    # lies in [0, 1] and the nearest distance only shrinks), so a value computed before the last
    # pick is an upper bound, in floating point too (the same sums, in the same order, of terms
    # that can only shrink). The heap holds such bounds; its top is picked once its value is
    # current, and ties go to the lower index as in a full scan (equal bounds sort by index).
    heap = [(-value(i), i) for i in range(count)]
    heapq.heapify(heap)
    current = [0] * count                  # the number of picks when each heap value was computed
    order, scores = [], [0.0] * count
    for picks in range(min(k, count)):
        while current[heap[0][1]] != picks:
            i = heap[0][1]
            current[i] = picks
            heapq.heapreplace(heap, (-value(i), i))
        negative, i = heapq.heappop(heap)
        order.append(i)
        scores[i] = -negative
        if len(order) == count:
            break                                 # nothing left whose value the pick would change
        coverage.capture(evidence.candidate_views[i])
        coverage.retire(i)
        if density is not None:
            density.capture(i)
        elif spread:
            nearest = torch.minimum(nearest, (cand - cand[i]).norm(dim=1))
    taken = set(order)
    rest = [(value(i), i) for i in range(count) if i not in taken]
    for v, i in rest:
        scores[i] = v
    return Selection(order + [i for _, i in sorted(rest, key=lambda item: (-item[0], item[1]))], scores,
                     coverage_rule(targets is not None, density is not None, spread))


FALLBACK_RULE = ("spread from the captured views, weighted by sigma_mean (fvs_sigma_floor: this model's family "
                 "reports no visibility)")


def coverage_rule(targeted: bool, dense: bool, spread: bool) -> str:
    """The rule `coverage_select` ordered by, in words: what it valued, and how it spread the picks."""
    toward = ("toward what the target views show that no captured view saw" if targeted
              else "toward what no captured view saw")
    how = ("followed the targets' density (they are the capture's own path), " if dense
           else "spread from the captured views, " if spread else "")
    return how + toward


def uncovered_share(views: list[Visibility], captured: Sequence[Visibility | Seen]) -> Tensor:
    """[V] float64 in [0, 1]: the share of each view's image of the model that the captured views
    did not see from a nearby direction (0 when a view shows none of the model)."""
    if not views:
        return torch.zeros(0, dtype=torch.float64)
    coverage = Coverage(views, fragility=False)
    coverage.capture(*captured)
    return torch.tensor([coverage.share(c) for c in range(len(views))], dtype=torch.float64)


def _visibility(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=False)


def _visibility_sigma(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=True)


def _visibility_sigma_fvs(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=True, spread=True)


VISIBILITY = Strategy("visibility", "the candidate showing most of what no captured view saw unhidden from a nearby "
                      "direction (the model's own coverage, occlusion included), picked greedily", _visibility,
                      uses_dropout=False, uses_visibility=True)
VISIBILITY_SIGMA = Strategy("visibility_sigma", "as visibility, each part weighted by its PH-Dropout fragility "
                            "(zeta on its pixels), so fragile parts count even when seen", _visibility_sigma,
                            uses_visibility=True)
VISIBILITY_SIGMA_FVS = Strategy("visibility_sigma_fvs", "as visibility_sigma, each candidate's value times the "
                                "distance from its centre to the nearest captured (or picked) one, so a batch "
                                "also spreads as farthest-view sampling does; told target views that stand where "
                                "the camera stands (the capture's own path), times how much it brings them closer "
                                "to a captured view instead, so picks follow where they crowd", _visibility_sigma_fvs,
                                uses_visibility=True)
