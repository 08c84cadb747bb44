"""What a next-best-view strategy is given and what it returns.

A strategy turns what is known about the candidate poses (where they are, where the
captured views are, and each candidate's PH-Dropout statistics) into one score per
candidate and an order. The first k of the order are a batch meant to be captured
together: greedy strategies count each pick as captured before they choose the next, so
two identical candidates are never both in a batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from ...renderers.visibility import Seen, Visibility
from ...scene import Camera


@dataclass
class Evidence:
    """What a strategy may use. Distances are between camera centres, in scene units; the
    views' Visibility (one render of the full model each) when the strategy uses it and the
    model's family can report it. Target views, when the caller knows where the model will be
    looked at from, make the coverage strategies value what a candidate fixes in them (`strategies.targets`)."""

    candidates: list[Camera]      # [C] poses to choose from
    captured: list[Camera]        # [T] poses the model was trained on (may be empty)
    sigma_max: Tensor             # [C] float64, max of zeta over H, W, C (the paper's score)
    sigma_mean: Tensor            # [C] float64, mean of zeta over H, W, C
    sigma_top: Tensor | None = None   # [C] float64, mean of the top 10 % of pixels' zeta
    area: Tensor | None = None        # [C] float64, share of pixels with zeta above a threshold
    candidate_views: list[Visibility] | None = None   # [C] what each candidate sees of the model (uses_visibility)
    captured_views: Sequence[Visibility | Seen] | None = None   # [T] what each captured view saw
    target_views: list[Visibility] | None = None      # what each target view (where the model will be looked
                                                      # at from) shows; None: every part counts as it fills a candidate
    candidate_fisher: Tensor | None = None   # [C, G, P] float64 each candidate's diag(J^T J) per splat and group
    captured_fisher: Tensor | None = None    # [G, P] float64 the captured views' sum (uses_fisher)


@dataclass
class Selection:
    order: list[int]              # every candidate, best first; order[:k] is the batch
    scores: list[float]           # [C] each candidate's score when it was ranked
    rule: str = ""                # the rule that made the order, for a strategy that chooses among rules
                                  # by its evidence ("" : the strategy's summary says it)


@dataclass(frozen=True)
class Strategy:
    name: str
    summary: str                  # one line for --help, the API schema and the docs
    select: Callable[[Evidence, int, int], Selection]   # (evidence, k, seed) -> Selection
    uses_dropout: bool = True     # False: the scores ignore sigma (it is still reported)
    uses_visibility: bool = False  # True: needs each view's Visibility (families without it: a fallback order)
    uses_fisher: bool = False      # True: needs each view's Fisher information (`Renderer.fisher`)


def centres(cameras: list[Camera]) -> Tensor:
    """[N, 3] float64 camera centres."""
    if not cameras:
        return torch.zeros(0, 3, dtype=torch.float64)
    return torch.stack([c.center for c in cameras])


def by_score(values: Tensor) -> Selection:
    """Highest score first; ties go to the lower index."""
    order = sorted(range(len(values)), key=lambda i: (-float(values[i]), i))
    return Selection(order, [float(v) for v in values])


def greedy(evidence: Evidence, k: int, gain: Callable[[Tensor], Tensor]) -> Selection:
    """Pick k candidates one at a time, each counted as captured before the next is scored.

    gain(nearest [C]) -> [C]: the value of each candidate given its distance to the
    nearest captured (or already picked) pose. The candidates after the batch follow in
    the order of their value once the batch is chosen.
    """
    cand = centres(evidence.candidates)                          # [C, 3]
    count = len(cand)
    if evidence.captured:
        nearest = torch.cdist(cand, centres(evidence.captured)).min(dim=1).values
    else:   # nothing captured: every candidate is equally far, the scores alone decide
        nearest = torch.ones(count, dtype=torch.float64)
    taken = torch.zeros(count, dtype=torch.bool)
    order, scores = [], [0.0] * count
    for _ in range(min(k, count)):
        values = gain(nearest).masked_fill(taken, -torch.inf)
        i = int(torch.argmax(values))                            # the first maximum: lower index on ties
        order.append(i)
        scores[i] = float(values[i])
        taken[i] = True
        nearest = torch.minimum(nearest, (cand - cand[i]).norm(dim=1))
    values = gain(nearest)
    rest = sorted((i for i in range(count) if not taken[i]), key=lambda i: (-float(values[i]), i))
    for i in rest:
        scores[i] = float(values[i])
    return Selection(order + rest, scores)
