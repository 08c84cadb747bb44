"""Measuring results against ground truth: image quality (`image`: PSNR, SSIM, RMSE) and
the quality of an uncertainty estimate (`uq`: correlations, AUSE, trends, ensemble
efficiency). Trainers use SSIM as a loss; the engine's selection reports E_ME."""

from .image import psnr, rmse, ssim
from .uq import (
    ause,
    ensemble_efficiency,
    image_uq_metrics,
    kendall_tau_b,
    mean_defined,
    pearson,
    sparsification_curves,
    spearman,
    top_k_overlap,
    trend_correlations,
)

__all__ = ["ause", "ensemble_efficiency", "image_uq_metrics", "kendall_tau_b", "mean_defined", "pearson", "psnr",
           "rmse", "spearman", "sparsification_curves", "ssim", "top_k_overlap", "trend_correlations"]
