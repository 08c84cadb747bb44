"""How good is an uncertainty estimate? Correlations, sparsification (AUSE), ranking
agreement, trends over training-set size and ensemble efficiency.

All statistics run in float64 and return None where they are undefined (a constant
input, a zero reference error, too few points), never NaN: None becomes `null` in JSON.
Pixel-level statistics treat every (pixel, channel) element as one sample: zeta is a
per-channel std and the error is the per-channel absolute error (the paper's "RMSE per
pixel and channel").
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError

AUSE_STEPS = 100        # removed fractions 0, 1/100, ..., 99/100
AUSE_METRICS = ("rmse", "mse", "mae")


def _vector(values: Any, name: str) -> Tensor:
    """Any tensor, array or sequence of numbers -> flat float64 tensor, checked finite."""
    if isinstance(values, Tensor):
        vector = values.detach().reshape(-1).to(torch.float64)
    else:
        vector = torch.as_tensor(np.asarray(values, dtype=np.float64).reshape(-1))
    if not torch.isfinite(vector).all():
        raise InputError(name, "contains NaN or infinite values")
    return vector


def _pair(x: Any, y: Any, names: tuple[str, str] = ("x", "y")) -> tuple[Tensor, Tensor]:
    x, y = _vector(x, names[0]), _vector(y, names[1])
    if x.numel() != y.numel():
        raise InputError(names[1], f"has {y.numel()} values but {names[0]} has {x.numel()}")
    return x, y


def _is_constant(v: Tensor) -> bool:
    return v.numel() < 2 or bool(v.min() == v.max())


def rankdata(values: Any) -> Tensor:
    """1-based ranks, ties sharing the average of their ranks: [n] float64."""
    v = _vector(values, "values")
    sorted_v, order = torch.sort(v, stable=True)
    _, counts = torch.unique_consecutive(sorted_v, return_counts=True)
    ends = torch.cumsum(counts, 0).to(torch.float64)          # last 1-based rank of each tie group
    average = ends - (counts.to(torch.float64) - 1) / 2       # mean of start..end
    ranks = torch.empty_like(v)
    ranks[order] = torch.repeat_interleave(average, counts)
    return ranks


def pearson(x: Any, y: Any) -> float | None:
    """Pearson correlation; None when either input is constant or has fewer than 2 values."""
    x, y = _pair(x, y)
    if _is_constant(x) or _is_constant(y):
        return None
    xc, yc = x - x.mean(), y - y.mean()
    denominator = xc.norm() * yc.norm()
    if denominator == 0:
        return None
    return max(-1.0, min(1.0, float((xc @ yc) / denominator)))


def spearman(x: Any, y: Any) -> float | None:
    """Spearman rank correlation (average ranks for ties); None when undefined."""
    x, y = _pair(x, y)
    if _is_constant(x) or _is_constant(y):
        return None
    return pearson(rankdata(x), rankdata(y))


def kendall_tau_b(x: Any, y: Any, *, chunk: int = 1024) -> float | None:
    """Kendall's tau-b (tie-corrected), O(n^2) over pairs in row chunks; None when undefined."""
    x, y = _pair(x, y)
    n = x.numel()
    if _is_constant(x) or _is_constant(y):
        return None
    concordance = ties_x = ties_y = 0
    for start in range(0, n, chunk):                           # ordered pairs (i, j), i != j
        sx = torch.sign(x[start:start + chunk, None] - x[None, :])   # [c, n]
        sy = torch.sign(y[start:start + chunk, None] - y[None, :])
        concordance += int((sx * sy).sum())
        ties_x += int((sx == 0).sum())
        ties_y += int((sy == 0).sum())
    # Every unordered pair was counted twice; the diagonal adds n ties to each count.
    pairs = n * (n - 1) // 2
    tied_x, tied_y = (ties_x - n) // 2, (ties_y - n) // 2
    denominator = math.sqrt((pairs - tied_x) * (pairs - tied_y))
    if denominator == 0:
        return None
    return max(-1.0, min(1.0, (concordance / 2) / denominator))


def order_by_score(scores: Any) -> list[int]:
    """Indices sorted by score, highest first, ties by index (the ranking rule)."""
    v = _vector(scores, "scores").tolist()
    return sorted(range(len(v)), key=lambda i: (-v[i], i))


def top_k_overlap(scores_a: Any, scores_b: Any, k: int) -> float:
    """|top-k of a ∩ top-k of b| / k, both ordered by `order_by_score`."""
    a, b = _pair(scores_a, scores_b, ("scores_a", "scores_b"))
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= a.numel():
        raise InputError("k", f"must be an integer in [1, {a.numel()}], got {k!r}")
    top_a, top_b = set(order_by_score(a)[:k]), set(order_by_score(b)[:k])
    return len(top_a & top_b) / k


