"""PH-Dropout: post hoc epistemic uncertainty from a trained model (ICLR 2025, Algorithm 1).

A keep-mask drops whole dropout units of a trained model (splats for Gaussian Splatting,
first-layer hidden units for NeRF) without rescaling the survivors. The engine only talks
to the renderer protocol (`phd_core.renderers.Renderer`): `render(camera, keep)` returns
one image per mask, so N sub-models of one view cost one batched pass.

    sampling     argument checks, nested keep-masks, batched masked renders, the std
    calibrate    Algorithm 1: r_drop on the training poses
    uncertainty  zeta, sigma_max, sigma_mean, sigma-max-bar
    strategies/  next-best-view strategies (a registry)
    candidates/  candidate-pose generators (a registry; hemisphere today)
    rank         candidates in the order a strategy would capture them
    select       per view, which of two models to trust

Everything public is importable from here: `from phd_core import uq`.
"""

from .calibrate import (
    DEFAULT_CALIBRATION_SAMPLES,
    DEFAULT_EPSILON,
    DEFAULT_SSIM_MARGIN,
    DEFAULT_STEP,
    LOOKAHEAD,
    CalibrationError,
    CalibrationResult,
    calibrate,
    calibrate_ssim,
)
from .candidates import GENERATORS
from .rank import RankedView, Ranking, candidate_evidence, coarse_cameras, rank_views, targets_at_size
from .sampling import (
    MAX_MASKS_PER_RENDER,
    Progress,
    RunningStd,
    dropout_uniforms,
    keep_masks,
    limit_mask_batch,
    sample_std,
)
from .select import (
    DEFAULT_SELECTION_RULE,
    SELECTION_RULES,
    SELECTION_TRAINING_VIEWS,
    SelectionResult,
    SelectionRule,
    ViewSelection,
    rules_help,
    select_models,
)
from .strategies import DEFAULT_STRATEGY, STRATEGIES
from .uncertainty import DEFAULT_SAMPLES, ViewUncertainty, sigma_max_bar, uncertainty, view_uncertainty

__all__ = [
    "DEFAULT_CALIBRATION_SAMPLES", "DEFAULT_EPSILON", "DEFAULT_SAMPLES", "DEFAULT_SELECTION_RULE",
    "DEFAULT_SSIM_MARGIN", "DEFAULT_STEP", "DEFAULT_STRATEGY", "GENERATORS", "LOOKAHEAD", "MAX_MASKS_PER_RENDER",
    "SELECTION_RULES", "SELECTION_TRAINING_VIEWS", "STRATEGIES", "CalibrationError", "CalibrationResult",
    "Progress", "RankedView", "Ranking", "RunningStd", "SelectionResult", "SelectionRule", "ViewSelection",
    "ViewUncertainty",
    "calibrate", "calibrate_ssim", "candidate_evidence", "coarse_cameras", "dropout_uniforms", "keep_masks",
    "limit_mask_batch", "rank_views", "rules_help", "sample_std", "select_models", "sigma_max_bar", "targets_at_size",
    "uncertainty",
    "view_uncertainty",
]
