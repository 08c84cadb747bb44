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
- weight(u, c): pixels of c's image that u fills (alpha times transmittance, summed); with
  target views (where the model will be looked at from, `target_weights`), the target pixels
  u fills seen from a direction near c's, per target view, times how fully c sees u: a
  candidate is worth what it fixes in those views;
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


CAPTURE_CHUNK = 1 << 16  # candidate elements a capture updates at once (its temporaries: ~7 MB)


class Coverage:
    """The candidates' novelty, conditioned on every view counted as captured so far.

    The elements of the candidates still in play sit in one list, the i-th such candidate's
    (number ids[i]) at entries offsets[i]:offsets[i + 1]: `index` into the union of all their
    elements, the direction from each element to the candidate's camera, its weight (pixels it
    fills times its fragility) and its novelty. Counting a view as captured updates them all in
    a few vectorised steps; a candidate `retire`d (picked) leaves the list once half of it is
    retired. At a million splats and 100 candidates, a loop over the candidates per capture was
    most of a ranking's time (docs/performance.md).
    """

    def __init__(self, candidates: list[Visibility], fragility: bool, angle_scale: float = ANGLE_SCALE,
                 weights: list[Tensor] | None = None):
        """weights: [C] each candidate's [K_c] weight per element in place of the pixels it fills
        (`target_weights`); None: the pixels."""
        self.angle_scale = angle_scale
        self.union = torch.unique(torch.cat([v.elements for v in candidates]))
        self.size = len(self.union)
        self.points = torch.zeros(self.size, 3, dtype=torch.float64)                  # [U, 3]
        counts = torch.tensor([len(v.elements) for v in candidates], dtype=torch.long)
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])  # [C + 1]
        total = int(self.offsets[-1])
        self.index = torch.empty(total, dtype=torch.long)                            # [S]
        self.dirs = torch.empty(total, 3, dtype=torch.float64)                       # [S, 3]
        self.weight = torch.empty(total, dtype=torch.float64)                        # [S]
        self.novelty = torch.ones(total, dtype=torch.float64)                        # [S]
        reference = _mean_zeta(candidates) if fragility else 0.0
        for c, vis in enumerate(candidates):
            part = slice(int(self.offsets[c]), int(self.offsets[c + 1]))
            self.index[part] = torch.searchsorted(self.union, vis.elements)
            self.points[self.index[part]] = vis.points
            self.dirs[part] = directions(vis.points, vis.camera.center)
            self.weight[part] = vis.weight if weights is None else weights[c]
            if fragility and reference > 0 and vis.valued is not None:
                self.weight[part] *= 1.0 + vis.valued / vis.weight.clamp_min(1e-300) / reference
        self.ids = list(range(len(candidates)))           # the candidate of each stored run of entries
        self.position = {c: c for c in self.ids}          # and the run of each candidate
        self.retired: set[int] = set()
        self.empty = [vis.empty for vis in candidates]
        self.axes = torch.stack([viewing_axis(vis) for vis in candidates])            # [C, 3]
        self.axis_novelty = [1.0] * len(candidates)
        self.sums = [self._sum(c) for c in range(len(candidates))]

    def _part(self, c: int) -> slice:
        """Candidate c's entries (c still in the list)."""
        i = self.position[c]
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))

    def _sum(self, c: int) -> float:
        """Candidate c's weight times novelty, summed over its elements."""
        part = self._part(c)
        return float((self.weight[part] * self.novelty[part]).sum())

    def value(self, c: int) -> float:
        """What candidate c would show that no view counted as captured saw (module docstring)."""
        return self.sums[c] + EMPTY_WEIGHT * self.empty[c] * self.axis_novelty[c]

    def share(self, c: int) -> float:
        """The share of candidate c's image of the model left unseen (0 when it shows none)."""
        total = float(self.weight[self._part(c)].sum())
        return self.sums[c] / total if total > 0 else 0.0

    def capture(self, vis: Visibility) -> None:
        """Count `vis` as captured: every candidate's novelty of the elements it saw falls."""
        index = torch.searchsorted(self.union, vis.elements).clamp_max(max(self.size - 1, 0))
        known = self.union[index] == vis.elements if self.size else torch.zeros(len(index), dtype=torch.bool)
        seen, toward = torch.zeros(self.size, dtype=torch.float64), torch.zeros(self.size, 3, dtype=torch.float64)
        seen[index[known]] = seen_share(vis)[known]                                   # [U]
        toward[index[known]] = directions(self.points[index[known]], vis.camera.center)  # [U, 3]
        changed = []
        for start in range(0, len(self.index), CAPTURE_CHUNK):
            chunk = self.index[start:start + CAPTURE_CHUNK]
            s = seen[chunk]
            touched = (s > 0).nonzero().squeeze(1)
            if len(touched):
                entries = touched + start
                self.novelty[entries] *= 1.0 - s[touched] * near(self.dirs[entries], toward[chunk[touched]],
                                                                  self.angle_scale)
                changed.append(entries)
        axis_near = near(self.axes, viewing_axis(vis), self.angle_scale).tolist()
        self.axis_novelty = [n * (1.0 - a) for n, a in zip(self.axis_novelty, axis_near)]
        if changed:                      # entries ascend, so their candidates do too
            owners = torch.searchsorted(self.offsets, torch.cat(changed), right=True) - 1
            for i in torch.unique_consecutive(owners).tolist():
                if self.ids[i] not in self.retired:
                    self.sums[self.ids[i]] = self._sum(self.ids[i])

    def retire(self, c: int) -> None:
        """Candidate c is out of play (picked): its value is no longer needed. Once half of the
        stored entries are retired candidates', they leave the list (each capture after costs less)."""
        self.retired.add(c)
        counts = self.offsets[1:] - self.offsets[:-1]
        gone = torch.tensor([i in self.retired for i in self.ids])
        if 2 * int(counts[gone].sum()) <= len(self.index):
            return
        keep = torch.repeat_interleave(~gone, counts)
        self.index = self.index[keep]             # one array at a time: at most half of one is copied at once
        self.dirs = self.dirs[keep]
        self.weight = self.weight[keep]
        self.novelty = self.novelty[keep]
        self.ids = [i for i, out in zip(self.ids, gone.tolist()) if not out]
        self.position = {c: i for i, c in enumerate(self.ids)}
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts[~gone].cumsum(0)])


