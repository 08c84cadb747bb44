"""Ensemble selection (Section 5.4): per view, the model with the lower score: the paper's
mean zeta; distance to the model's training views times its relative zeta; what of the view
the model's training views did not see times its relative zeta; or (the default) that last
score turned into an error estimate per model by checking each model against the other where
the other was trained."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Any, Sequence, cast

import torch
from torch import Tensor

from ..errors import InputError
from ..eval import ensemble_efficiency, psnr, rmse, ssim
from ..executors import LOCAL, Executor
from ..registry import Registry
from ..renderers import DEFAULT_SIGNAL, Renderer
from ..renderers.visibility import Visibility, reports_visibility
from ..scene import Camera
from .rank import view_visibility
from .sampling import (
    Progress,
    ProgressTicker,
    check_cameras,
    check_images,
    check_ratio,
    check_samples,
    check_seed,
    check_signal,
    dropout_uniforms,
    keep_masks,
)
from .strategies.visibility import uncovered_share
from .uncertainty import DEFAULT_SAMPLES, ViewUncertainty, measure_views


@dataclass
class ViewSelection:
    index: int
    choice: str                     # "a" | "b"
    score_a: float                  # model a's score of this view under the rule (lower wins)
    score_b: float
    image: Tensor | None = None     # [H, W, 3] the chosen model's full render (keep_images=True)
    other_image: Tensor | None = None   # [H, W, 3] the other model's full render (keep_images="both")

    def to_dict(self) -> dict:
        return {"index": self.index, "choice": self.choice, "score_a": self.score_a, "score_b": self.score_b}


@dataclass
class SelectionResult:
    views: list[ViewSelection]
    metrics: dict | None = None     # with ground truth: E_ME, PSNR/SSIM of a, b and the selection

    def to_dict(self) -> dict:
        return {"views": [v.to_dict() for v in self.views], "metrics": self.metrics}


@dataclass(frozen=True)
class SelectionRule:
    """How a view's score is made from a model's mean zeta (`select_models`)."""

    name: str
    summary: str                    # one line for --help and the API schema
    relative: bool                  # zeta relative to the model's own level on its training views
    coverage: bool = False          # times what its training views did not see (else the distance to them)
    checked: bool = False           # scaled to an error by checking each model where the other was trained


SELECTION_RULES: Registry[SelectionRule] = Registry("selection rule")
SELECTION_RULES.register(SelectionRule(
    "coverage_checked", "as coverage_sigma, scaled to an error per model by checking each model against the other's "
    "renders where the other was trained (needs both models' training cameras)", relative=True, coverage=True,
    checked=True))
SELECTION_RULES.register(SelectionRule(
    "coverage_sigma", "the share of the view its training views did not see times the view's mean zeta relative to "
    "the model's own training views", relative=True, coverage=True))
SELECTION_RULES.register(SelectionRule(
    "distance_sigma", "as coverage_sigma with the distance to the model's nearest training camera in place of the "
    "share", relative=True))
SELECTION_RULES.register(SelectionRule("sigma_mean", "the paper's rule, the lower mean zeta", relative=False))
DEFAULT_SELECTION_RULE = "coverage_checked"   # at or above the better model on every pair (docs/nbv.md)


def rules_help() -> str:
    """Each rule with its summary, for --help and the API schema."""
    return "; ".join(f"{name}{' (default)' if name == DEFAULT_SELECTION_RULE else ''}: {rule.summary}"
                     for name, rule in SELECTION_RULES.items())


UNCOVERED_FLOOR = 0.05             # coverage_sigma: a fully covered view still counts its zeta
# coverage_checked: renders closer than this count as equal (below 8-bit quantisation), so two
# models that agree where each was trained keep their scores' order instead of all tying at 0
CHECKED_RMSE_FLOOR = 1e-4
SELECTION_TRAINING_VIEWS = 8       # training views (evenly spaced) that set a model's own zeta level


def _nearest_distance(camera: Camera, training: Sequence[Camera]) -> float:
    return float(torch.stack([c.center for c in training]).sub(camera.center).norm(dim=1).min())


def _training_views(renderer: Renderer, training: Sequence[Camera] | None, name: str, rule: str) -> list[Camera]:
    """A model's training cameras (default: the renderer's), which every rule but `sigma_mean` needs."""
    training = list((renderer.training_cameras or []) if training is None else training)
    if not training:
        raise InputError(name, f"the model carries no training cameras, which rule '{rule}' needs: "
                               "give them with the model, or use rule 'sigma_mean'")
    return training


def level_views(training: list[Camera]) -> list[Camera]:
    """Up to 8 evenly spaced training views: their mean zeta is the level a model's uncertainty
    has where it was trained, which the rules but `sigma_mean` divide by."""
    return training[::max(1, len(training) // SELECTION_TRAINING_VIEWS)][:SELECTION_TRAINING_VIEWS]


def select_models(renderer_a: Renderer, renderer_b: Renderer, cameras: Sequence[Camera], *, ratio_a: float,
                  ratio_b: float, samples: int = DEFAULT_SAMPLES, seed: int = 0,
                  images: Tensor | Sequence[Tensor] | None = None,
                  rule: str = DEFAULT_SELECTION_RULE, training_a: Sequence[Camera] | None = None,
                  training_b: Sequence[Camera] | None = None, keep_images: bool | str = False,
                  progress: Progress | None = None, executor: Executor = LOCAL,
                  signal: str = DEFAULT_SIGNAL) -> SelectionResult:
    """Per view, pick the model with the lower score (each at its own dropout ratio).

    rule "sigma_mean" (the paper): the mean zeta of the view. Rule "distance_sigma": the
    distance from the view to the model's nearest training camera times the view's mean zeta
    relative to the model's mean zeta on its own training views, so two models of different
    size and r_drop are compared like with like. Rule "coverage_sigma": in place of the
    distance, UNCOVERED_FLOOR plus the share of the view's image of the model that its
    training views did not see from a nearby direction (`phd_core.uq.strategies.visibility`;
    families without visibility use the distance). Rule "coverage_checked" (the default,
    docs/nbv.md): the coverage_sigma score times each model's error per unit of score where
    the OTHER model was trained: there the other model's render stands in for the image it
    was fitted to, so RMSE(this model's render, the other's) summed over the other's level
    views, divided by this model's summed score on them, turns scores into errors. A model
    that is worse everywhere (which its relative zeta cannot say) then loses the views it
    would have won.
    training_a / training_b: each model's training cameras (default: the renderer's own).
    Ties go to model a. With ground-truth `images` (one [H, W, 3] per camera), `metrics` holds the
    mean PSNR and SSIM of a, b and the selection, E_ME (mean over views of
    SSIM(selected) / max(SSIM(a), SSIM(b))) and how often the choice was the model
    with the higher SSIM. keep_images: True keeps the chosen model's full render per view,
    "both" also the other model's (to show the two side by side). `executor`
    (phd_core.executors) runs the masked renders in chunks, anywhere; the full renders of
    the chosen models stay in this process. `signal`: what zeta is measured on
    (phd_core.renderers.SIGNALS); the full renders are composited whatever it is.
    """
    ratio_a, ratio_b = check_ratio(ratio_a, "ratio_a"), check_ratio(ratio_b, "ratio_b")
    samples, _ = check_samples(samples, 1)
    seed = check_seed(seed)
    signal = check_signal(signal)
    cameras = check_cameras(cameras)
    chosen = SELECTION_RULES.lookup(rule, "rule")
    if images is not None:
        images = check_images(images, cameras)
    renderers = {"a": renderer_a, "b": renderer_b}
    keeps = {"a": keep_masks(dropout_uniforms(renderer_a.num_units, samples, seed), ratio_a),
             "b": keep_masks(dropout_uniforms(renderer_b.num_units, samples, seed), ratio_b)}
    if chosen.relative:
        given = {"a": training_a, "b": training_b}
        training = {key: _training_views(renderers[key], given[key], f"model_{key}", rule) for key in renderers}
        levels = {key: level_views(training[key]) for key in renderers}
    else:
        levels = {"a": [], "b": []}
    checked = chosen.checked                  # each model also measured at the other's level views
    ticker = ProgressTicker(progress, 2 * len(cameras) + (1 + checked) * (len(levels["a"]) + len(levels["b"])))

    # Full renders: both models when scoring against ground truth, else only the chosen one (made
    # from the prepared view that served the masks, for both models, before the choice is known).
    both = images is not None or keep_images == "both"

    def measure(key: str, views: list[Camera], keep_full: bool = False) -> list[ViewUncertainty]:
        """Each view under model `key`'s masks, on the executor."""
        chunks = executor.split(views)
        parts = executor.map(partial(measure_views, ddof=1, keep_maps=False, dtype=torch.float64,
                                     keep_full=keep_full, keep_visibility=chosen.coverage, signal=signal), chunks,
                             executor.share(renderers[key]), keeps[key], done=lambda i: ticker.tick(len(chunks[i])))
        return [view for part in parts for view in part]

    measured = {key: measure(key, cameras, keep_full=both or bool(keep_images)) for key in renderers}
    if chosen.relative:
        own, at_own = {}, {}
        for key in renderers:
            at_own[key] = measure(key, levels[key], keep_full=checked)
            means = [view.sigma_mean for view in at_own[key]]
            own[key] = max(sum(means) / len(means), 1e-12)
    visible = {key: view_visibility(renderer, training[key]) for key, renderer in renderers.items()
               if chosen.coverage and reports_visibility(renderer)}

    def scores_of(key: str, views: list[Camera], measured_views: list[ViewUncertainty]) -> list[float]:
        """Model `key`'s score of each view (lower: trust it more)."""
        sigma = [view.sigma_mean for view in measured_views]
        if not chosen.relative:
            return sigma
        if key in visible:
            # measured with keep_visibility=chosen.coverage on a family that reports it: never None
            uncovered = uncovered_share(cast(list[Visibility], [view.visibility for view in measured_views]),
                                        visible[key])
            return [(UNCOVERED_FLOOR + float(u)) * s / own[key] for u, s in zip(uncovered, sigma)]
        return [_nearest_distance(c, training[key]) * s / own[key] for c, s in zip(views, sigma)]

    view_scores = {key: scores_of(key, cameras, measured[key]) for key in renderers}
    if checked:
        for key, other in (("a", "b"), ("b", "a")):
            at_other = measure(key, levels[other], keep_full=True)
            error = sum(max(rmse(_full(mine), _full(theirs)), CHECKED_RMSE_FLOOR)
                        for mine, theirs in zip(at_other, at_own[other]))
            per_score = error / max(sum(scores_of(key, levels[other], at_other)), 1e-12)
            view_scores[key] = [score * per_score for score in view_scores[key]]

    views: list[ViewSelection] = []
    scores: dict[str, list] = {"a": [], "b": [], "selected": []}
    for i in range(len(cameras)):
        score_a, score_b = view_scores["a"][i], view_scores["b"][i]
        choice, other = ("a", "b") if score_a <= score_b else ("b", "a")
        image = measured[choice][i].image
        if images is not None:          # so both models were measured with keep_full
            _score_images(scores, _full(measured["a"][i]), _full(measured["b"][i]), _full(measured[choice][i]),
                          images[i])
        views.append(ViewSelection(index=i, choice=choice, score_a=score_a, score_b=score_b,
                                   image=image if keep_images else None,
                                   other_image=measured[other][i].image if keep_images == "both" else None))
    metrics = _selection_metrics(views, scores) if images is not None else None
    ticker.finish()
    return SelectionResult(views=views, metrics=metrics)


