"""Calibration (Algorithm 1): r_drop is the largest multiple of `step` below 1 whose mean
|F(x; theta) - F(x; D(theta, r))| over the training views stays below `epsilon`.

Linear scan (the paper's loop) or bisection over the same nested masks; bisection assumes
that the error grows with r for a fixed draw. The linear scan renders LOOKAHEAD ratios per
pass over the views (one mask batch of LOOKAHEAD x samples per view instead of LOOKAHEAD
small ones: the fused compositor's cost per mask halves from 4 to 16 masks); ratios
past the first failure are rendered but not reported, so the result equals a one-by-one scan.
Nesting makes that the rule, not a theorem:
dropping a splat can uncover one of similar colour, so the mean error may dip. Both
searches only return ratios they have evaluated as passing.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor

from ..errors import InputError, check_float, check_int
from ..eval import ssim
from ..executors import LOCAL, Executor
from ..renderers import DEFAULT_SIGNAL, Renderer
from ..scene import Camera
from .sampling import (
    PreparedViews,
    Progress,
    ProgressTicker,
    check_cameras,
    check_images,
    check_seed,
    check_signal,
    check_step,
    dropout_uniforms,
    keep_masks,
    masked_renders,
    render_masks,
)

# Defaults measured on the 16-view lego 3DGS model (docs/uq.md, bench/bench_phdropout.py).
DEFAULT_EPSILON = 0.0175           # mean |full - dropped| per pixel and channel on [0, 1]: on lego16 the
                                   # ratio where mean training SSIM drops 5 % (the reference criterion)
DEFAULT_STEP = 0.05                # dropout-ratio grid of the search
DEFAULT_CALIBRATION_SAMPLES = 4    # masks per ratio during calibration
DEFAULT_SSIM_MARGIN = 0.05         # calibrate_ssim: allowed relative drop of mean SSIM
LOOKAHEAD = 4                      # linear scan: ratios per pass (at most 3 rendered in vain)


class CalibrationError(InputError):
    """r_drop = 0: even the smallest ratio breaks the training views.

    Carries the evaluated error curve so that callers can show it.
    """

    def __init__(self, field: str, reason: str, ratios: list[float], errors: list[float]):
        super().__init__(field, reason)
        self.ratios = ratios
        self.errors = errors


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
    signal: str = DEFAULT_SIGNAL    # the images Error(r) was measured on (phd_core.renderers.SIGNALS)

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


def _expected_passes(grid: int, method: str) -> int:
    return math.ceil(grid / LOOKAHEAD) if method == "linear" else max(1, math.ceil(math.log2(grid + 1)))


def _finish_calibration(k: int, grid: int, step: float, probes: dict[int, float], *, epsilon: float,
                        samples: int, seed: int, method: str, criterion: str,
                        signal: str = DEFAULT_SIGNAL) -> CalibrationResult:
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
                             samples=samples, seed=seed, method=method, capped=capped, warnings=warnings,
                             signal=signal)


@dataclass
class CalibrationChunk:
    """Training views of one executor chunk: cameras and full renders, plus their prepared
    views (`Renderer.prepare`), kept where the chunk lives so that every ratio tried re-uses
    the projection, sort and fragments. Pickling drops them (a worker prepares its own).

    A view's full render (its reference) is taken from the view the first pass prepares for
    its masks: a view the cache cannot keep is prepared once per pass, not once more for its
    reference, and the reference costs one unmasked compositing pass, which stops where each
    pixel is spent. A remote chunk whose references do not come back renders them again at
    each pass, from the views that pass prepares anyway."""

    cameras: list[Camera]
    share: float                                  # of VIEW_CACHE_BYTES, for this chunk's prepared views
    signal: str = DEFAULT_SIGNAL                  # what the renders return (phd_core.renderers.SIGNALS)
    references: list[Tensor] = field(default_factory=list)   # [1, H, W, C] full renders, in camera order
    prepared: PreparedViews | None = None

    def views(self, renderer: Renderer) -> PreparedViews:
        if self.prepared is None:
            self.prepared = PreparedViews(renderer, self.cameras, self.share)
        return self.prepared

    def __getstate__(self) -> dict:
        return {**self.__dict__, "prepared": None}


def dropout_errors(chunk: CalibrationChunk, renderer: Renderer, keep: Tensor, samples: int) -> list[list[float]]:
    """Per view of a chunk, per group of `samples` consecutive masks in keep [G x samples, U]
    (one group per ratio): mean |full - dropped| over the group's masks, pixels and channels.
    The first call renders the chunk's references too, from the same prepared views."""
    views = chunk.views(renderer)
    errors = []
    for i in range(len(views)):
        view = views[i]
        if i == len(chunk.references):
            chunk.references.append(render_masks(view, None, chunk.signal))
        reference = chunk.references[i]
        per_mask = torch.cat([part.to(torch.float64, copy=True).sub_(reference).abs_().sum(dim=(1, 2, 3))  # [m]
                              for part in masked_renders(view, keep, chunk.signal)])
        errors.append((per_mask.view(-1, samples).sum(dim=1) / (samples * reference.numel())).tolist())
    return errors