# ----------------------------------------------------------------------------------------
# Sparsification

def sparsification_curves(uncertainty: Any, error: Any, metric: str = "rmse",
                          steps: int = AUSE_STEPS) -> tuple[Tensor, Tensor, Tensor] | None:
    """Sparsification curve and its oracle, normalised by the error of all elements.

    Elements are removed most uncertain first (ties in input order); the oracle removes
    the largest |error| first. At removed fraction f = k / steps, k = 0..steps-1, the
    curve is `metric` (rmse, mse or mae) of the remaining elements divided by its value
    at f = 0. Returns (fractions, curve, oracle) [steps] float64, or None when the
    uncertainty is constant (no ordering) or the total error is 0 (no normalisation).
    """
    if metric not in AUSE_METRICS:
        raise InputError("metric", f"must be one of {AUSE_METRICS}, got {metric!r}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise InputError("steps", f"must be a positive integer, got {steps!r}")
    u, e = _pair(uncertainty, error, ("uncertainty", "error"))
    e = e.abs()
    n = e.numel()
    if _is_constant(u) or not bool((e > 0).any()):
        return None
    per_element = e if metric == "mae" else e.square()
    fractions = torch.arange(steps, dtype=torch.float64) / steps
    removed = torch.div(torch.arange(steps) * n, steps, rounding_mode="floor")   # floor(f * n), exact
    remaining = (n - removed).to(torch.float64)

    def curve(order: Tensor) -> Tensor:
        values = per_element[order]
        suffix = torch.flip(torch.cumsum(torch.flip(values, [0]), 0), [0])        # suffix[m] = sum(values[m:])
        mean = suffix[removed] / remaining
        value = mean.sqrt() if metric == "rmse" else mean
        return value / value[0]

    by_uncertainty = torch.sort(u, descending=True, stable=True).indices
    by_error = torch.sort(e, descending=True, stable=True).indices
    return fractions, curve(by_uncertainty), curve(by_error)


def ause(uncertainty: Any, error: Any, metric: str = "rmse", steps: int = AUSE_STEPS) -> float | None:
    """Area between the sparsification curve and its oracle (trapezoid rule); None when undefined."""
    curves = sparsification_curves(uncertainty, error, metric, steps)
    if curves is None:
        return None
    fractions, curve, oracle = curves
    return float(torch.trapezoid(curve - oracle, fractions))


def image_uq_metrics(zeta: Tensor, render: Tensor, truth: Tensor, steps: int = AUSE_STEPS) -> dict[str, Any]:
    """Per-image agreement between zeta and the absolute error |render - truth|.

    zeta, render, truth: [H, W, 3]. Returns spearman, pearson, ause_rmse, ause_mse,
    ause_mae (None where undefined) and the image's rmse.
    """
    if not (zeta.shape == render.shape == truth.shape):
        raise InputError("images", f"zeta {list(zeta.shape)}, render {list(render.shape)} and truth "
                         f"{list(truth.shape)} must have one shape")
    error = (render.to(torch.float64) - truth.to(torch.float64)).abs()
    result: dict[str, Any] = {"spearman": spearman(zeta, error), "pearson": pearson(zeta, error)}
    for metric in AUSE_METRICS:
        result[f"ause_{metric}"] = ause(zeta, error, metric, steps)
    result["rmse"] = float(error.square().mean().sqrt())
    return result


# ----------------------------------------------------------------------------------------
# Trends and ensembles

def trend_correlations(num_views: Sequence[float], sigma_max_bars: Sequence[float],
                       r_drops: Sequence[float]) -> dict[str, float | None]:
    """Active-learning trends (Spearman over models trained on different view counts):
    rho_U = rho_s(sigma-max-bar, N_train), expected negative; rho_R = rho_s(r_drop, N_train),
    expected positive."""
    return {"rho_u": spearman(sigma_max_bars, num_views), "rho_r": spearman(r_drops, num_views)}


def ensemble_efficiency(ssim_selected: Sequence[float], ssim_a: Sequence[float],
                        ssim_b: Sequence[float]) -> float | None:
    """E_ME: mean over views of SSIM(selected) / max(SSIM(a), SSIM(b)).

    Views whose better SSIM is not positive have no defined ratio and are skipped;
    None when no view is left.
    """
    selected, a = _pair(ssim_selected, ssim_a, ("ssim_selected", "ssim_a"))
    _, b = _pair(ssim_selected, ssim_b, ("ssim_selected", "ssim_b"))
    best = torch.maximum(a, b)
    defined = best > 0
    if not bool(defined.any()):
        return None
    return float((selected[defined] / best[defined]).mean())


def mean_defined(values: Sequence[float | None]) -> float | None:
    """Mean of the values that are not None; None when all are."""
    defined = [v for v in values if v is not None]
    return sum(defined) / len(defined) if defined else None
