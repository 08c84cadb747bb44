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
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence, cast

import torch
from tqdm import tqdm

from ..data import Dataset, load_dataset, locate
from ..errors import InputError, check_color, check_float, check_int
from ..eval import ssim
from ..io import write_json_atomic
from ..renderers.composite import COMPOSITORS, DEFAULT_COMPOSITOR
from ..renderers.provenance import record_training
from ..renderers.splats import SH_C0, SIDECAR_FORMAT, GaussianModel, read_sidecar, sidecar_path, write_ply
from ..renderers.splats.renderer import RenderOutput, SplatRenderer
from ..scene import Camera, footprint, scene_bounds, visual_hull
from ..scene.rotations import quaternion_to_rotation

StepCallback = Callable[[int, int], None]     # (step just done, steps in the run)


@dataclass
class TrainConfig:
    """The splat loop's settings, checked when built (`validate`)."""

    iterations: int = 2000
    sh_degree: int = 3
    ssim_weight: float = 0.2
    lr_means: float = 1.6e-4          # times the scene extent, decays to 1% over the run
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    init_points: int = 6000
    background_splats: int = 0        # a far shell of this many splats for captures without alpha masks
    shell_radius: float = 3.0         # times the largest camera distance from the scene centre
    splats_per_pixel: float = 4.0     # budget: this many splats per pixel of one view (the largest)
    densify_from: float = 0.05        # fractions of the run
    densify_until: float = 0.6
    densify_every: int = 100
    grad_threshold: float = 2e-4      # mean screen-space gradient (NDC units, as the reference)
    dense_fraction: float = 0.01      # splats larger than this times the extent are split
    opacity_reset_every: float = 0.3  # fraction of the run; 0 disables
    min_opacity: float = 0.005
    sh_up_every: float = 0.1          # raise the active SH degree every this fraction of the run
    seed: int = 0
    tile: int = 4
    compositor: str = DEFAULT_COMPOSITOR   # stage 4 and its gradient: "fused" (compiled) or "reference" (torch)
    background: str | Sequence[float] | None = None   # behind the splats: a name or [r, g, b]; None: the data's
                                      # (alpha masks: white) or the training images' mean (a real capture)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> "TrainConfig":
        """Raise `InputError` naming the first field out of range; return self."""
        for name, lo, hi in (("iterations", 1, None), ("sh_degree", 0, 3), ("init_points", 1, None),
                             ("background_splats", 0, None), ("densify_every", 1, None), ("seed", None, None),
                             ("tile", 1, None)):
            check_int(getattr(self, name), name, lo, hi)
        for name, low, high in (("ssim_weight", 0.0, 1.0), ("lr_means", 0.0, None), ("lr_sh_dc", 0.0, None),
                             ("lr_sh_rest", 0.0, None), ("lr_opacity", 0.0, None), ("lr_scales", 0.0, None),
                             ("lr_quats", 0.0, None), ("shell_radius", 0.0, None), ("splats_per_pixel", 0.0, None),
                             ("densify_from", 0.0, 1.0), ("densify_until", 0.0, 1.0), ("grad_threshold", 0.0, None),
                             ("dense_fraction", 0.0, None), ("opacity_reset_every", 0.0, 1.0),
                             ("min_opacity", 0.0, 1.0), ("sh_up_every", 0.0, None)):
            check_float(getattr(self, name), name, low, high)
        COMPOSITORS.lookup(self.compositor, "compositor")
        if self.background is not None:
            self.background = list(check_color(self.background, "background"))
        return self

    @property
    def background_rgb(self) -> Sequence[float] | None:
        """`background` as `validate` leaves it: a checked [r, g, b] (a name resolved), or None."""
        return cast("Sequence[float] | None", self.background)


@dataclass(frozen=True)
class Recipe:
    """What differs between the splat families this loop trains."""

    kind: str                                     # the renderer's kind, and the progress label
    model_type: type[GaussianModel]               # GaussianModel, or a subclass with other scale_axes
    renderer_type: type[SplatRenderer]
    render: Callable[..., RenderOutput]           # (model, camera, background, tile=) -> output
    # (output, camera, fraction of the run done, scene extent) -> loss added to the photometric one
    regulariser: Callable[[RenderOutput, Camera, float, float], torch.Tensor] | None = None
    random_rotations: bool = False                # initial orientations: random, or all identity


# ----------------------------------------------------------------------------- scene

