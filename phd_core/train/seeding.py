"""Where a splat run starts: the first splats of a cold start (`seed_model`: carved from the
alpha masks, the SfM points, or uniform; `phd_core.train.splats`' docstring says when each), or
the splats of a model to continue from (`warm_start`, the capture loop's next round), with the
SfM points only the new photos see added (`with_new_points`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import torch

from ..data import Dataset
from ..errors import InputError
from ..renderers.outputs.base import nearest_distances
from ..renderers.splats import SH_C0, GaussianModel, read_sidecar
from ..renderers.splats.renderer import SplatRenderer
from ..scene import footprint, visual_hull
from .config import Recipe, TrainConfig


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
        points = data.points.to(torch.float64)
        colours, spacing = point_colours(data, points), neighbour_spacing(points)
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


def point_colours(data: Dataset, points: torch.Tensor) -> torch.Tensor:
    """[P, 3] float64 colours of the SfM points `points` [P, 3] of `data`: theirs, or where the model was
    published without colours (all black) the mean of the training pixels they project to."""
    assert data.point_colors is not None  # the readers that give points give their colours
    colours = data.point_colors.to(torch.float64)
    if not colours.any():
        colour_sum, seen = pixels_behind(data, points)
        colours = torch.where(seen[:, None] > 0, colour_sum / seen.clamp_min(1)[:, None], 0.5)
    return colours


NEW_POINT_REACH = 2.0    # an SfM point farther than this many of its neighbour spacings from every splat is new


def with_new_points(model: GaussianModel, data: Dataset, extent: float, gen: torch.Generator,
                    recipe: Recipe) -> GaussianModel:
    """A warm start's splats plus a seeded splat (as `seed_model` seeds) at each SfM point of `data` that no
    splat of `model` comes near (NEW_POINT_REACH of its neighbour spacing): what only the photos added since
    the model was trained see, which densification would have to grow into from afar. Data without
    SfM points, or with alpha masks (whose cold start carves, not seeds from points): `model` as it is."""
    if data.alphas is not None or data.points is None or len(data.points) == 0 or model.num_splats == 0:
        return model
    points = data.points.to(torch.float64)
    spacing = neighbour_spacing(points)                                               # [P]
    new = nearest_distances(points, model.means.detach()) > NEW_POINT_REACH * spacing  # [P]
    if not new.any():
        return model
    added = initial_model(points[new].float(), point_colours(data, points)[new].float(), model.sh_degree, extent,
                          gen, recipe, spacing[new])
    return recipe.model_type(*(torch.cat([getattr(model, k), getattr(added, k)]).contiguous()
                               for k in ("means", "log_scales", "quats", "opacity_logits", "sh")))


def with_sh_degree(model: GaussianModel, degree: int, recipe: Recipe) -> GaussianModel:
    """`model` as `recipe`'s model type with `degree` SH bands: higher bands cut, missing ones zero."""
    if not isinstance(model, recipe.model_type):
        raise InputError("init", f"the initial model is not a {recipe.kind} model")
    coefficients = (degree + 1) ** 2
    sh = model.sh[:, :coefficients]
    if sh.shape[1] < coefficients:
        sh = torch.cat([sh, sh.new_zeros(len(sh), coefficients - sh.shape[1], 3)], dim=1)
    return recipe.model_type(model.means, model.log_scales, model.quats, model.opacity_logits, sh.contiguous())


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