def seen_share(vis: Visibility) -> Tensor:
    """[K] how fully the view saw each of its elements: min(1, visible share / SEEN_SHARE)."""
    return (vis.visible_share / SEEN_SHARE).clamp_max(1.0)


def target_weights(candidates: list[Visibility], targets: list[Visibility],
                   angle_scale: float = ANGLE_SCALE) -> list[Tensor]:
    """[C] each candidate's [K_c] float64 weight per element when the model will be looked at from
    `targets`: the pixels the element fills in the target views (occlusion included), each target
    counted by how near its direction to the element is to the candidate's, averaged over the
    targets, times how fully the candidate sees the element (`seen_share`). An element no target
    shows is worth nothing, however much of a candidate's image it fills."""
    counts = [len(v.elements) for v in candidates]
    elements = torch.cat([v.elements for v in candidates])                         # [S]
    points = torch.cat([v.points for v in candidates])                             # [S, 3]
    dirs = torch.cat([directions(v.points, v.camera.center) for v in candidates])  # [S, 3]
    size = 1 + max((int(v.elements.max()) for v in [*candidates, *targets] if len(v.elements)), default=-1)
    shown = torch.zeros(len(elements), dtype=torch.float64)                        # [S]
    for target in targets:
        pixels = torch.zeros(size, dtype=torch.float64)
        pixels[target.elements] = target.weight
        hit = pixels[elements]
        entries = (hit > 0).nonzero().squeeze(1)
        toward = directions(points[entries], target.camera.center)
        shown[entries] += hit[entries] * near(dirs[entries], toward, angle_scale)
    shown /= max(len(targets), 1)
    return list((shown * torch.cat([seen_share(v) for v in candidates])).split(counts))


def _mean_zeta(views: list[Visibility]) -> float:
    """Mean zeta per pixel of model weight over every candidate (the fragility scale)."""
    valued = sum(float(v.valued.sum()) for v in views if v.valued is not None)
    weight = sum(float(v.weight.sum()) for v in views if v.valued is not None)
    return valued / weight if weight > 0 else 0.0


def coverage_select(evidence: Evidence, k: int, fragility: bool, angle_scale: float = ANGLE_SCALE,
                    spread: bool = False) -> Selection:
    """Greedy batch by coverage (module docstring); the rest follow by their value after it.
    With the evidence's target views, each element is weighted by what they show of it.
    spread: each value times the distance from the candidate's centre to the nearest captured
    (or picked) one, as farthest-view sampling weighs (`visibility_sigma_fvs`), at least
    SPREAD_FLOOR of the candidates' mean distance: cameras at a captured centre looking
    different ways still rank by what they see."""
    count = len(evidence.candidates)
    if evidence.candidate_views is None or evidence.captured_views is None:
        return FVS_SIGMA_FLOOR.select(evidence, k, 0)
    weights = (target_weights(evidence.candidate_views, evidence.target_views, angle_scale)
               if evidence.target_views is not None else None)
    coverage = Coverage(evidence.candidate_views, fragility, angle_scale, weights)
    for vis in evidence.captured_views:
        coverage.capture(vis)
    cand = centres(evidence.candidates)                                         # [C, 3]
    nearest = (torch.cdist(cand, centres(evidence.captured)).min(dim=1).values
               if spread and evidence.captured else torch.ones(count, dtype=torch.float64))
    floor = SPREAD_FLOOR * float(nearest.mean()) or 1.0                         # all at captured centres: 1

    def value(i: int) -> float:
        return coverage.value(i) * max(float(nearest[i]), floor)

    taken = [False] * count
    order, scores = [], [0.0] * count
    for _ in range(min(k, count)):
        values = [-float("inf") if taken[i] else value(i) for i in range(count)]
        i = max(range(count), key=lambda j: (values[j], -j))         # the first maximum: lower index on ties
        order.append(i)
        scores[i] = values[i]
        taken[i] = True
        coverage.capture(evidence.candidate_views[i])
        coverage.retire(i)
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
                                "also spreads as farthest-view sampling does", _visibility_sigma_fvs,
                                uses_visibility=True)
