"""The splat training loop: fit a splat model (3DGS, 2DGS) to a capture (any `phd_core.data`
format) on the CPU.

The recipe is the reference 3DGS one (Kerbl et al. 2023) scaled to short CPU runs:
L1 + 0.2 D-SSIM, Adam with per-parameter learning rates and an exponentially decaying
position rate, adaptive density control (clone small / split large splats whose
screen-space gradient is high, prune transparent ones) and an opacity reset. The
schedule is expressed in fractions of the run, so it holds for any iteration count.

What the scene needs is derived from the data, not configured:
- bounds: from the cameras (the point their optical axes pass closest to, and the
  extent every camera sees);
- initial splats: carved from the training alpha masks where the data has them (a point
  is kept when every training view that sees it sees foreground there), coloured by the
  pixels it projects to; else the SfM points where the format has them (COLMAP), each
  splat as wide as the mean distance to its 3 nearest neighbours, as the reference trainer
  starts, in the point's colour (the mean pixel it projects to when the model has none: a
  model published without colours holds them all black); uniform in the bounds otherwise;
- real captures (no alpha masks): the background is real and unbounded. The SfM points
  reach into it; the renderer's background colour is the training images' mean colour;
  the extent that scales the position rate and the split size is the cameras' spread, as
  the reference uses. Optionally (`background_splats`) a shell of splats far outside the
  cameras, coloured by the pixels behind it: on cup_colmap it cost 1.9 dB at 4 views and
  0.9 dB at 8, and gained 0.5-0.9 dB at 12 and 16 (docs/formats.md), so it is off by default;
- splat budget: a multiple of the pixels in one training view.

The loop is shared by the splat families: a `Recipe` names what differs (the model and
renderer classes, the rasteriser, an optional regulariser, initial rotations), and each
family's trainer is its recipe (`phd_core.train.gs3d`, `phd_core.train.gs2d`).
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence, cast

import torch
from tqdm import tqdm

from ..data import Dataset, load_dataset, locate
from ..errors import InputError
from ..eval import ssim
from ..io import write_json_atomic
from ..renderers.provenance import record_training
from ..renderers.splats import SIDECAR_FORMAT, GaussianModel, sidecar_path, write_ply
from ..renderers.splats.renderer import SplatRenderer
from ..scene import scene_bounds
from ..scene.rotations import quaternion_to_rotation
from .clock import TrainClock
from .config import Recipe, StepCallback, TrainConfig
from .seeding import seed_model, warm_start, with_new_points, with_sh_degree


def training_background(data: Dataset, given: Sequence[float] | None = None) -> tuple[float, float, float]:
    """The colour behind the splats: the one given, else the dataset's where alpha masks define
    it, else the training images' mean colour (a real capture has no empty background)."""
    # tuple() cannot tell mypy its length: three (a checked colour, an image's RGB mean)
    if given is not None:
        return cast(tuple[float, float, float], tuple(float(v) for v in given))
    if data.alphas is not None or data.images is None:
        return data.background
    total = torch.stack([image.double().sum(dim=(0, 1)) for image in data.images]).sum(0)     # [3], views of any size
    pixels = sum(image.shape[0] * image.shape[1] for image in data.images)
    return cast(tuple[float, float, float], tuple(float(v) / pixels for v in total))


def training_extent(data: Dataset, extent: float) -> float:
    """The scale of position steps and splits: the bounds' extent for object captures, the
    cameras' spread (1.1 x the largest distance from their mean, as the reference) for real ones."""
    if data.alphas is not None:
        return extent
    eyes = torch.stack([c.center for c in data.cameras])
    return max(extent, 1.1 * float((eyes - eyes.mean(0)).norm(dim=1).max()))


