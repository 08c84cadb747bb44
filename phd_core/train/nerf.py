"""Train a NeRF (`phd_core.renderers.nerf`) on Blender or nerfstudio data on the CPU.

Adam on random batches of training rays with an exponentially decaying learning rate.
The loss is the colour MSE, plus (when the images have alpha) the MSE of the accumulated
opacity, which keeps the white background from being painted as white matter.

Model only what the scene requires:
- near/far come from the dataset; the scene box is the region every training camera sees
  between near and far (the frustum intersection), unless `bounds` is given.
- The occupancy grid starts as the visual hull of the alpha masks (a cell is carved when
  it projects onto pure background in some view), so training never evaluates the empty
  box. Every `grid_every` iterations it is re-estimated from the model's own density, and
  an emptiness penalty on random points of empty cells keeps the model empty where the
  grid skips it, so that renders with and without the grid agree. At the end the grid is
  rebuilt from the model's density alone.

FreeNeRF (Yang et al., CVPR 2023), each part switchable: the frequency mask reveals the
encoding's bands linearly until `frequency_end` (90%) of training, and the occlusion
penalty weighs the density of the first `occlusion_range` samples of every ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data import Dataset, load_dataset
from ..errors import InputError, check_bool, check_color, check_float, check_int
from ..renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, band_weights, camera_rays, render_rays, save_nerf
from ..renderers.nerf.family import NeRFOptions
from ..renderers.provenance import record_training
from ..scene import Camera, frustum_bounds, visual_hull
from .clock import TrainClock
from .config import StepCallback

# 100x100 images, 16 views, 2 shared CPU cores: about 0.1 s per iteration, 4 minutes (docs/nerf.md).
DEFAULT_ITERATIONS = 2000


@dataclass
class TrainSettings:
    """Optimisation settings (not stored in the checkpoint)."""

    batch_rays: int = 1024
    lr: float = 1e-2                # MLP learning rate (high: the schedule is short), decayed exponentially ...
    lr_final: float = 1e-3          # ... to this at the last iteration
    hash_lr: float = 1e-2           # hash tables learn faster (InstantNGP)
    alpha_weight: float = 0.1       # accumulated opacity vs the image alpha
    empty_weight: float = 0.01      # mean density at random points of empty cells
    empty_points: int = 2048
    occlusion_weight: float = 0.01  # FreeNeRF occlusion penalty
    occlusion_range: int = 10       # ... on the first samples of each ray
    frequency_end: float = 0.9      # FreeNeRF mask fully open at this share of training
    grid_every: int = 16
    grid_decay: float = 0.95
    hull: bool = True               # start the grid as the visual hull of the alpha masks

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> "TrainSettings":
        """Raise `InputError` naming the first field out of range; return self."""
        for name, lo in (("batch_rays", 1), ("empty_points", 1), ("grid_every", 1), ("occlusion_range", 0)):
            check_int(getattr(self, name), name, lo)
        for name in ("lr", "lr_final", "hash_lr"):
            check_float(getattr(self, name), name, 0.0, open_min=True)
        for name in ("alpha_weight", "empty_weight", "occlusion_weight"):
            check_float(getattr(self, name), name, 0.0)
        for name in ("frequency_end", "grid_decay"):
            check_float(getattr(self, name), name, 0.0, 1.0, open_min=True)
        check_bool(self.hull, "hull")
        return self


def train_nerf(data: str | Path | Dataset, *, views: int | Sequence[int] = 16, downscale: float = 2,
               encoding: str = NeRFOptions.encoding, freenerf: bool = NeRFOptions.freenerf,
               iterations: int | None = None, seed: int = 0, out: str | Path | None, progress: bool = True,
               split: str = "train", init: str | Path | None = None,
               on_step: StepCallback | None = None, **overrides: Any) -> NeRFRenderer:
    """Train a NeRF on a split of `data` (`views` within it) and write it to `out` (None: don't write),
    with what identifies the capture and the fit reached on it when `data` is a path
    (`phd_core.renderers.provenance`; a Dataset in memory names no capture).

    `views`: a count of evenly spaced training frames or a list of frame indices, loaded at
    1/`downscale` resolution (both ignored when `data` is an already loaded Dataset).
    `freenerf` switches on both FreeNeRF parts; the overrides `freenerf_frequency` /
    `freenerf_occlusion` switch them one by one. Other overrides are `NeRFConfig` fields
    (depth, width, samples, bounds, ...) or `TrainSettings` fields (batch_rays, lr, ...).
    iterations=None: DEFAULT_ITERATIONS. `on_step(TrainStep)` after every step (raising from it
    stops the run). A warm start (`init`) is for the splat families: refused here, since a NeRF's
    occupancy grid and bounds are fitted to the views it started with.
    """
    if init is not None:
        raise InputError("init", "a NeRF trains from scratch: warm starts continue splat models (3dgs, 2dgs)")
    NeRFOptions(encoding, freenerf)
    iterations = check_int(DEFAULT_ITERATIONS if iterations is None else iterations, "iterations", 1)
    seed = check_int(seed, "seed")
    config_keys = {f.name for f in fields(NeRFConfig)}
    settings_keys = {f.name for f in fields(TrainSettings)}
    for key in overrides:
        if key not in config_keys | settings_keys or key == "encoding":
            raise InputError(key, "unknown training option")
    settings = TrainSettings(**{k: v for k, v in overrides.items() if k in settings_keys})
    background = list(check_color(overrides.get("background", "white"), "background"))
    if isinstance(data, Dataset):
        dataset = data
        if "background" in overrides and background != list(dataset.background):
            raise InputError("background", f"the dataset's images are composited on {list(dataset.background)}")
    else:
        dataset = load_dataset(data, split, downscale=downscale, views=views, background=background)
    if dataset.images is None:
        raise InputError("data", "training needs the images (the dataset was loaded without them)")

    # The background is the one the training images are composited on.
    config_values = {"encoding": encoding, "freenerf_frequency": freenerf, "freenerf_occlusion": freenerf,
                     **{k: v for k, v in overrides.items() if k in config_keys}, "background": list(dataset.background)}
    if "near" not in overrides or "far" not in overrides:
        near, far = scene_near_far(dataset)
        config_values.setdefault("near", near)
        config_values.setdefault("far", far)
    if "bounds" not in overrides:
        config_values["bounds"] = frustum_bounds(dataset.cameras, config_values["near"], config_values["far"])
    config = NeRFConfig(**config_values)
    model = RadianceField(config, seed=seed)
    if settings.hull and dataset.alphas is not None:
        hull = grid_hull(model, dataset.cameras, dataset.alphas)
        model.grid.set_density(torch.full((config.grid_resolution ** 3,), math.inf), allowed=hull)
    else:
        hull = None

    fit(model, dataset, settings, iterations=iterations, seed=seed, hull=hull, progress=progress, on_step=on_step)
    model.grid.set_density(model.cell_density())
    renderer = NeRFRenderer(model, list(dataset.cameras))
    if not isinstance(data, Dataset):
        renderer.trained_on = record_training(renderer, data)
    if out is not None:
        save_nerf(renderer, out)
    return renderer


def fit(model: RadianceField, dataset: Dataset, settings: TrainSettings, *, iterations: int, seed: int,
        hull: torch.Tensor | None, progress: bool,
        on_step: StepCallback | None = None) -> list[float]:
    """The optimisation loop; returns the loss of every iteration."""
    config = model.config
    generator = torch.Generator().manual_seed(seed)
    rays = [camera_rays(camera) for camera in dataset.cameras]
    origins = torch.cat([r[0] for r in rays])                               # [P, 3]
    dirs = torch.cat([r[1] for r in rays])                                  # [P, 3]
    assert dataset.images is not None, "fit needs a dataset loaded with its images"
    colors = torch.cat([image.reshape(-1, 3) for image in dataset.images])                     # [P, 3]
    alphas = torch.cat([alpha.reshape(-1) for alpha in dataset.alphas]) if dataset.alphas is not None else None
    table = [p for n, p in model.named_parameters() if n.startswith("encoding.")]
    mlp = [p for n, p in model.named_parameters() if not n.startswith("encoding.")]
    groups = [{"params": mlp, "lr": settings.lr, "base": settings.lr}]
    if table:
        groups.append({"params": table, "lr": settings.hash_lr, "base": settings.hash_lr, "eps": 1e-15})
    optimizer = torch.optim.Adam(groups)
    decay = settings.lr_final / settings.lr
    box_lo, box_size = model.grid.lo, model.grid.size
    losses = []
    model.train()
    bar = tqdm(range(iterations), desc=f"nerf {config.encoding}", disable=not progress, unit="it")
    clock = TrainClock(iterations)
    for step in bar:
        progress_share = step / iterations
        for group in optimizer.param_groups:
            group["lr"] = group["base"] * decay ** progress_share
        weights = dir_weights = None
        if config.freenerf_frequency:       # the lowest band from the start, all bands at frequency_end
            opened = min(1.0, progress_share / settings.frequency_end)
            weights = band_weights(model.encoding.bands, 1.0 + opened * model.encoding.bands)
            dir_weights = band_weights(config.dir_freqs, 1.0 + opened * config.dir_freqs)

        batch = torch.randint(origins.shape[0], (settings.batch_rays,), generator=generator)
        out = render_rays(model, origins[batch], dirs[batch], generator=generator, weights=weights,
                          dir_weights=dir_weights, with_sigma=config.freenerf_occlusion)
        loss = F.mse_loss(out.rgb[0], colors[batch])
        if alphas is not None and settings.alpha_weight > 0:
            loss = loss + settings.alpha_weight * F.mse_loss(out.alpha[0], alphas[batch])
        if config.freenerf_occlusion and settings.occlusion_range > 0:
            assert out.sigma is not None                    # rendered with_sigma=config.freenerf_occlusion
            occlusion = out.sigma[0, :, :settings.occlusion_range].sum(-1).mean() / config.samples
            loss = loss + settings.occlusion_weight * occlusion
        if settings.empty_weight > 0:
            probe = box_lo + torch.rand(settings.empty_points, 3, generator=generator) * box_size
            probe = probe[~model.grid.lookup(probe)]
            if probe.shape[0]:
                loss = loss + settings.empty_weight * model.density(probe, weights).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())

        if (step + 1) % settings.grid_every == 0 and step + 1 < iterations:
            update_grid(model, generator, settings.grid_decay, hull)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{losses[-1]:.4f}", occupied=f"{model.grid.fraction:.3f}", samples=out.samples)
        if on_step is not None:
            on_step(clock.tick(step + 1))            # the model's size is fixed: the recent pace holds
    model.eval()
    return losses


@torch.no_grad()
def update_grid(model: RadianceField, generator: torch.Generator, decay: float, allowed: torch.Tensor | None) -> None:
    """Probe one random point per cell; keep a decaying running max (InstantNGP's rule)."""
    old = model.grid.density.flatten()
    new = model.cell_density(generator=generator)
    model.grid.set_density(torch.where(torch.isfinite(old), torch.maximum(old * decay, new), new), allowed)


def scene_near_far(dataset: Dataset) -> tuple[float, float]:
    """near/far from the dataset; without them, 1% and 200% of the largest camera spread."""
    if dataset.near is not None and dataset.far is not None:
        return dataset.near, dataset.far
    centers = torch.stack([c.center for c in dataset.cameras])
    spread = float(torch.cdist(centers, centers).max()) if len(centers) > 1 else 1.0
    spread = spread if spread > 0 else 1.0
    near = dataset.near if dataset.near is not None else 0.01 * spread
    far = dataset.far if dataset.far is not None else max(2.0 * spread, near * 2)
    return near, far


def grid_hull(model: RadianceField, cameras: list[Camera], alphas: list[torch.Tensor]) -> torch.Tensor:
    """[res^3] bool: the occupancy-grid cells no view's alpha mask carves (any alpha > 0 is
    foreground): `phd_core.scene.visual_hull` of the cells, each a ball around its centre."""
    grid = model.grid
    centers = grid.cell_points(torch.full((1, 3), 0.5)).double()            # [C, 3]
    half_diagonal = float((grid.size.double() / grid.resolution).norm() / 2)
    return visual_hull(centers, cameras, alphas, radius=half_diagonal)
