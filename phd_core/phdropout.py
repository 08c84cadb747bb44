"""PH-Dropout: post hoc epistemic uncertainty from a trained model (ICLR 2025, Algorithm 1).

A keep-mask drops whole dropout units of a trained model (splats for Gaussian Splatting,
first-layer hidden units for NeRF) without rescaling the survivors. The engine only talks
to the renderer protocol (`phd_core.protocol.Renderer`): `render(camera, keep)` returns
one image per mask, so N sub-models of one view cost one batched pass.

Masks are nested: every (sample, unit) gets one uniform number u in [0, 1) from a seeded
generator and the unit is kept where u >= r. Raising r only ever drops more units, one
draw serves every ratio, r = 0 keeps everything and r = 1 drops everything.

- Calibration (Algorithm 1): r_drop is the largest multiple of `step` below 1 whose mean
  |F(x; theta) - F(x; D(theta, r))| over the training views stays below `epsilon`.
  Linear scan (the paper's loop) or bisection over the same nested masks; bisection
  assumes that the error grows with r for a fixed draw. Nesting makes that the rule, not
  a theorem: dropping a splat can uncover one of similar colour, so the mean error may
  dip. Both searches only return ratios they have evaluated as passing.
- Uncertainty: zeta = per-pixel, per-channel standard deviation over the N masked
  renders; sigma_max = max of zeta over H, W, C; sigma-max-bar = mean of sigma_max over
  views (Appendix A.1).
- Next-best view: candidates ordered by a strategy from `phd_core.strategies` (the paper's
  sigma_max is one; the default won the active-learning benchmark, docs/nbv.md).
- Ensemble selection (Section 5.4): per view, the model with the lower score: the paper's
  mean zeta, or (default) distance to the model's training views times its relative zeta.
"""

from __future__ import annotations

import math
import operator
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from .cameras import Camera
from .errors import InputError
from .protocol import Renderer
from .strategies import DEFAULT_STRATEGY, Evidence, get_strategy

# Defaults measured on the 16-view lego 3DGS model (docs/phdropout.md, bench/bench_phdropout.py).
DEFAULT_EPSILON = 0.0175           # mean |full - dropped| per pixel and channel on [0, 1]: on lego16 the
                                   # ratio where mean training SSIM drops 5 % (the reference criterion)
DEFAULT_STEP = 0.05                # dropout-ratio grid of the search
DEFAULT_SAMPLES = 32               # masks per view for zeta, ranking and selection
DEFAULT_CALIBRATION_SAMPLES = 4    # masks per ratio during calibration
DEFAULT_SSIM_MARGIN = 0.05         # calibrate_ssim: allowed relative drop of mean SSIM
MAX_MASKS_PER_RENDER = 64          # masks per renderer.render call (bounds renderer memory)

Progress = Callable[[float], None]


class CalibrationError(InputError):
    """r_drop = 0: even the smallest ratio breaks the training views.

    Carries the evaluated error curve so that callers can show it.
    """

    def __init__(self, field: str, reason: str, ratios: list[float], errors: list[float]):
        super().__init__(field, reason)
        self.ratios = ratios
        self.errors = errors


# ----------------------------------------------------------------------------------------
# Argument checks (every public function validates its numbers with InputError)

def _check_int(value: Any, name: str, minimum: int) -> int:
    if isinstance(value, bool):
        raise InputError(name, f"must be an integer, got {value!r}")
    try:
        value = operator.index(value)
    except TypeError:
        raise InputError(name, f"must be an integer, got {value!r}") from None
    if value < minimum:
        raise InputError(name, f"must be at least {minimum}, got {value}")
    return value


