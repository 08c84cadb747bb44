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
  counts as seen by v, one hidden behind an occluder does not;
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

Batches are greedy with real conditioning: each pick is counted as captured (its own
visibility multiplies the novelty of every element it sees) before the next is scored, so
two identical candidates never share a batch. Families that cannot report visibility get the
`fvs_sigma_floor` order (camera centres), which every family supports.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...renderers.visibility import Visibility
from .base import Evidence, Selection, Strategy, centres
from .hybrid import FVS_SIGMA_FLOOR

SEEN_SHARE = 0.25        # visible share at which a captured view counts as having seen an element
ANGLE_SCALE = 0.5        # 1 - cos(angle) at which `near` falls to 1/e (60 degrees)
SPREAD_FLOOR = 1e-3      # the least distance factor, of the mean: over 10x below the closest two poses of any
                         # benchmark scene (lego_200), so the benchmark's picks never meet it
EMPTY_WEIGHT = 0.1       # a pixel of empty box against a pixel of unseen model (0.5 lost 1.1 dB on lego, docs/nbv.md)


def near(a: Tensor, b: Tensor, scale: float = ANGLE_SCALE) -> Tensor:
    """[K] similarity of unit directions a, b [K, 3] (or b [3]): 1 when equal, falling with the angle."""
    return torch.exp(-(1.0 - (a * b).sum(-1)) / scale)


def directions(points: Tensor, camera_centre: Tensor) -> Tensor:
    """[K, 3] unit directions from points [K, 3] to a camera centre [3]."""
    d = camera_centre - points
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def viewing_axis(vis: Visibility) -> Tensor:
    """[3] float64 the direction the camera looks along (OpenGL: -z)."""
    return -vis.camera.c2w[:3, 2].double()


@dataclass
class Candidate:
    """One candidate's elements, in the index of the union of every view's elements."""

    index: Tensor       # [K_c] long
    dirs: Tensor        # [K_c, 3] element -> camera directions
    weight: Tensor      # [K_c] pixels each fills, times its fragility
    novelty: Tensor     # [K_c] what the captured (and picked) views left unseen, updated by each pick
    empty: float
    axis: Tensor        # [3]
    axis_novelty: float

    def value(self) -> float:
        return float((self.weight * self.novelty).sum()) + EMPTY_WEIGHT * self.empty * self.axis_novelty


class Coverage:
    """The candidates' novelty, conditioned on every view counted as captured so far."""

    def __init__(self, candidates: list[Visibility], fragility: bool, angle_scale: float = ANGLE_SCALE):
        self.angle_scale = angle_scale
        union = torch.unique(torch.cat([v.elements for v in candidates]))
        self.size = len(union)
        self.points = torch.zeros(self.size, 3, dtype=torch.float64)
        reference = _mean_zeta(candidates) if fragility else 0.0
        self.candidates = []
        for vis in candidates:
            index = torch.searchsorted(union, vis.elements)
            self.points[index] = vis.points
            weight = vis.weight.clone()
            if fragility and reference > 0 and vis.valued is not None:
                weight *= 1.0 + vis.valued / vis.weight.clamp_min(1e-300) / reference
            self.candidates.append(Candidate(index, directions(vis.points, vis.camera.center), weight,
                                             torch.ones(len(index), dtype=torch.float64),
                                             vis.empty, viewing_axis(vis), 1.0))
        self.union = union

    def capture(self, vis: Visibility) -> None:
        """Count `vis` as captured: every candidate's novelty of the elements it saw falls."""
        index = torch.searchsorted(self.union, vis.elements).clamp_max(max(self.size - 1, 0))
        known = self.union[index] == vis.elements if self.size else torch.zeros(len(index), dtype=torch.bool)
        dense = torch.zeros(self.size, dtype=torch.float64)
        dense[index[known]] = seen_share(vis)[known]
        centre, axis = vis.camera.center, viewing_axis(vis)
        for cand in self.candidates:
            s = dense[cand.index]
            touched = s > 0
            if touched.any():
                toward = directions(self.points[cand.index[touched]], centre)
                cand.novelty[touched] *= 1.0 - s[touched] * near(cand.dirs[touched], toward, self.angle_scale)
            cand.axis_novelty *= 1.0 - float(near(cand.axis, axis, self.angle_scale))


def seen_share(vis: Visibility) -> Tensor:
    """[K] how fully the view saw each of its elements: min(1, visible share / SEEN_SHARE)."""
    return (vis.visible_share / SEEN_SHARE).clamp_max(1.0)


def _mean_zeta(views: list[Visibility]) -> float:
    """Mean zeta per pixel of model weight over every candidate (the fragility scale)."""
    valued = sum(float(v.valued.sum()) for v in views if v.valued is not None)
    weight = sum(float(v.weight.sum()) for v in views if v.valued is not None)
    return valued / weight if weight > 0 else 0.0


def coverage_select(evidence: Evidence, k: int, fragility: bool, angle_scale: float = ANGLE_SCALE,
                    spread: bool = False) -> Selection:
    """Greedy batch by coverage (module docstring); the rest follow by their value after it.
    spread: each value times the distance from the candidate's centre to the nearest captured
    (or picked) one, as farthest-view sampling weighs (`visibility_sigma_fvs`), at least
    SPREAD_FLOOR of the candidates' mean distance: cameras at a captured centre looking
    different ways still rank by what they see."""
    count = len(evidence.candidates)
    if evidence.candidate_views is None or evidence.captured_views is None:
        return FVS_SIGMA_FLOOR.select(evidence, k, 0)
    coverage = Coverage(evidence.candidate_views, fragility, angle_scale)
    for vis in evidence.captured_views:
        coverage.capture(vis)
    cand = centres(evidence.candidates)                                         # [C, 3]
    nearest = (torch.cdist(cand, centres(evidence.captured)).min(dim=1).values
               if spread and evidence.captured else torch.ones(count, dtype=torch.float64))
    floor = SPREAD_FLOOR * float(nearest.mean()) or 1.0                         # all at captured centres: 1

    def value(i: int) -> float:
        return coverage.candidates[i].value() * max(float(nearest[i]), floor)

    taken = [False] * count
    order, scores = [], [0.0] * count
    for _ in range(min(k, count)):
        values = [-float("inf") if taken[i] else value(i) for i in range(count)]
        i = max(range(count), key=lambda j: (values[j], -j))         # the first maximum: lower index on ties
        order.append(i)
        scores[i] = values[i]
        taken[i] = True
        coverage.capture(evidence.candidate_views[i])
        if spread:
            nearest = torch.minimum(nearest, (cand - cand[i]).norm(dim=1))
    rest = [(value(i), i) for i in range(count) if not taken[i]]
    for v, i in rest:
        scores[i] = v
    return Selection(order + [i for _, i in sorted(rest, key=lambda item: (-item[0], item[1]))], scores)


def uncovered_share(views: list[Visibility], captured: list[Visibility]) -> Tensor:
    """[V] float64 in [0, 1]: the share of each view's image of the model that the captured views
    did not see from a nearby direction (0 when a view shows none of the model)."""
    if not views:
        return torch.zeros(0, dtype=torch.float64)
    coverage = Coverage(views, fragility=False)
    for vis in captured:
        coverage.capture(vis)
    return torch.tensor([float((c.weight * c.novelty).sum() / c.weight.sum()) if c.weight.sum() > 0 else 0.0
                         for c in coverage.candidates], dtype=torch.float64)


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
                                "also spreads as farthest-view sampling does", _visibility_sigma_fvs,
                                uses_visibility=True)
