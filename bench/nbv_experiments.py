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
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from phd_core.uq.strategies import STRATEGIES, Evidence, Selection, Strategy
from phd_core.uq.strategies.base import by_score, centres, greedy
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
               "visibility_sigma_angle0.25", "visibility_sigma_fvs_angle0.25", "visibility_fvs")


def _visibility_sharp(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=True, angle_scale=0.25)


def _visibility_fvs(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=False, spread=True)


def _visibility_fvs_sharp(evidence: Evidence, k: int, seed: int) -> Selection:
    return coverage_select(evidence, k, fragility=True, angle_scale=0.25, spread=True)


for _strategy in (
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
                 _visibility_sharp, uses_visibility=True),
        Strategy("visibility_sigma_fvs_angle0.25", "visibility_sigma_fvs with the direction kernel at 0.25",
                 _visibility_fvs_sharp, uses_visibility=True),
        Strategy("visibility_fvs", "visibility_sigma_fvs without the fragility weighting", _visibility_fvs,
                 uses_dropout=False, uses_visibility=True)):
    STRATEGIES.register(_strategy)