def _check_float(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(name, f"must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(name, f"must be finite, got {value}")
    return value


def _check_ratio(value: Any, name: str = "ratio") -> float:
    value = _check_float(value, name)
    if not 0.0 <= value <= 1.0:
        raise InputError(name, f"dropout ratio must lie in [0, 1], got {value}")
    return value


def _check_seed(seed: Any) -> int:
    seed = _check_int(seed, "seed", 0)
    if seed >= 2**63:
        raise InputError("seed", f"must be below 2**63, got {seed}")
    return seed


def _check_samples(samples: Any, ddof: Any) -> tuple[int, int]:
    ddof = _check_int(ddof, "ddof", 0)
    samples = _check_int(samples, "samples", 1)
    if samples - ddof < 1:
        raise InputError("samples", f"need more than ddof={ddof} samples for a standard deviation, "
                         f"got {samples} (use at least {ddof + 1})")
    return samples, ddof


def _check_cameras(cameras: Sequence[Camera], name: str = "cameras") -> list[Camera]:
    cameras = list(cameras)
    if not cameras:
        raise InputError(name, "no cameras given")
    for i, camera in enumerate(cameras):
        if not isinstance(camera, Camera):
            raise InputError(f"{name}[{i}]", f"must be a Camera, got {type(camera).__name__}")
    return cameras


def _check_step(step: Any) -> float:
    step = _check_float(step, "step")
    if not 0.0 < step < 1.0:
        raise InputError("step", f"must lie in (0, 1), got {step}")
    if step < 1e-4:
        raise InputError("step", f"must be at least 1e-4 (at most 10000 ratios), got {step}")
    return step


# ----------------------------------------------------------------------------------------
# Masks and rendering

def dropout_uniforms(num_units: int, samples: int, seed: int) -> Tensor:
    """One uniform number per (sample, unit): [N, U] float32 in [0, 1), reproducible from `seed`."""
    num_units = _check_int(num_units, "num_units", 0)
    samples = _check_int(samples, "samples", 1)
    generator = torch.Generator().manual_seed(_check_seed(seed))
    return torch.rand((samples, num_units), generator=generator, dtype=torch.float32)


def keep_masks(uniforms: Tensor, ratio: float) -> Tensor:
    """Keep-masks [N, U] bool for dropout ratio `ratio`: unit kept where u >= ratio.

    Masks of a larger ratio are subsets of those of a smaller one (nested).
    """
    return uniforms >= _check_ratio(ratio)


def _render(renderer: Renderer, camera: Camera, keep: Tensor | None) -> Tensor:
    """Render with a batch of keep-masks (None = full model), MAX_MASKS_PER_RENDER at a time.

    Returns [N, H, W, 3] float32, checked for shape and finiteness.
    """
    if keep is None:
        images = renderer.render(camera)
        expected = 1
    else:
        parts = [renderer.render(camera, chunk) for chunk in keep.split(MAX_MASKS_PER_RENDER)]
        images = torch.cat(parts) if len(parts) > 1 else parts[0]
        expected = keep.shape[0]
    shape = (expected, camera.height, camera.width, 3)
    if tuple(images.shape) != shape:
        raise RuntimeError(f"renderer returned shape {list(images.shape)}, expected {list(shape)}")
    if not torch.isfinite(images).all():
        raise RuntimeError("renderer returned NaN or infinite pixel values")
    return images.to(torch.float32)


def sample_std(images: Tensor, *, ddof: int = 1, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """Per-element standard deviation and mean over the first axis, accumulated in `dtype`.

    images: [N, ...]. Two passes over the samples shifted by the first one, so identical
    samples give a standard deviation of exactly 0 in any dtype and nearly equal ones
    lose no precision to cancellation. Divides by N - ddof.
    Returns (std [...], mean [...]), both in `dtype`.
    """
    n = images.shape[0]
    _check_samples(n, ddof)
    shift = images[0].to(dtype)                       # [...]
    total = torch.zeros_like(shift)
    for chunk in images.split(MAX_MASKS_PER_RENDER):
        total += (chunk.to(dtype) - shift).sum(0)
    mean_offset = total / n                          # mean of (x_i - x_0)
    squares = torch.zeros_like(shift)
    for chunk in images.split(MAX_MASKS_PER_RENDER):
        squares += ((chunk.to(dtype) - shift) - mean_offset).square().sum(0)
    std = (squares / (n - ddof)).sqrt()
    return std, shift + mean_offset


# ----------------------------------------------------------------------------------------
# Calibration (Algorithm 1)

@dataclass
class CalibrationResult:
    """r_drop and the error curve it came from (tested ratios, ascending)."""

    r_drop: float
    ratios: list[float]
    errors: list[float]
    epsilon: float          # the threshold (for method "ssim": the SSIM margin)
    step: float
    samples: int
    seed: int
    method: str             # "linear" | "bisection" | "ssim"
    capped: bool            # every ratio passed; r_drop capped at the largest multiple of step below 1
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def _grid_ratio(k: int, step: float) -> float:
    """k * step without float noise (0.30000000000000004 -> 0.3)."""
    return round(k * step, 10)


def _grid_size(step: float) -> int:
    """K: the number of grid ratios step, 2 step, ... strictly below 1."""
    k = math.floor(1.0 / step)
    while _grid_ratio(k, step) >= 1.0:
        k -= 1
    return k


def _search(evaluate: Callable[[int], float], grid: int, threshold: float, method: str) -> int:
    """Largest k in [1, grid] with evaluate(k) < threshold, 0 if none.

    linear: k = 1, 2, ... until the first failure (Algorithm 1).
    bisection: assumes evaluate is non-decreasing in k; k = 0 passes and k = grid + 1
    fails by definition, and the bracket halves until it closes.
    """
    if method == "linear":
        for k in range(1, grid + 1):
            if not evaluate(k) < threshold:
                return k - 1
        return grid
    passing, failing = 0, grid + 1
    while failing - passing > 1:
        k = (passing + failing) // 2
        if evaluate(k) < threshold:
            passing = k
        else:
            failing = k
    return passing


class _ProgressTicker:
    """Turns 'one more view done' into progress(fraction) calls, never beyond 0.99 until done."""

    def __init__(self, progress: Progress | None, total: int):
        self.progress, self.total, self.done = progress, max(total, 1), 0

    def tick(self) -> None:
        self.done += 1
        if self.progress is not None:
            self.progress(min(self.done / self.total, 0.99))

    def finish(self) -> None:
        if self.progress is not None:
            self.progress(1.0)


def _expected_probes(grid: int, method: str) -> int:
    return grid if method == "linear" else max(1, math.ceil(math.log2(grid + 1)))


def _finish_calibration(k: int, grid: int, step: float, probes: dict[int, float], *, epsilon: float,
                        samples: int, seed: int, method: str, criterion: str) -> CalibrationResult:
    ks = sorted(probes)
    ratios = [_grid_ratio(j, step) for j in ks]
    errors = [float(probes[j]) for j in ks]
    if k == 0:
        raise CalibrationError(
            "epsilon",
            f"r_drop = 0: dropping even {ratios[0]:.3g} of the units changes the training views by "
            f"{errors[0]:.4g} ({criterion}), which is not below {epsilon:.4g}. The model is not properly "
            f"trained (too few units for the scene) or epsilon is too small.", ratios, errors)
    r_drop = _grid_ratio(k, step)
    capped = k == grid
    warnings = []
    if capped:
        warnings.append(f"every tested ratio up to {r_drop} stayed below epsilon={epsilon}: r_drop is capped "
                        f"at {r_drop} (never 1, which would drop every unit); epsilon is likely too large")
    return CalibrationResult(r_drop=r_drop, ratios=ratios, errors=errors, epsilon=epsilon, step=step,
                             samples=samples, seed=seed, method=method, capped=capped, warnings=warnings)


def calibrate(renderer: Renderer, cameras: Sequence[Camera], *, epsilon: float = DEFAULT_EPSILON,
              step: float = DEFAULT_STEP, samples: int = DEFAULT_CALIBRATION_SAMPLES,
              method: str = "linear", seed: int = 0, progress: Progress | None = None) -> CalibrationResult:
    """Algorithm 1: the largest dropout ratio whose mean absolute error on the training
    views stays below `epsilon`.

    Error(r) = mean over views (each view weighs the same), masks, pixels and channels of
    |F(x; theta) - F(x; D(theta, r))|, with the same `samples` nested masks for every r.
    Raises CalibrationError when r_drop would be 0.
    """
    epsilon = _check_float(epsilon, "epsilon")
    if epsilon <= 0:
        raise InputError("epsilon", f"must be positive, got {epsilon}")
    step = _check_step(step)
    samples = _check_int(samples, "samples", 1)
    seed = _check_seed(seed)
    if method not in ("linear", "bisection"):
        raise InputError("method", f"must be 'linear' or 'bisection', got {method!r}")
    cameras = _check_cameras(cameras)

    grid = _grid_size(step)
    ticker = _ProgressTicker(progress, len(cameras) * (1 + _expected_probes(grid, method)))
    references = []                                   # [1, H, W, 3] full renders
    for camera in cameras:
        references.append(_render(renderer, camera, None).double())
        ticker.tick()
    uniforms = dropout_uniforms(renderer.num_units, samples, seed)
    probes: dict[int, float] = {}

    def error(k: int) -> float:
        if k not in probes:
            keep = keep_masks(uniforms, _grid_ratio(k, step))
            per_view = []
            for camera, reference in zip(cameras, references):
                per_view.append((_render(renderer, camera, keep).double() - reference).abs().mean().item())
                ticker.tick()
            probes[k] = sum(per_view) / len(per_view)
        return probes[k]

    k = _search(error, grid, epsilon, method)
    result = _finish_calibration(k, grid, step, probes, epsilon=epsilon, samples=samples, seed=seed,
                                 method=method, criterion="mean absolute error")
    ticker.finish()
    return result


def calibrate_ssim(renderer: Renderer, cameras: Sequence[Camera], images: Tensor, *,
                   margin: float = DEFAULT_SSIM_MARGIN, step: float = DEFAULT_STEP,
                   samples: int = DEFAULT_CALIBRATION_SAMPLES, seed: int = 0,
                   progress: Progress | None = None) -> CalibrationResult:
    """The public reference code's criterion: the largest ratio whose mean SSIM against
    the training images drops by less than `margin` relative to the full model's.

    Error(r) = (S(0) - S(r)) / S(0), S = mean SSIM over views and masks. Linear scan.
    images: [V, H, W, 3] float in [0, 1], one per camera.
    """
    from .metrics import ssim

    margin = _check_float(margin, "margin")
    if not 0 < margin < 1:
        raise InputError("margin", f"must lie in (0, 1), got {margin}")
    step = _check_step(step)
    samples = _check_int(samples, "samples", 1)
    seed = _check_seed(seed)
    cameras = _check_cameras(cameras)
    images = _check_images(images, cameras)

    grid = _grid_size(step)
    ticker = _ProgressTicker(progress, len(cameras) * (1 + grid))
    full = []
    for camera, image in zip(cameras, images):
        full.append(float(ssim(_render(renderer, camera, None), image[None]).mean()))
        ticker.tick()
    baseline = sum(full) / len(full)
    if baseline <= 0:
        raise CalibrationError("images", f"the full model's mean SSIM against the images is {baseline:.4g}; "
                               "a relative drop is undefined (wrong images or an untrained model)", [], [])
    uniforms = dropout_uniforms(renderer.num_units, samples, seed)
    probes: dict[int, float] = {}

    def drop(k: int) -> float:
        keep = keep_masks(uniforms, _grid_ratio(k, step))
        scores = []
        for camera, image in zip(cameras, images):
            masked = _render(renderer, camera, keep)
            scores.append(float(ssim(masked, image[None].expand_as(masked)).mean()))
            ticker.tick()
        probes[k] = (baseline - sum(scores) / len(scores)) / baseline
        return probes[k]

    k = _search(drop, grid, margin, "linear")
    result = _finish_calibration(k, grid, step, probes, epsilon=margin, samples=samples, seed=seed,
                                 method="ssim", criterion="relative drop of mean SSIM")
    ticker.finish()
    return result


def _check_images(images: Tensor, cameras: list[Camera], name: str = "images") -> Tensor:
    if not isinstance(images, Tensor):
        raise InputError(name, f"must be a tensor [V, H, W, 3], got {type(images).__name__}")
    if images.dim() != 4 or images.shape[0] != len(cameras) or images.shape[-1] != 3:
        raise InputError(name, f"must have shape [{len(cameras)}, H, W, 3] (one per camera), "
                         f"got {list(images.shape)}")
    for i, camera in enumerate(cameras):
        if tuple(images.shape[1:3]) != (camera.height, camera.width):
            raise InputError(name, f"image {i} is {images.shape[2]}x{images.shape[1]} but its camera "
                             f"renders {camera.width}x{camera.height}")
    if not torch.isfinite(images).all():
        raise InputError(name, "contains NaN or infinite values")
    return images.to(torch.float32)


# ----------------------------------------------------------------------------------------
# Uncertainty

@dataclass
class ViewUncertainty:
    """Uncertainty of one view under N dropout masks."""

    sigma_max: float                # max of zeta over H, W, C
    sigma_mean: float               # mean of zeta over H, W, C
    mean: Tensor | None = None      # [H, W, 3] float32 mean image over the N samples (keep_maps=True)
    zeta: Tensor | None = None      # [H, W, 3] float32 per-pixel per-channel std (keep_maps=True)


def _view_uncertainty(renderer: Renderer, camera: Camera, keep: Tensor, ddof: int, keep_maps: bool,
                      dtype: torch.dtype) -> ViewUncertainty:
    images = _render(renderer, camera, keep)             # [N, H, W, 3]
    zeta, mean = sample_std(images, ddof=ddof, dtype=dtype)
    return ViewUncertainty(
        sigma_max=float(zeta.max()), sigma_mean=float(zeta.mean()),
        mean=mean.to(torch.float32) if keep_maps else None,
        zeta=zeta.to(torch.float32) if keep_maps else None)


def _check_dtype(dtype: Any) -> torch.dtype:
    if dtype not in (torch.float32, torch.float64):
        raise InputError("dtype", f"accumulation dtype must be torch.float32 or torch.float64, got {dtype}")
    return dtype


def view_uncertainty(renderer: Renderer, camera: Camera, *, ratio: float, samples: int = DEFAULT_SAMPLES,
                     seed: int = 0, ddof: int = 1, keep_maps: bool = False,
                     dtype: torch.dtype = torch.float64) -> ViewUncertainty:
    """zeta, sigma_max and sigma_mean of one view from `samples` masked renders (one batched pass).

    ddof=1 (default) is the unbiased sample std and needs samples >= 2; ddof=0 is the
    population std. `dtype` is the accumulation precision of the std.
    """
    return uncertainty(renderer, [camera], ratio=ratio, samples=samples, seed=seed, ddof=ddof,
                       keep_maps=keep_maps, dtype=dtype)[0]


def uncertainty(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float,
                samples: int = DEFAULT_SAMPLES, seed: int = 0, ddof: int = 1, keep_maps: bool = False,
                progress: Progress | None = None, dtype: torch.dtype = torch.float64) -> list[ViewUncertainty]:
    """view_uncertainty for every camera under the SAME N sub-models (one draw from `seed`)."""
    ratio = _check_ratio(ratio)
    samples, ddof = _check_samples(samples, ddof)
    seed = _check_seed(seed)
    dtype = _check_dtype(dtype)
    cameras = _check_cameras(cameras)
    keep = keep_masks(dropout_uniforms(renderer.num_units, samples, seed), ratio)
    ticker = _ProgressTicker(progress, len(cameras))
    views = []
    for camera in cameras:
        views.append(_view_uncertainty(renderer, camera, keep, ddof, keep_maps, dtype))
        ticker.tick()
    ticker.finish()
    return views


def sigma_max_bar(views: Sequence[ViewUncertainty]) -> float:
    """Appendix A.1: the mean over views of each view's sigma_max."""
    if not views:
        raise InputError("views", "no views to average")
    return sum(v.sigma_max for v in views) / len(views)


# ----------------------------------------------------------------------------------------
# Next-best-view ranking

@dataclass
class RankedView:
    index: int          # position of the candidate in the input list
    sigma_max: float
    sigma_mean: float
    score: float        # the strategy's score when the candidate was ranked
    rank: int           # 0 = capture first; ranks 0..k-1 are a batch to capture together

    def to_dict(self) -> dict:
        return asdict(self)


def candidate_evidence(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float,
                       samples: int = DEFAULT_SAMPLES, seed: int = 0, captured: Sequence[Camera] | None = None,
                       progress: Progress | None = None) -> Evidence:
    """What a strategy sees: the candidates' PH-Dropout statistics under one draw of N
    sub-models, and the captured poses (default: the model's training cameras)."""
    views = uncertainty(renderer, cameras, ratio=ratio, samples=samples, seed=seed, progress=progress)
    if captured is None:
        captured = renderer.training_cameras or []
    captured = _check_cameras(captured, "captured") if captured else []
    return Evidence(list(cameras), captured, torch.tensor([v.sigma_max for v in views], dtype=torch.float64),
                    torch.tensor([v.sigma_mean for v in views], dtype=torch.float64))


def rank_views(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float, samples: int = DEFAULT_SAMPLES,
               seed: int = 0, top_k: int | None = None, strategy: str = DEFAULT_STRATEGY,
               captured: Sequence[Camera] | None = None, progress: Progress | None = None) -> list[RankedView]:
    """Candidates in the order the strategy would capture them; ties go to the lower index.

    top_k keeps the first k, a batch meant to be captured together (all when k exceeds the
    number of candidates). Every candidate carries sigma_max and sigma_mean whatever the
    strategy. `captured` are the poses already taken (default: the model's training cameras).
    """
    chosen = get_strategy(strategy)
    if top_k is not None:
        top_k = _check_int(top_k, "top_k", 1)
    evidence = candidate_evidence(renderer, cameras, ratio=ratio, samples=samples, seed=seed, captured=captured,
                                  progress=progress)
    count = len(evidence.candidates)
    selection = chosen.select(evidence, count if top_k is None else min(top_k, count), seed)
    order = selection.order if top_k is None else selection.order[:top_k]
    return [RankedView(index=i, sigma_max=float(evidence.sigma_max[i]), sigma_mean=float(evidence.sigma_mean[i]),
                       score=selection.scores[i], rank=rank) for rank, i in enumerate(order)]


# ----------------------------------------------------------------------------------------
# Ensemble selection (Section 5.4)

@dataclass
class ViewSelection:
    index: int
    choice: str                     # "a" | "b"
    score_a: float                  # model a's score of this view under the rule (lower wins)
    score_b: float
    image: Tensor | None = None     # [H, W, 3] the chosen model's full render (keep_images=True)

    def to_dict(self) -> dict:
        return {"index": self.index, "choice": self.choice, "score_a": self.score_a, "score_b": self.score_b}


@dataclass
class SelectionResult:
    views: list[ViewSelection]
    metrics: dict | None = None     # with ground truth: E_ME, PSNR/SSIM of a, b and the selection

    def to_dict(self) -> dict:
        return {"views": [v.to_dict() for v in self.views], "metrics": self.metrics}


SELECTION_RULES = ("distance_sigma", "sigma_mean")
DEFAULT_SELECTION_RULE = "distance_sigma"
SELECTION_TRAINING_VIEWS = 8       # training views (evenly spaced) that set a model's own zeta level


def _nearest_distance(camera: Camera, training: Sequence[Camera]) -> float:
    return float(torch.stack([c.center for c in training]).sub(camera.center).norm(dim=1).min())


def _own_level(renderer: Renderer, training: Sequence[Camera] | None, keep: Tensor,
               name: str) -> tuple[list[Camera], float]:
    """A model's training cameras (default: the renderer's) and its mean zeta over up to 8 of
    them: the level its uncertainty has where it was trained, which `distance_sigma` divides by."""
    training = list(renderer.training_cameras or [] if training is None else training)
    if not training:
        raise InputError(name, "the model carries no training cameras, which rule 'distance_sigma' needs: "
                               "give them with the model, or use rule 'sigma_mean'")
    step = max(1, len(training) // SELECTION_TRAINING_VIEWS)
    levels = [_view_uncertainty(renderer, c, keep, 1, False, torch.float64).sigma_mean
              for c in training[::step][:SELECTION_TRAINING_VIEWS]]
    return training, max(sum(levels) / len(levels), 1e-12)


def select_models(renderer_a: Renderer, renderer_b: Renderer, cameras: Sequence[Camera], *, ratio_a: float,
                  ratio_b: float, samples: int = DEFAULT_SAMPLES, seed: int = 0, images: Tensor | None = None,
                  rule: str = DEFAULT_SELECTION_RULE, training_a: Sequence[Camera] | None = None,
                  training_b: Sequence[Camera] | None = None, keep_images: bool = False,
                  progress: Progress | None = None) -> SelectionResult:
    """Per view, pick the model with the lower score (each at its own dropout ratio).

    rule "sigma_mean" (the paper): the mean zeta of the view. Rule "distance_sigma" (the
    default, docs/nbv.md): the distance from the view to the model's nearest training
    camera times the view's mean zeta relative to the model's mean zeta on its own
    training views, so two models of different size and r_drop are compared like with like.
    training_a / training_b: each model's training cameras (default: the renderer's own).
    Ties go to model a. With ground-truth `images` [V, H, W, 3], `metrics` holds the
    mean PSNR and SSIM of a, b and the selection, E_ME (mean over views of
    SSIM(selected) / max(SSIM(a), SSIM(b))) and how often the choice was the model
    with the higher SSIM.
    """
    ratio_a, ratio_b = _check_ratio(ratio_a, "ratio_a"), _check_ratio(ratio_b, "ratio_b")
    samples, _ = _check_samples(samples, 1)
    seed = _check_seed(seed)
    cameras = _check_cameras(cameras)
    if rule not in SELECTION_RULES:
        raise InputError("rule", f"must be one of {', '.join(SELECTION_RULES)}, got {rule!r}")
    if images is not None:
        images = _check_images(images, cameras)
    renderers = {"a": renderer_a, "b": renderer_b}
    keeps = {"a": keep_masks(dropout_uniforms(renderer_a.num_units, samples, seed), ratio_a),
             "b": keep_masks(dropout_uniforms(renderer_b.num_units, samples, seed), ratio_b)}
    if rule == "distance_sigma":
        training = {"a": training_a, "b": training_b}
        own = {key: _own_level(renderers[key], training[key], keeps[key], f"model_{key}") for key in renderers}

    def score(key: str, camera: Camera) -> float:
        sigma = _view_uncertainty(renderers[key], camera, keeps[key], 1, False, torch.float64).sigma_mean
        if rule == "sigma_mean":
            return sigma
        training, level = own[key]
        return _nearest_distance(camera, training) * sigma / level

    ticker = _ProgressTicker(progress, len(cameras))
    views, scores = [], {"a": [], "b": [], "selected": []}
    for i, camera in enumerate(cameras):
        score_a, score_b = score("a", camera), score("b", camera)
        choice = "a" if score_a <= score_b else "b"
        # Full renders: both models when scoring against ground truth, else only the chosen one.
        needed = ("a", "b") if images is not None else (choice,) if keep_images else ()
        full = {key: _render(renderers[key], camera, None)[0] for key in needed}
        image = full.get(choice)
        if images is not None:
            _score_images(scores, full["a"], full["b"], image, images[i])
        views.append(ViewSelection(index=i, choice=choice, score_a=score_a, score_b=score_b,
                                   image=image if keep_images else None))
        ticker.tick()
    metrics = _selection_metrics(views, scores) if images is not None else None
    ticker.finish()
    return SelectionResult(views=views, metrics=metrics)


def _score_images(scores: dict[str, list], image_a: Tensor, image_b: Tensor, selected: Tensor,
                  truth: Tensor) -> None:
    from .metrics import psnr, ssim

    for key, image in (("a", image_a), ("b", image_b), ("selected", selected)):
        scores[key].append((float(psnr(image, truth)), float(ssim(image[None], truth[None]).mean())))


def _selection_metrics(views: list[ViewSelection], scores: dict[str, list]) -> dict:
    from .uq_metrics import ensemble_efficiency

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
