"""Next-best view for target views: a candidate is worth what it fixes in the views the model will be looked at from.

Given target views (a walkthrough, a turntable ring, the views a robot will plan from), every
element u a target t shows is one target entry (t, u) with a weight, the pixels u fills in t
(occlusion included, `Visibility.weight`), and a novelty: how badly the captured views cover u
from the direction t looks at it,

    n_t(u) = prod over captured (and already picked) v of (1 - seen(u, v) * near(dir(u, t), dir(u, v)))

(`Coverage` over the target views, the targets in the role it gives candidates: `seen`, `near`
as in `strategies.visibility`). A candidate c's value is how much capturing it would lower the
targets' weighted novelty:

    gain(c) = sum over u that c sees, over target entries (t, u) of
              weight_t(u) * n_t(u) * seen(u, c) * near(dir(u, t), dir(u, c)) * fragility(u, c)

fragility (with dropout, `visibility_sigma`) as in `strategies.visibility`: 1 + mean zeta on
u's pixels in c / the mean of that over every candidate; 1 without dropout. An element no
target shows is worth nothing, and space the model has nothing in (the untargeted ranking's
empty-box term) is not counted. Capturing c multiplies each n_t(u) by exactly the factor the
gain sums the loss of, so gains only fall as views are picked (submodular): the lazy greedy of
`coverage_select` is exact. Unlike the untargeted value reweighted by the target pixels (the
design before), it counts novelty from the directions the targets look from, so a candidate
that sees what the captured views already show the targets gains nothing. The default's
distance factor multiplies the gain as without targets: without it cup_colmap lost 2.5 dB
(docs/nbv.md, "Target views on the four scenes").

Targets that are the capture's own path (`walked`: most of them stand where a candidate or a
captured view stands, as when a capture is told its own frames) say where the model will be
looked at densely: there the distance factor, which sends picks to the path's sparse ends, gives
way to `TargetDensity`, how much a candidate brings the targets closer to a captured centre, so
picks follow where the targets crowd (docs/nbv.md, "Following the targets' density").
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from ...renderers.visibility import Seen, Visibility
from .coverage import ANGLE_SCALE, SUPPORT, Coverage, directions, mean_zeta, seen_share

WALKED_SHARE = 0.5       # `walked`: the share of the targets standing where the camera stands
SAME_PLACE = 1e-6        # `walked`: centres this close, of the poses' mean distance from their mean, are one


def spread_of(points: torch.Tensor) -> float:
    """The mean distance of points [N, 3] from their mean (0 for none): the size SAME_PLACE is of."""
    return float((points - points.mean(0)).norm(dim=1).mean()) if len(points) else 0.0


def walked(targets: torch.Tensor, stands: torch.Tensor) -> bool:
    """Whether the target centres [T, 3] are the capture's own path: at least WALKED_SHARE of them
    where a candidate or captured view stands (`stands` [S, 3], to SAME_PLACE of the scene's size)."""
    if not len(targets) or not len(stands):
        return False
    there = torch.cdist(targets, stands).min(dim=1).values <= SAME_PLACE * (spread_of(stands) or 1.0)
    return float(there.double().mean()) >= WALKED_SHARE


def density_bytes(targets: int, candidates: int, captured: int) -> int:
    """The most `walked` and `TargetDensity` hold at once (float64): the targets' distances to every
    pose the camera stands at, to the candidates, and to each other."""
    return 8 * targets * (2 * candidates + captured + targets)


class TargetDensity:
    """Facility location over the target centres [T, 3]: how much capturing candidate i lowers the
    targets' distance to their nearest captured centre, on log(distance + eps) (eps the median
    distance from a target to its nearest other one elsewhere) or on the distance itself, so picks follow
    where the targets crowd. A value only falls as centres are captured (the lazy greedy holds)."""

    def __init__(self, targets: torch.Tensor, candidates: torch.Tensor, captured: torch.Tensor, log: bool = True):
        self.to_candidate = torch.cdist(targets, candidates)                                   # [T, C]
        self.nearest = (torch.cdist(targets, captured).min(dim=1).values if len(captured)
                        else self.to_candidate.max(dim=1).values)                              # [T]
        # Each target's nearest other target elsewhere: itself, and a target given twice, at (about) 0 are not.
        apart = torch.cdist(targets, targets)
        apart = apart.masked_fill(apart <= SAME_PLACE * spread_of(targets), float("inf")).min(dim=1).values
        apart = apart[torch.isfinite(apart)]
        eps = float(apart.median()) if len(apart) else 1.0
        self.f = (lambda d: torch.log(d + eps)) if log else (lambda d: d)
        self.now = self.f(self.nearest)                  # [T] f of each target's nearest distance, kept

    def value(self, i: int) -> float:
        return float((self.now - self.f(torch.minimum(self.nearest, self.to_candidate[:, i]))).sum())

    def capture(self, i: int) -> None:
        """Candidate i is captured: every target's nearest captured centre is at most that far."""
        self.nearest = torch.minimum(self.nearest, self.to_candidate[:, i])
        self.now = self.f(self.nearest)


class TargetGain:
    """Each candidate's gain on the target views (module docstring), conditioned on every view counted as captured."""

    def __init__(self, candidates: list[Visibility], targets: list[Visibility], fragility: bool,
                 angle_scale: float = ANGLE_SCALE, support: float = SUPPORT):
        self.angle_scale = angle_scale
        # n_t(u), weight_t(u): the targets in the role Coverage gives candidates
        self.targets = Coverage(targets, fragility=False, angle_scale=angle_scale, support=support)
        reference = mean_zeta(candidates) if fragility else 0.0
        # Per candidate, the elements it sees that some target shows: their union ids [K], the
        # directions from each to the candidate [K, 3] and seen(u, c) * fragility(u, c) [K].
        self.entries: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
        union = self.targets.union
        for vis in candidates:
            scale = seen_share(vis, support)
            if fragility and reference > 0 and vis.valued is not None:
                scale = scale * (1.0 + vis.valued / vis.weight.clamp_min(1e-300) / reference)
            shown = torch.isin(vis.elements, union) & (scale > 0)
            self.entries.append((torch.searchsorted(union, vis.elements[shown]).numpy(),
                                 directions(vis.points[shown], vis.camera.center).numpy(), scale[shown].numpy()))

    def capture(self, *views: Visibility | Seen) -> None:
        """Count `views` as captured: the targets' novelty of every element they saw falls."""
        self.targets.capture(*views)

    def retire(self, c: int) -> None:
        """Candidate c is out of play (picked): its entries go."""
        self.entries[c] = None

    def value(self, c: int) -> float:
        """How much capturing candidate c would lower the targets' weighted novelty (module docstring)."""
        entries = self.entries[c]
        assert entries is not None, f"candidate {c} was retired"
        element, toward, scale = entries
        t = self.targets
        return _gain(element, toward, scale, t.first.numpy(), t.dirs.numpy(), t.weight.numpy(), t.novelty.numpy(),
                     self.angle_scale)


@numba.njit(cache=True, nogil=True)
def _gain(element, toward, scale, first, dirs, weight, novelty, angle_scale):  # pragma: no cover
    """Sum over a candidate's elements k (union id element[k], direction toward[k] to the candidate,
    seen share times fragility scale[k]) and over the target entries e of that element of
    weight[e] * novelty[e] * scale[k] * near(dirs[e], toward[k]). The same terms in the same order
    on every call, so a gain computed later (novelties only fall) is never larger."""
    total = 0.0
    for k in range(len(element)):
        u = element[k]
        part = 0.0
        for e in range(first[u], first[u + 1]):
            dot = dirs[e, 0] * toward[k, 0] + dirs[e, 1] * toward[k, 1] + dirs[e, 2] * toward[k, 2]
            part += weight[e] * novelty[e] * np.exp(-(1.0 - dot) / angle_scale)
        total += scale[k] * part
    return total
