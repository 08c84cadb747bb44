"""Next-best view by Fisher information (FisherRF, Jiang et al., ECCV 2024), on the CPU.

A view's information about the model's parameters is the diagonal of J^T J, J the Jacobian
of its render (`Renderer.fisher`: estimated by backward passes with random +-1 pixel
weights, E[(J^T v)^2] = diag(J^T J)), summed per splat over each parameter group. The
captured views hold H = sum of theirs. A candidate's gain is how much it adds relative to
what is held, sum of F_c / (H + lambda), with lambda = LAMBDA_SHARE of the mean of H per
group (a prior that keeps parameters no captured view constrains from dominating by division
by nearly 0). Batches are greedy: each pick's F joins H before the next is scored.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .base import Evidence, Selection, Strategy
from .hybrid import FVS_SIGMA_FLOOR

LAMBDA_SHARE = 0.1


def information_gain(candidate: Tensor, held: Tensor) -> Tensor:
    """sum over splats and groups of candidate / (held + lambda): candidate [C, G, P] or [G, P],
    held [G, P] -> [C] or []."""
    prior = LAMBDA_SHARE * held.mean(0).clamp_min(1e-30)                  # [P]
    return (candidate / (held + prior)).sum((-2, -1))


def _fisher(evidence: Evidence, k: int, seed: int) -> Selection:
    if evidence.candidate_fisher is None or evidence.captured_fisher is None:
        return FVS_SIGMA_FLOOR.select(evidence, k, seed)
    held = evidence.captured_fisher.clone()                               # [G, P]
    count = len(evidence.candidates)
    taken = torch.zeros(count, dtype=torch.bool)
    order, scores = [], [0.0] * count
    for _ in range(min(k, count)):
        gains = information_gain(evidence.candidate_fisher, held).masked_fill(taken, -torch.inf)
        i = int(torch.argmax(gains))                                      # the first maximum: lower index on ties
        order.append(i)
        scores[i] = float(gains[i])
        taken[i] = True
        held += evidence.candidate_fisher[i]
    gains = information_gain(evidence.candidate_fisher, held)
    rest = sorted((i for i in range(count) if not taken[i]), key=lambda i: (-float(gains[i]), i))
    for i in rest:
        scores[i] = float(gains[i])
    return Selection(order + rest, scores)


FISHER = Strategy("fisher", "FisherRF: the candidate adding most Fisher information relative to what the captured "
                  "views hold (diagonal, by random projections), picked greedily", _fisher, uses_dropout=False,
                  uses_fisher=True)
