"""Uncertainty times distance: farthest-view sampling weighted by PH-Dropout.

Per held-out view, the render error follows the distance to the nearest captured pose
(Spearman about 0.75-0.78 on lego and donut, docs/nbv.md); sigma_mean adds what distance
cannot see (how much of the model a view depends on is fragile). The score is their
product, and picks are greedy: each pick counts as captured before the next is scored,
so a batch spreads out like farthest-view sampling does.

`fvs_sigma_floor` adds the candidates' mean sigma_mean to every sigma_mean, so a view
of a part of the scene the model left empty (no splats, hence no dropout variance) still
scores by its distance instead of scoring 0.
"""

from __future__ import annotations

from .base import Evidence, Selection, Strategy, greedy


def _fvs_sigma(evidence: Evidence, k: int, seed: int) -> Selection:
    weight = evidence.sigma_mean
    return greedy(evidence, k, lambda nearest: weight * nearest)


def _fvs_sigma_floor(evidence: Evidence, k: int, seed: int) -> Selection:
    weight = evidence.sigma_mean + evidence.sigma_mean.mean()
    return greedy(evidence, k, lambda nearest: weight * nearest)


FVS_SIGMA = Strategy("fvs_sigma", "distance to the nearest captured pose times sigma_mean, picked greedily",
                     _fvs_sigma)
FVS_SIGMA_FLOOR = Strategy("fvs_sigma_floor", "as fvs_sigma with the mean sigma_mean added to every "
                           "candidate's, so views of empty, unobserved space still count", _fvs_sigma_floor)
