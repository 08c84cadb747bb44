"""Rank by a candidate's own PH-Dropout statistic, as the paper does (no batch diversity)."""

from __future__ import annotations

from .base import Evidence, Selection, Strategy, by_score


def _sigma_max(evidence: Evidence, k: int, seed: int) -> Selection:
    return by_score(evidence.sigma_max)


def _sigma_mean(evidence: Evidence, k: int, seed: int) -> Selection:
    return by_score(evidence.sigma_mean)


SIGMA_MAX = Strategy("sigma_max", "the paper's rule: highest sigma_max (max of zeta over the image) first",
                     _sigma_max)
SIGMA_MEAN = Strategy("sigma_mean", "highest sigma_mean (mean of zeta over the image) first", _sigma_mean)