def carve_points(data: Dataset, centre: torch.Tensor, extent: float, count: int,
                 gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial points [P, 3] and colours [P, 3].

    With alpha masks: a grid over the bounds, keeping points that every view which sees
    them sees as foreground (alpha > 0.5): the visual hull (`phd_core.scene.visual_hull`).
    Colours are the mean of the pixels the points project to. Without masks: uniform in
    the bounds, grey.
    """
    if data.alphas is None:
        pts = centre + (torch.rand(count, 3, generator=gen, dtype=torch.float64) * 2 - 1) * extent
        return pts.float(), torch.full((count, 3), 0.5)
    res = 64
    axis = torch.linspace(-extent, extent, res, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + centre
    inside = visual_hull(grid, data.cameras, data.alphas, threshold=0.5)
    colour_sum, seen = pixels_behind(data, grid)
    hull = inside.nonzero().squeeze(1)
    if len(hull) == 0:
        raise InputError("data", "the training alpha masks leave no foreground: nothing to fit")
    pick = hull[torch.randint(len(hull), (count,), generator=gen)]
    voxel = 2 * extent / (res - 1)
    jitter = (torch.rand(count, 3, generator=gen, dtype=torch.float64) - 0.5) * voxel
    colours = colour_sum[pick] / seen[pick].clamp_min(1)[:, None]
    return (grid[pick] + jitter).float(), colours.float()


def pixels_behind(data: Dataset, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The summed colour [P, 3] of the training pixels points [P, 3] project to, and in how
    many views [P] they do (float64; no occlusion test)."""
    colour_sum = torch.zeros(len(points), 3, dtype=torch.float64)
    seen = torch.zeros(len(points), dtype=torch.float64)
    assert data.images is not None  # the trainers refuse a dataset loaded without them
    for cam, image in zip(data.cameras, data.images):
        pixel = footprint(cam, points)
        colour_sum += torch.where(pixel.inside[:, None], image[pixel.v0, pixel.u0].double(), 0.0)
        seen += pixel.inside.double()
    return colour_sum, seen


def initial_model(points: torch.Tensor, colours: torch.Tensor, sh_degree: int, extent: float,
                  gen: torch.Generator, recipe: Recipe, spacing: torch.Tensor | None = None) -> GaussianModel:
    """Small isotropic splats at `points` with 10% opacity and DC colour from `colours`; their
    size is half of `spacing` [P] (default the mean distance between points in the bounds)."""
    n, axes = len(points), recipe.model_type.scale_axes
    if spacing is None:      # the mean distance between n points spread over the bounds
        log_scales = torch.full((n, axes), math.log(extent * 2 / max(1.0, n ** (1 / 3)) * 0.5))
    else:
        log_scales = (spacing.double() * 0.5).clamp_min(1e-7).log().float()[:, None].expand(n, axes).contiguous()
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
    sh[:, 0] = (colours - 0.5) / SH_C0
    if recipe.random_rotations:
        quats = torch.randn(n, 4, generator=gen)
    else:
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
    return recipe.model_type(
        means=points.clone(),
        log_scales=log_scales,
        quats=quats,
        opacity_logits=torch.full((n,), math.log(0.1 / 0.9)),
        sh=sh,
    )


def neighbour_spacing(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    """[P] mean distance of each point to its k nearest other points (chunked: no P x P matrix)."""
    out = torch.empty(len(points), dtype=points.dtype)
    k = min(k, len(points) - 1)
    if k < 1:
        return torch.ones(len(points), dtype=points.dtype)
    for start in range(0, len(points), chunk):
        d = torch.cdist(points[start:start + chunk], points)                     # [c, P]
        out[start:start + chunk] = d.topk(k + 1, largest=False).values[:, 1:].mean(1)
    return out


def background_shell(data: Dataset, centre: torch.Tensor, radius: float, count: int
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points [B, 3], colours [B, 3] and spacing [B] on a sphere of `radius` around `centre`:
    the directions some training view sees, coloured by the mean pixel behind them."""
    total = 4 * count
    i = torch.arange(total, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / total
    azimuth = math.pi * (3 - math.sqrt(5)) * i
    ring = (1 - z * z).sqrt()
    sphere = centre + radius * torch.stack([ring * azimuth.cos(), ring * azimuth.sin(), z], dim=1)   # [4B, 3]
    colour_sum, seen = pixels_behind(data, sphere)
    visible = (seen > 0).nonzero().squeeze(1)[:count]
    spacing = torch.full((len(visible),), radius * math.sqrt(4 * math.pi / total) * 2, dtype=torch.float64)
    return sphere[visible], (colour_sum[visible] / seen[visible, None]), spacing


def seed_model(data: Dataset, centre: torch.Tensor, extent: float, config: TrainConfig,
               gen: torch.Generator, recipe: Recipe) -> GaussianModel:
    """The first splats: from the alpha masks' hull, else the SfM points, else uniform (module docstring)."""
    if data.alphas is not None or data.points is None or len(data.points) == 0:
        points, colours = carve_points(data, centre, extent, config.init_points, gen)
        spacing = None
    else:
        assert data.point_colors is not None  # the readers that give points give their colours
        points, colours = data.points.to(torch.float64), data.point_colors.to(torch.float64)
        if not colours.any():           # a model published without colours (all black): the pixels behind
            colour_sum, seen = pixels_behind(data, points)
            colours = torch.where(seen[:, None] > 0, colour_sum / seen.clamp_min(1)[:, None], 0.5)
        spacing = neighbour_spacing(points)
    if data.alphas is None and config.background_splats > 0:
        eyes = torch.stack([c.center for c in data.cameras])
        radius = config.shell_radius * float((eyes - centre).norm(dim=1).max())
        if spacing is None:
            spacing = torch.full((len(points),), extent * 2 / max(1.0, len(points) ** (1 / 3)), dtype=torch.float64)
        shell, shell_colours, shell_spacing = background_shell(data, centre, radius, config.background_splats)
        points = torch.cat([points.double(), shell])
        colours = torch.cat([colours.double(), shell_colours])
        spacing = torch.cat([spacing.double(), shell_spacing])
    return initial_model(points.float(), colours.float(), config.sh_degree, extent, gen, recipe, spacing)


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


def with_sh_degree(model: GaussianModel, degree: int, recipe: Recipe) -> GaussianModel:
    """`model` as `recipe`'s model type with `degree` SH bands: higher bands cut, missing ones zero."""
    if not isinstance(model, recipe.model_type):
        raise InputError("init", f"the initial model is not a {recipe.kind} model")
    coefficients = (degree + 1) ** 2
    sh = model.sh[:, :coefficients]
    if sh.shape[1] < coefficients:
        sh = torch.cat([sh, sh.new_zeros(len(sh), coefficients - sh.shape[1], 3)], dim=1)
    return recipe.model_type(model.means, model.log_scales, model.quats, model.opacity_logits, sh.contiguous())


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


def warm_start(path: str | Path, recipe: Recipe, background: Sequence[float]) -> GaussianModel:
    """The splats of the model at `path` to continue training from: of `recipe`'s family, and,
    when its sidecar says what it was trained over, over `background` (splats fitted over another
    colour carry it in their edges); else an InputError naming `init`. A bare PLY records no
    background: the run's applies."""
    from ..renderers import load_model_bytes

    path = Path(path)
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise InputError("init", f"cannot read {path}: {exc.strerror or exc}") from None
    renderer = load_model_bytes(content, path.name)
    if renderer.kind != recipe.kind or not isinstance(renderer, SplatRenderer):
        raise InputError("init", f"{path.name} is a {renderer.kind} model: a {recipe.kind} run continues "
                         f"from a {recipe.kind} model")
    sidecar = read_sidecar(path) or {}
    theirs = [round(float(v), 4) for v in sidecar.get("background", background)]
    if theirs != [round(float(v), 4) for v in background]:
        raise InputError("init", f"{path.name} was trained over the background {theirs}, this run trains over "
                         f"{[round(float(v), 4) for v in background]}: give the same background")
    return renderer.model


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
    round's model of an active capture after new photos came. Densification runs on the run's
    schedule (the new views show new high-gradient regions) within the splat budget; the SH
    bands the init has are active from the start; the opacity reset is skipped
    (`opacity_reset_interval`); the position rate keeps its schedule: a tenth of it (a shorter
    warm-up for splats already in place) lost 0.05-0.15 dB of test PSNR in each of the four
    measured cases (bench/bench_warm_start.py, docs/gaussians.md "Warm start"). `on_step(step, total)` is
    called after every step (progress; raising from it stops the run).

    Seeded: bit-identical for a seed on one torch thread; with several threads, parallel
    sums may round differently in the last bits.
    """
    if dataset.images is None:
        raise InputError("data", "training needs the images")
    gen = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    centre, extent = scene_bounds(dataset.cameras)
    model = seed_model(dataset, centre, extent, config, gen, recipe) if init is None else \
        with_sh_degree(init, config.sh_degree, recipe)
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
            on_step(step, n_iter)
    final = splats.model()
    keep = torch.sigmoid(final.opacity_logits.detach()) >= config.min_opacity
    detached = recipe.model_type(*(t.detach().clone() for t in (final.means, final.log_scales, final.quats,
                                                                 final.opacity_logits, final.sh)))
    return detached.subset(keep), history
