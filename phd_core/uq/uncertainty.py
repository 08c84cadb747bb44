"""Uncertainty: zeta = per-pixel, per-channel standard deviation over N masked renders;
sigma_max = max of zeta over H, W, C; sigma-max-bar = mean of sigma_max over views (Appendix A.1).
The channels are the signal's (`phd_core.renderers.SIGNALS`): RGB over the background (the
paper's), or RGB over black plus alpha.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import torch
from torch import Tensor

from ..errors import InputError
from ..executors import LOCAL, Executor
from ..renderers import DEFAULT_SIGNAL, Renderer, View
from ..renderers.visibility import Visibility, prepare_seeing, reports_visibility
from ..scene import Camera
from .sampling import (
    Progress,
    ProgressTicker,
    RunningStd,
    check_cameras,
    check_dtype,
    check_ratio,
    check_samples,
    check_seed,
    check_signal,
    dropout_uniforms,
    keep_masks,
    masked_renders,
    render_masks,
)

TOP_SHARE = 0.1                    # sigma_top: the share of pixels it averages
AREA_THRESHOLD = 0.05              # area: zeta above this (on [0, 1] colours) counts as uncertain
DEFAULT_SAMPLES = 32               # masks per view for zeta, ranking and selection


@dataclass
class ViewUncertainty:
    """Uncertainty of one view under N dropout masks."""

    sigma_max: float                # max of zeta over H, W, C
    sigma_mean: float               # mean of zeta over H, W, C
    sigma_top: float = 0.0          # mean of the top TOP_SHARE of pixels' zeta (max over C): an upper-quantile mean
    area: float = 0.0               # share of pixels whose zeta (max over C) exceeds AREA_THRESHOLD
    mean: Tensor | None = None      # [H, W, C] float32 mean image over the N samples (keep_maps=True)
    zeta: Tensor | None = None      # [H, W, C] float32 per-pixel per-channel std (keep_maps=True)
    peak: Tensor | None = None      # [H, W] float32 zeta's max over channels, what a heat map draws (keep_peak=True)
    image: Tensor | None = None     # [H, W, 3] float32 the full model's render, from the same prepared view (keep_full)
    visibility: Visibility | None = None   # what the view sees of the model, zeta's channel max per element


def measure_view(view: View, keep: Tensor, ddof: int, keep_maps: bool, dtype: torch.dtype,
                 keep_peak: bool = False, keep_full: bool = False,
                 visibility: Callable[[View, Tensor], Visibility] | None = None,
                 signal: str = DEFAULT_SIGNAL) -> ViewUncertainty:
    running = RunningStd(dtype)                               # never holds all N renders
    for chunk in masked_renders(view, keep, signal):          # [m, H, W, C]
        running.add(chunk)
    zeta, mean = running.result(ddof)
    peak = zeta.amax(dim=-1)                                  # [H, W]
    per_pixel = peak.flatten()                                # [H * W]
    top = per_pixel.topk(max(1, round(TOP_SHARE * per_pixel.numel()))).values
    return ViewUncertainty(
        sigma_max=float(zeta.max()), sigma_mean=float(zeta.mean()), sigma_top=float(top.mean()),
        area=float((per_pixel > AREA_THRESHOLD).double().mean()),
        mean=mean.to(torch.float32) if keep_maps else None,
        zeta=zeta.to(torch.float32) if keep_maps else None,
        peak=peak.to(torch.float32) if keep_peak else None,
        image=render_masks(view, None)[0] if keep_full else None,
        visibility=None if visibility is None else visibility(view, peak))


def measure_views(cameras: list[Camera], renderer: Renderer, keep: Tensor, *, ddof: int, keep_maps: bool,
                  dtype: torch.dtype, keep_peak: bool = False, keep_full: bool = False,
                  keep_visibility: bool = False, signal: str = DEFAULT_SIGNAL) -> list[ViewUncertainty]:
    """measure_view for a chunk of cameras (what an executor runs): one `prepare` per camera
    serves the N masked renders of `signal` and, with keep_full, the full model's composited
    render; with keep_visibility (and a family that reports it), what the view sees of the model,
    from the same view (`prepare_seeing`)."""
    visibility = renderer.visibility if keep_visibility and reports_visibility(renderer) else None
    prepare = renderer.prepare if visibility is None else partial(prepare_seeing, renderer)
    return [measure_view(prepare(camera), keep, ddof, keep_maps, dtype, keep_peak, keep_full, visibility, signal)
            for camera in cameras]


def view_uncertainty(renderer: Renderer, camera: Camera, *, ratio: float, samples: int = DEFAULT_SAMPLES,
                     seed: int = 0, ddof: int = 1, keep_maps: bool = False,
                     dtype: torch.dtype = torch.float64, signal: str = DEFAULT_SIGNAL) -> ViewUncertainty:
    """zeta, sigma_max and sigma_mean of one view from `samples` masked renders (one batched pass).

    ddof=1 (default) is the unbiased sample std and needs samples >= 2; ddof=0 is the
    population std. `dtype` is the accumulation precision of the std; `signal` the images
    zeta is measured on (phd_core.renderers.SIGNALS).
    """
    return uncertainty(renderer, [camera], ratio=ratio, samples=samples, seed=seed, ddof=ddof,
                       keep_maps=keep_maps, dtype=dtype, signal=signal)[0]


def uncertainty(renderer: Renderer, cameras: Sequence[Camera], *, ratio: float,
                samples: int = DEFAULT_SAMPLES, seed: int = 0, ddof: int = 1, keep_maps: bool = False,
                keep_peak: bool = False, progress: Progress | None = None,
                dtype: torch.dtype = torch.float64, executor: Executor = LOCAL,
                keep_visibility: bool = False, signal: str = DEFAULT_SIGNAL) -> list[ViewUncertainty]:
    """view_uncertainty for every camera under the SAME N sub-models (one draw from `seed`).

    keep_maps keeps zeta and the mean image of every view (24 bytes a pixel); keep_peak only
    zeta's max over channels (4 bytes a pixel), enough to draw heat maps after ranking.
    keep_visibility keeps what each view sees of the model (`Renderer.visibility`, with zeta's
    channel max per element) where the family reports it.
    `executor` (phd_core.executors) runs chunks of cameras, anywhere; the masks are drawn
    here and shipped, so every executor gives the same numbers. `signal`: what zeta is
    measured on (phd_core.renderers.SIGNALS; the paper's is the default, "composited").
    """
    ratio = check_ratio(ratio)
    samples, ddof = check_samples(samples, ddof)
    seed = check_seed(seed)
    dtype = check_dtype(dtype)
    signal = check_signal(signal)
    cameras = check_cameras(cameras)
    keep = keep_masks(dropout_uniforms(renderer.num_units, samples, seed), ratio)
    ticker = ProgressTicker(progress, len(cameras))
    chunks = executor.split(cameras)
    parts = executor.map(partial(measure_views, ddof=ddof, keep_maps=keep_maps, dtype=dtype, keep_peak=keep_peak,
                                 keep_visibility=keep_visibility, signal=signal), chunks,
                         executor.share(renderer), keep, done=lambda i: ticker.tick(len(chunks[i])))
    ticker.finish()
    return [view for part in parts for view in part]


def sigma_max_bar(views: Sequence[ViewUncertainty]) -> float:
    """Appendix A.1: the mean over views of each view's sigma_max."""
    if not views:
        raise InputError("views", "no views to average")
    return sum(v.sigma_max for v in views) / len(views)