# ----------------------------------------------------------------------------- optimiser

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class Splats:
    """Trainable splat parameters with their Adam state, resized by densification."""

    def __init__(self, model: GaussianModel, config: TrainConfig, extent: float):
        tensors = {"means": model.means, "log_scales": model.log_scales, "quats": model.quats,
                   "opacity_logits": model.opacity_logits, "sh_dc": model.sh[:, :1], "sh_rest": model.sh[:, 1:]}
        self.params = {k: torch.nn.Parameter(v.detach().clone().contiguous()) for k, v in tensors.items()}
        self.model_type = type(model)
        self.lr_means = config.lr_means * extent
        lrs = {"means": self.lr_means, "log_scales": config.lr_scales, "quats": config.lr_quats,
               "opacity_logits": config.lr_opacity, "sh_dc": config.lr_sh_dc, "sh_rest": config.lr_sh_rest}
        self.optimizer = torch.optim.Adam([{"params": [self.params[k]], "lr": lrs[k], "name": k} for k in PARAMS],
                                          eps=1e-15)

    def model(self, active_degree: int | None = None) -> GaussianModel:
        sh = torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)
        if active_degree is not None:   # unused higher bands contribute nothing yet
            sh = sh[:, : (active_degree + 1) ** 2]
        return self.model_type(self.params["means"], self.params["log_scales"], self.params["quats"],
                               self.params["opacity_logits"], sh)

    def set_means_lr(self, fraction: float) -> None:
        """Log-linear decay of the position rate to 1% of its start over the run."""
        lr = self.lr_means * (0.01 ** fraction)
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lr

    def replace(self, select: torch.Tensor, extra: dict[str, torch.Tensor] | None = None) -> None:
        """Keep rows `select` (bool [G]) and append `extra` rows; Adam state follows, new rows start at 0."""
        for group in self.optimizer.param_groups:
            name = group["name"]
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            kept = old.detach()[select]
            added = extra[name] if extra else kept[:0]
            new = torch.nn.Parameter(torch.cat([kept, added]).contiguous())
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    state[key] = torch.cat([state[key][select], torch.zeros_like(added)])
                self.optimizer.state[new] = state
            group["params"][0] = new
            self.params[name] = new

    @property
    def count(self) -> int:
        return self.params["means"].shape[0]


def densify(splats: Splats, grad_norm: torch.Tensor, config: TrainConfig, extent: float, budget: int,
            gen: torch.Generator) -> None:
    """Clone small and split large high-gradient splats; prune transparent ones."""
    p = {k: v.detach() for k, v in splats.params.items()}
    scales = p["log_scales"].exp().max(dim=-1).values
    grow = grad_norm >= config.grad_threshold
    room = max(0, budget - splats.count)
    if grow.sum() > room:   # over budget: grow only the highest gradients
        top = torch.topk(torch.where(grow, grad_norm, torch.zeros_like(grad_norm)), room).indices
        grow = torch.zeros_like(grow)
        grow[top] = True
    clone = grow & (scales <= config.dense_fraction * extent)
    split = grow & ~clone
    extra = {k: v[clone] for k, v in p.items()}
    # Split: two children sampled from the parent's Gaussian, 1/1.6 of its size.
    idx = split.nonzero().squeeze(1).repeat(2)
    if len(idx):
        std = p["log_scales"][idx].exp()                               # [S, axes]
        rot = quaternion_to_rotation(p["quats"][idx])[:, :, :std.shape[1]]   # the scaled axes
        offset = (rot @ (torch.randn(len(idx), std.shape[1], generator=gen) * std)[..., None]).squeeze(-1)
        children = {k: v[idx] for k, v in p.items()}
        children["means"] = children["means"] + offset
        children["log_scales"] = children["log_scales"] - math.log(1.6)
        extra = {k: torch.cat([extra[k], children[k]]) for k in p}
    opacity = torch.sigmoid(p["opacity_logits"])
    keep = ~split & (opacity >= config.min_opacity)
    splats.replace(keep, extra)


# ----------------------------------------------------------------------------- training

# While densification adds splats every step grows slower, so the time left that tqdm extrapolates
# from the rate so far runs short (issue 48: 3:19, then 7:53, in one run); until the splat count
# stops growing the bar shows the rate and the splats, and the time left only from then on.
GROWING_BAR = ("{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}; time left once the splats "
               "stop growing]")