def _full(view: ViewUncertainty) -> Tensor:
    """The full render of a view measured with keep_full=True."""
    assert view.image is not None
    return view.image


def _score_images(scores: dict[str, list], image_a: Tensor, image_b: Tensor, selected: Tensor,
                  truth: Tensor) -> None:

    for key, image in (("a", image_a), ("b", image_b), ("selected", selected)):
        scores[key].append((float(psnr(image, truth)), float(ssim(image[None], truth[None]).mean())))


def _selection_metrics(views: list[ViewSelection], scores: dict[str, list]) -> dict:

    ssim_of = {key: [s for _, s in values] for key, values in scores.items()}
    metrics: dict[str, Any] = {}
    for key, values in scores.items():
        mean_psnr = sum(p for p, _ in values) / len(values)     # inf when a render equals its image
        metrics[f"psnr_{key}"] = mean_psnr if math.isfinite(mean_psnr) else None
        metrics[f"ssim_{key}"] = sum(s for _, s in values) / len(values)
    per_view = [max(a, b) for (a, _), (b, _) in zip(scores["a"], scores["b"])]
    oracle = sum(per_view) / len(per_view)
    metrics["psnr_oracle"] = oracle if math.isfinite(oracle) else None   # the better model per view
    metrics["e_me"] = ensemble_efficiency(ssim_of["selected"], ssim_of["a"], ssim_of["b"])
    better = ["a" if a >= b else "b" for a, b in zip(ssim_of["a"], ssim_of["b"])]
    metrics["choices_a"] = sum(v.choice == "a" for v in views)
    metrics["choices_b"] = sum(v.choice == "b" for v in views)
    metrics["choice_matches_higher_ssim"] = sum(v.choice == b for v, b in zip(views, better)) / len(views)
    return metrics
