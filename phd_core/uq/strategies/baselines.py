"""The two baselines every strategy is measured against: random and farthest-view sampling."""

from __future__ import annotations

import random

import torch

from .base import Evidence, Selection, Strategy, by_score, greedy


def _random(evidence: Evidence, k: int, seed: int) -> Selection:
    rng = random.Random(seed)
    return by_score(torch.tensor([rng.random() for _ in evidence.candidates], dtype=torch.float64))


def _fvs(evidence: Evidence, k: int, seed: int) -> Selection:
    return greedy(evidence, k, lambda nearest: nearest)


RANDOM = Strategy("random", "a seeded random order", _random, uses_dropout=False)
FVS = Strategy("fvs", "farthest-view sampling: the candidate farthest from every captured (and picked) pose",
               _fvs, uses_dropout=False)