def check_calibration(epsilon: float, step: float, samples: int, seed: int, method: str,
                      signal: str) -> tuple[float, float, int, int, str]:
    """`calibrate`'s settings, checked: epsilon, step, samples, seed and signal as it uses them.
    Callers that hold a calibration until other inputs are read (the CLI) check them first."""
    epsilon = check_float(epsilon, "epsilon")
    if epsilon <= 0:
        raise InputError("epsilon", f"must be positive, got {epsilon}")
    if method not in ("linear", "bisection"):
        raise InputError("method", f"must be 'linear' or 'bisection', got {method!r}")
    return epsilon, check_step(step), check_int(samples, "samples", 1), check_seed(seed), check_signal(signal)


def calibrate(renderer: Renderer, cameras: Sequence[Camera], *, epsilon: float = DEFAULT_EPSILON,
              step: float = DEFAULT_STEP, samples: int = DEFAULT_CALIBRATION_SAMPLES,
              method: str = "linear", seed: int = 0, progress: Progress | None = None,
              executor: Executor = LOCAL, signal: str = DEFAULT_SIGNAL) -> CalibrationResult:
    """Algorithm 1: the largest dropout ratio whose mean absolute error on the training
    views stays below `epsilon`.

    Error(r) = mean over views (each view weighs the same), masks, pixels and channels of
    |F(x; theta) - F(x; D(theta, r))|, with the same `samples` nested masks for every r.
    `executor` (phd_core.executors) renders chunks of views, anywhere; each chunk's full
    renders stay shared between the ratios. `signal`: the images the error is measured on
    (phd_core.renderers.SIGNALS; the default is the paper's, "composited"); the result records
    it, and zeta must be measured on the same signal. Raises CalibrationError when r_drop would be 0.
    """
    epsilon, step, samples, seed, signal = check_calibration(epsilon, step, samples, seed, method, signal)
    cameras = check_cameras(cameras)

    grid = _grid_size(step)
    ticker = ProgressTicker(progress, len(cameras) * _expected_passes(grid, method))
    model = executor.share(renderer)
    chunks = executor.split(cameras)

    def tick(i: int) -> None:
        ticker.tick(len(chunks[i]))

    # Prepared views are kept across ratios within VIEW_CACHE_BYTES in all (split among chunks).
    views = [executor.share(CalibrationChunk(chunk, 1 / len(chunks), signal)) for chunk in chunks]
    uniforms = dropout_uniforms(renderer.num_units, samples, seed)
    probes: dict[int, float] = {}

    def error(k: int) -> float:
        if k not in probes:
            ks = range(k, min(grid, k + LOOKAHEAD - 1) + 1) if method == "linear" else [k]
            keep = torch.cat([keep_masks(uniforms, _grid_ratio(j, step)) for j in ks])      # [len(ks) x samples, U]
            per_view = [e for part in executor.map(dropout_errors, views, model, keep, samples, done=tick)
                        for e in part]                                                  # [views][len(ks)]
            for g, j in enumerate(ks):
                probes[j] = sum(errors[g] for errors in per_view) / len(per_view)
        return probes[k]

    k = _search(error, grid, epsilon, method)
    if method == "linear":                                          # the one-by-one scan's curve
        probes = {j: e for j, e in probes.items() if j <= k + 1}
    result = _finish_calibration(k, grid, step, probes, epsilon=epsilon, samples=samples, seed=seed,
                                 method=method, criterion=f"mean absolute error on the {signal} images",
                                 signal=signal)
    ticker.finish()
    return result


def calibrate_ssim(renderer: Renderer, cameras: Sequence[Camera], images: Tensor | Sequence[Tensor], *,
                   margin: float = DEFAULT_SSIM_MARGIN, step: float = DEFAULT_STEP,
                   samples: int = DEFAULT_CALIBRATION_SAMPLES, seed: int = 0,
                   progress: Progress | None = None) -> CalibrationResult:
    """The public reference code's criterion: the largest ratio whose mean SSIM against
    the training images drops by less than `margin` relative to the full model's.

    Error(r) = (S(0) - S(r)) / S(0), S = mean SSIM over views and masks. Linear scan.
    images: one [H, W, 3] float in [0, 1] per camera (a tensor [V, H, W, 3] or a list).
    """
    margin = check_float(margin, "margin")
    if not 0 < margin < 1:
        raise InputError("margin", f"must lie in (0, 1), got {margin}")
    step = check_step(step)
    samples = check_int(samples, "samples", 1)
    seed = check_seed(seed)
    cameras = check_cameras(cameras)
    images = check_images(images, cameras)

    grid = _grid_size(step)
    ticker = ProgressTicker(progress, len(cameras) * (1 + grid))
    views = PreparedViews(renderer, cameras)
    full = []
    for i, image in enumerate(images):
        full.append(float(ssim(render_masks(views[i], None), image[None]).mean()))
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
        for i, image in enumerate(images):
            masked = render_masks(views[i], keep)
            scores.append(float(ssim(masked, image[None].expand_as(masked)).mean()))
            ticker.tick()
        probes[k] = (baseline - sum(scores) / len(scores)) / baseline
        return probes[k]

    k = _search(drop, grid, margin, "linear")
    result = _finish_calibration(k, grid, step, probes, epsilon=margin, samples=samples, seed=seed,
                                 method="ssim", criterion="relative drop of mean SSIM")
    ticker.finish()
    return result
