"""Next-best view: candidates ordered by a strategy from `phd_core.uq.strategies` (the
paper's sigma_max is one; the default won the active-learning benchmark, docs/nbv.md)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Iterable, Sequence, cast

import torch

from ..errors import InputError, check_float, check_int
from ..executors import LOCAL, Executor
from ..renderers import DEFAULT_SIGNAL, Renderer
from ..renderers.visibility import ReportsVisibility, Visibility, reports_visibility
from ..scene import Camera
from .sampling import Progress, check_cameras
from .strategies import DEFAULT_STRATEGY, STRATEGIES, Evidence, get_strategy
from .strategies.captured import CapturedStore, captured_seen
from .uncertainty import DEFAULT_SAMPLES, ViewUncertainty, uncertainty


@dataclass
class RankedView:
    index: int          # position of the candidate in the input list
    sigma_max: float
    sigma_mean: float
    score: float        # the strategy's score when the candidate was ranked
    rank: int           # 1 = capture first; ranks 1..k are a batch to capture together (as every table says)
    refined: bool = True  # False: scored only at the coarse resolution (rank_views' coarse pass)
    peak: torch.Tensor | None = field(default=None, repr=False)  # [H, W] zeta max over channels (keep_peak=True)

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k != "peak"}


class Ranking(list[RankedView]):
    """`rank_views`' answer: the ranked views in order, and `rule`, in words, the rule that ordered them
    (a strategy may choose among rules by what it is told: the default follows targets that are the
    capture's own path, and spreads from the captured views otherwise)."""

    def __init__(self, views: Iterable[RankedView], rule: str):
        super().__init__(views)
        self.rule = rule


def candidate_evidence(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float,
                       samples: int = DEFAULT_SAMPLES, seed: int = 0, captured: Sequence[Camera] | None = None,
                       keep_peak: bool = False, progress: Progress | None = None,
                       executor: Executor = LOCAL, visibility: bool = False,
                       fisher: bool = False, signal: str = DEFAULT_SIGNAL,
                       captured_store: CapturedStore | None = None,
                       targets: Sequence[Camera] | None = None) -> tuple[Evidence, list[ViewUncertainty]]:
    """What a strategy sees: the candidates' PH-Dropout statistics under one draw of N
    sub-models, and the captured poses (default: the model's training cameras); with the
    per-view measurements (keeping zeta's channel max when keep_peak). With `visibility`
    (and a family that reports it) also what each candidate, captured and target view sees of the model;
    with `fisher`, each view's Fisher information (`add_fisher`). `signal`: what zeta is
    measured on (phd_core.renderers.SIGNALS). What the captured views saw comes from
    `captured_store` where it holds them (`phd_core.uq.strategies.captured`)."""
    views = uncertainty(renderer, cameras, ratio=ratio, samples=samples, seed=seed, keep_peak=keep_peak,
                        progress=progress, executor=executor, keep_visibility=visibility, signal=signal)
    captured = captured_cameras(renderer, captured)

    def stat(name: str) -> torch.Tensor:
        return torch.tensor([getattr(v, name) for v in views], dtype=torch.float64)
    evidence = Evidence(list(cameras), captured, stat("sigma_max"), stat("sigma_mean"), stat("sigma_top"), stat("area"))
    if visibility and reports_visibility(renderer):
        # measured with keep_visibility on a family that reports it: every view has one
        evidence.candidate_views = cast(list[Visibility], [v.visibility for v in views])
        evidence.captured_views = captured_seen(renderer, captured, captured_store)
        evidence.target_views = view_visibility(renderer, targets) if targets else None
    if fisher:
        add_fisher(evidence, renderer, seed)
    return evidence, views


def captured_cameras(renderer: Renderer, captured: Sequence[Camera] | None) -> list[Camera]:
    """The poses already taken: `captured`, or the model's training cameras (maybe none)."""
    if captured is None:
        captured = renderer.training_cameras or []
    return check_cameras(captured, "captured") if captured else []


def view_visibility(renderer: ReportsVisibility, cameras: Sequence[Camera]) -> list[Visibility]:
    """What each camera sees of the model (one render of the full model each)."""
    return [renderer.visibility(renderer.prepare(camera)) for camera in cameras]


def visibility_evidence(renderer: Renderer, cameras: Sequence[Camera], captured: Sequence[Camera] | None = None,
                        targets: Sequence[Camera] | None = None) -> Evidence:
    """What a strategy that ignores dropout sees: the poses and, where the family reports it,
    each view's visibility (no dropout renders; sigma is reported as 0)."""
    captured = captured_cameras(renderer, captured)
    zeros = torch.zeros(len(cameras), dtype=torch.float64)
    evidence = Evidence(list(cameras), captured, zeros, zeros)
    if reports_visibility(renderer):
        evidence.candidate_views = view_visibility(renderer, cameras)
        evidence.captured_views = captured_seen(renderer, captured)
        evidence.target_views = view_visibility(renderer, targets) if targets else None
    return evidence


def check_target_strategy(strategy: str) -> None:
    """An InputError on `targets` unless `strategy` weighs the model's coverage by target views."""
    if not get_strategy(strategy).uses_visibility:
        names = ", ".join(name for name, s in STRATEGIES.items() if s.uses_visibility)
        raise InputError("targets", f"strategy {strategy!r} ignores target views; choose one that weighs the model's "
                         f"coverage by them ({names})")


def check_targets(renderer: Renderer, targets: Sequence[Camera] | None, strategy: str) -> list[Camera] | None:
    """The target views (where the model will be looked at from), or None for none: only the
    coverage strategies weigh by them, and only on a family that reports visibility."""
    if targets is None:
        return None
    targets = check_cameras(targets, "targets")
    check_target_strategy(strategy)
    if not reports_visibility(renderer):
        raise InputError("targets", "this model's family cannot report what a view sees of it, which target views "
                         "need")
    return targets


def add_fisher(evidence: Evidence, renderer: Renderer, seed: int = 0) -> Evidence:
    """Each candidate's and the captured views' Fisher information, where the family computes it
    (`Renderer.fisher`; FisherRF's quantity by random projections)."""
    fisher = getattr(renderer, "fisher", None)      # an optional method, not on the Renderer protocol
    if callable(fisher):
        evidence.candidate_fisher = torch.stack([fisher(c, seed=seed) for c in evidence.candidates])
        held = [fisher(c, seed=seed) for c in evidence.captured]
        evidence.captured_fisher = (torch.stack(held).sum(0) if held else
                                    torch.zeros_like(evidence.candidate_fisher[0]))
    return evidence


COARSE_REFINE_SHARE = 0.2     # coarse-to-fine: re-score this share of the candidates at full size (at least top_k)


def check_coarse(coarse: float | None, refine: int | None) -> tuple[float | None, int | None]:
    """The coarse pass's scale (0 < coarse < 1, or None: no coarse pass) and the number of
    candidates to re-score at full size (None: the default share)."""
    if coarse is not None:
        coarse = check_float(coarse, "coarse")
        if not 0 < coarse < 1:
            raise InputError("coarse", f"must lie strictly between 0 and 1 (a scale of the image size), got {coarse}")
    if refine is not None:
        if coarse is None:
            raise InputError("refine", "re-scoring needs a coarse pass: give coarse too")
        refine = check_int(refine, "refine", 1)
    return coarse, refine


def check_rank(renderer: Renderer, strategy: str, top_k: int | None, coarse: float | None, refine: int | None,
               targets: Sequence[Camera] | None
               ) -> tuple[int | None, float | None, int | None, list[Camera] | None]:
    """`rank_views`' choices, checked as it uses them (top_k, coarse, refine, targets for the
    strategy): callers that calibrate before ranking (the CLI) check them first."""
    get_strategy(strategy)
    if top_k is not None:
        top_k = check_int(top_k, "top_k", 1)
    coarse, refine = check_coarse(coarse, refine)
    return top_k, coarse, refine, check_targets(renderer, targets, strategy)


def coarse_cameras(cameras: Sequence[Camera], scale: float) -> list[Camera]:
    """The cameras at `scale` times their size (at least 1 x 1 pixels), intrinsics scaled."""
    return [c.resized(max(1, round(c.width * scale)), max(1, round(c.height * scale))) for c in cameras]


def targets_at_size(targets: Sequence[Camera], candidates: Sequence[Camera]) -> list[Camera]:
    """The target views at the candidates' render size: each scaled, its aspect kept, so that its
    longer side is the candidates' longest. Targets only weigh what they show, so they need the
    resolution the candidates are judged at, not their photos' (a capture's 720x1280 frames
    would otherwise render above a server's cap while its candidates render at a tenth of that)."""
    side = max(max(c.width, c.height) for c in candidates)
    return [coarse_cameras([t], side / max(t.width, t.height))[0] for t in targets]


def rank_views(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float, samples: int = DEFAULT_SAMPLES,
               seed: int = 0, top_k: int | None = None, strategy: str = DEFAULT_STRATEGY,
               captured: Sequence[Camera] | None = None, keep_peak: bool = False,
               progress: Progress | None = None, executor: Executor = LOCAL,
               coarse: float | None = None, refine: int | None = None,
               signal: str = DEFAULT_SIGNAL, captured_store: CapturedStore | None = None,
               targets: Sequence[Camera] | None = None) -> Ranking:
    """Candidates in the order the strategy would capture them, and the rule that ordered them (`Ranking`);
    ties go to the lower index.

    top_k keeps the first k, a batch meant to be captured together (all when k exceeds the
    number of candidates). Every candidate carries sigma_max and sigma_mean whatever the
    strategy. `captured` are the poses already taken (default: the model's training cameras).
    keep_peak keeps each returned view's zeta channel max, so heat maps need no second render
    (4 bytes a pixel for every candidate until the ranking is known).
    `executor` (phd_core.executors) renders the candidates in chunks, anywhere: the same
    masks go to every chunk, so the ranking is the local one. `signal`: what zeta is measured
    on (phd_core.renderers.SIGNALS; rank at a ratio calibrated on the same signal).
    `captured_store` keeps what the captured views saw between ranks (strategies that use
    visibility; `phd_core.uq.strategies.captured`): a rank renders only the views it lacks.
    `targets`: the views the model will be looked at from (a walkthrough, a turntable ring):
    the coverage strategies then value a candidate by what it fixes in those views
    (`strategies.targets`); None ranks for every view alike.

    Coarse to fine (`coarse`, a scale in (0, 1)): every candidate is ranked at `coarse`
    times its size, then the best `refine` (default: COARSE_REFINE_SHARE of them, at least
    top_k) are ranked again at full size under the same masks and come first; the others
    follow in their coarse order with their coarse statistics and peaks (refined=False). The price
    and the agreement with the full-size ranking are in docs/performance.md.
    """
    chosen = get_strategy(strategy)
    top_k, coarse, refine, targets = check_rank(renderer, strategy, top_k, coarse, refine, targets)
    if coarse is not None:
        return coarse_to_fine(renderer, cameras, coarse, refine, ratio=ratio, samples=samples, seed=seed,
                              top_k=top_k, strategy=strategy, captured=captured, keep_peak=keep_peak,
                              progress=progress, executor=executor, signal=signal, captured_store=captured_store,
                              targets=targets)
    evidence, views = candidate_evidence(renderer, cameras, ratio=ratio, samples=samples, seed=seed,
                                         captured=captured, keep_peak=keep_peak, progress=progress,
                                         executor=executor, visibility=chosen.uses_visibility,
                                         fisher=chosen.uses_fisher, signal=signal, captured_store=captured_store,
                                         targets=targets)
    count = len(evidence.candidates)
    selection = chosen.select(evidence, count if top_k is None else min(top_k, count), seed)
    order = selection.order if top_k is None else selection.order[:top_k]
    ranked = (RankedView(index=i, sigma_max=float(evidence.sigma_max[i]), sigma_mean=float(evidence.sigma_mean[i]),
                         score=selection.scores[i], rank=rank, peak=views[i].peak) for rank, i in enumerate(order, 1))
    return Ranking(ranked, selection.rule or chosen.summary)


def coarse_to_fine(renderer: Renderer, cameras: Sequence[Camera], coarse: float, refine: int | None, *,
                   top_k: int | None, keep_peak: bool, progress: Progress | None, **rank_args) -> Ranking:
    """`rank_views` with a coarse pass (see there): all candidates at `coarse` times their
    size, then the best `refine` again at full size."""
    cameras = check_cameras(cameras, "cameras")
    count = len(cameras)
    if refine is None:
        refine = max(math.ceil(COARSE_REFINE_SHARE * count), top_k or 1)
    refine = min(refine, count)
    half = (lambda start: (lambda done: progress(start + done / 2))) if progress is not None else (lambda start: None)
    first = rank_views(renderer, coarse_cameras(cameras, coarse), keep_peak=keep_peak, progress=half(0.0), **rank_args)
    best = [v.index for v in first[:refine]]
    fine = rank_views(renderer, [cameras[i] for i in best], keep_peak=keep_peak, progress=half(0.5), **rank_args)
    ranked = [replace(v, index=best[v.index]) for v in fine]
    ranked += [replace(v, rank=len(ranked) + j, refined=False) for j, v in enumerate(first[refine:], 1)]
    return Ranking(ranked if top_k is None else ranked[:top_k], fine.rule)