def train_splats(data: str | Path, recipe: Recipe, *, views: int | Sequence[int] = 16, downscale: float = 2,
                 iterations: int | None = None, seed: int = 0, out: str | Path, progress: bool = True,
                 split: str = "train", init: str | Path | None = None, on_step: StepCallback | None = None,
                 **overrides: Any) -> SplatRenderer:
    """Train `recipe`'s family on a split of a capture (Blender, nerfstudio, COLMAP, LLFF; `views`
    within it) and write `out` (PLY) plus the sidecar `<stem>.json` with the training cameras, the
    views, the settings and what identifies the capture with the fit reached on it
    (`phd_core.renderers.provenance`). `init`: a model of the same family to continue from (a
    warm start, `fit`), trained over the same background; the sidecar records it."""
    extra: dict[str, Any] = {} if iterations is None else {"iterations": iterations}
    config = TrainConfig(seed=seed, **overrides, **extra)
    source = locate(data, split)[0].name              # the capture's format: its pose convention
    dataset = load_dataset(data, split, downscale=downscale, views=views,
                           background=config.background or (1.0, 1.0, 1.0))
    background = training_background(dataset, config.background_rgb)
    start = None if init is None else warm_start(init, recipe, background)
    started = time.perf_counter()
    model, history = fit(dataset, config, recipe, progress=progress, init=start, on_step=on_step)
    seconds = time.perf_counter() - started
    renderer = recipe.renderer_type(model, background, dataset.cameras, tile=config.tile, camera_format=source)
    renderer.trained_on = record_training(renderer, data)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(model, out)
    sidecar = {
        "format": SIDECAR_FORMAT,
        "model": recipe.kind,
        "name": f"{out.resolve().parent.name}/{out.stem}",    # the run's folder and file: what an upload is named
        **renderer.trained_on.fields(),
        "split": split,
        "view_indices": dataset.indices,
        "downscale": downscale,
        "background": list(background),
        "training_cameras": [c.to_frame() for c in dataset.cameras],
        "settings": asdict(config),
        "num_splats": model.num_splats,
        "train_seconds": round(seconds, 2),
        "final_loss": history[-1] if history else None,
    }
    if init is not None:
        assert start is not None
        sidecar["init"] = {"file": Path(init).name, "sha256": hashlib.sha256(Path(init).read_bytes()).hexdigest(),
                           "num_splats": start.num_splats}
    write_json_atomic(sidecar_path(out), sidecar)
    return renderer


def opacity_reset_interval(config: TrainConfig, *, warm: bool) -> int:
    """Steps between opacity resets (0: none). A warm start skips them: the reset clears the
    floaters of a model's first steps, and on a trained model it throws the fit away. Measured
    (8 -> 12 views, docs/gaussians.md "Warm start"): with the resets a warm start lost 2.4 dB of
    test PSNR on cup_colmap and 1.3 dB on donut_200 after 100 steps, 0.3 and 0.2 dB after 200."""
    if warm or config.opacity_reset_every <= 0:
        return 0
    return int(config.opacity_reset_every * config.iterations)


