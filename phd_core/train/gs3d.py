"""Fit a 3D Gaussian Splatting model: the splat loop (`phd_core.train.splats`) with the 3DGS
recipe (the 3DGS model, renderer and rasteriser, identity initial rotations, no regulariser).

`TrainConfig` and `training_background` are the loop's, importable from here for the 3DGS callers
(the demo, the benchmarks)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence, cast

from ..data import Dataset
from ..renderers.gs3d import GaussianModel, GaussianRenderer, rasterize
from . import splats
from .splats import Recipe, TrainConfig, training_background

GAUSSIANS = Recipe("3dgs", GaussianModel, GaussianRenderer, rasterize)


def fit(dataset: Dataset, config: TrainConfig, *, progress: bool = True, init: GaussianModel | None = None,
        on_step: splats.StepCallback | None = None) -> tuple[GaussianModel, list[float]]:
    """The splat loop on `dataset` with the 3DGS recipe (`init`: a warm start, `on_step`: each
    step done, as `splats.fit`); returns the model and the loss every 100 steps."""
    return splats.fit(dataset, config, GAUSSIANS, progress=progress, init=init, on_step=on_step)


def train_gaussians(data: str | Path, *, views: int | Sequence[int] = 16, downscale: float = 2,
                    iterations: int | None = None, seed: int = 0, out: str | Path, progress: bool = True,
                    **overrides: Any) -> GaussianRenderer:
    """Train 3DGS on a split of a capture (`split`, default train); writes `out` (PLY) plus the
    sidecar `<stem>.json` (`phd_core.train.splats.train_splats`). `overrides` are its keywords
    (`split`, `init`, `on_step`) and TrainConfig fields."""
    renderer = splats.train_splats(data, GAUSSIANS, views=views, downscale=downscale, iterations=iterations,
                                   seed=seed, out=out, progress=progress, **overrides)
    return cast(GaussianRenderer, renderer)             # what the GAUSSIANS recipe builds


__all__ = ["GAUSSIANS", "TrainConfig", "fit", "train_gaussians", "training_background"]