def fit(dataset: Dataset, config: TrainConfig, recipe: Recipe, *, progress: bool = True,
        init: GaussianModel | None = None,
        on_step: StepCallback | None = None) -> tuple[GaussianModel, list[float]]:
    """The optimisation loop; returns the trained model and the loss every 100 steps.

    `init` (a warm start): the splats to start from instead of the seeded ones, e.g. the last
    round's model of an active capture after new photos came, plus a seeded splat at each SfM
    point none of its splats comes near (`with_new_points`: what only the new photos see).
    Densification runs on the run's schedule (the new views show new high-gradient regions)
    within the splat budget; the SH bands the init has are active from the start; the opacity reset is skipped
    (`opacity_reset_interval`); the position rate keeps its schedule: a tenth of it (a shorter
    warm-up for splats already in place) lost 0.05-0.15 dB of test PSNR in each of the four
    measured cases (bench/bench_warm_start.py, docs/gaussians.md "Warm start"). `on_step(TrainStep)` is
    called after every step (progress and time left, `phd_core.train.clock`; raising from it stops the run).

    Seeded: bit-identical for a seed on one torch thread; with several threads, parallel
    sums may round differently in the last bits.
    """
    if dataset.images is None:
        raise InputError("data", "training needs the images")
    gen = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    centre, extent = scene_bounds(dataset.cameras)
    model = seed_model(dataset, centre, extent, config, gen, recipe) if init is None else \
        with_new_points(with_sh_degree(init, config.sh_degree, recipe), dataset, extent, gen, recipe)
    start_degree = 0 if init is None else min(init.sh_degree, config.sh_degree)
    extent = training_extent(dataset, extent)
    splats = Splats(model, config, extent)
    background = torch.tensor(training_background(dataset, config.background_rgb))
    largest = max(c.width * c.height for c in dataset.cameras)           # views may differ in size
    budget = int(config.splats_per_pixel * largest)
    n_iter = config.iterations
    densify_from, densify_until = int(config.densify_from * n_iter), int(config.densify_until * n_iter)
    reset_every = opacity_reset_interval(config, warm=init is not None)
    sh_up = max(1, int(config.sh_up_every * n_iter))
    grad_sum = torch.zeros(splats.count)
    grad_count = torch.zeros(splats.count)
    history: list[float] = []
    order = torch.randperm(len(dataset.cameras), generator=gen)
    bar = tqdm(range(n_iter), disable=not progress, desc=recipe.kind, unit="it", bar_format=GROWING_BAR)
    clock = TrainClock(n_iter, budget=budget, grows_at=[s for s in range(max(1, densify_from), densify_until)
                                                        if s % config.densify_every == 0])
    for step in bar:
        if step == densify_until:
            bar.bar_format = None           # the splat count holds from here: tqdm's time left is fair
        if step % len(order) == 0 and step:
            order = torch.randperm(len(dataset.cameras), generator=gen)
        view = int(order[step % len(order)])
        cam, target = dataset.cameras[view], dataset.images[view]
        splats.set_means_lr(step / n_iter)
        degree = min(config.sh_degree, max(start_degree, step // sh_up))
        out = recipe.render(splats.model(degree), cam, background, tile=config.tile, compositor=config.compositor)
        out.means2d.retain_grad()
        image = out.rgb[0]
        l1 = (image - target).abs().mean()
        loss = (1 - config.ssim_weight) * l1 + config.ssim_weight * (1 - ssim(image, target))
        if recipe.regulariser is not None:
            loss = loss + recipe.regulariser(out, cam, step / n_iter, extent)
        splats.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if step < densify_until:
            # Screen-space gradient in NDC units (pixels * W / 2), as the reference thresholds it.
            assert out.means2d.grad is not None  # retain_grad() before backward() kept it
            g = out.means2d.grad.float() * torch.tensor([cam.width / 2, cam.height / 2])
            grad_sum += torch.where(out.visible, g.norm(dim=-1), 0.0)
            grad_count += out.visible.float()
        splats.optimizer.step()
        if densify_from <= step < densify_until and step % config.densify_every == 0 and step > 0:
            densify(splats, grad_sum / grad_count.clamp_min(1), config, extent, budget, gen)
            grad_sum = torch.zeros(splats.count)
            grad_count = torch.zeros(splats.count)
        if reset_every and step % reset_every == 0 and 0 < step < densify_until:
            with torch.no_grad():
                splats.params["opacity_logits"].clamp_(max=math.log(0.01 / 0.99))
            opacity_state = splats.optimizer.state.get(splats.params["opacity_logits"])
            if opacity_state:
                opacity_state["exp_avg"].zero_()
                opacity_state["exp_avg_sq"].zero_()
        if step % 100 == 0 or step == n_iter - 1:
            history.append(round(loss.item(), 5))
            bar.set_postfix(loss=f"{loss.item():.4f}", splats=splats.count)
        if on_step is not None:
            on_step(clock.tick(step + 1, size=splats.count))
    final = splats.model()
    keep = torch.sigmoid(final.opacity_logits.detach()) >= config.min_opacity
    detached = recipe.model_type(*(t.detach().clone() for t in (final.means, final.log_scales, final.quats,
                                                                 final.opacity_logits, final.sh)))
    return detached.subset(keep), history
