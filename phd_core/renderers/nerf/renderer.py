"""`NeRFRenderer`: a trained radiance field behind the renderer protocol."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ...scene import Camera
from ..protocol import RenderMemory, View, check_keep
from ..provenance import TrainedOn
from ..signals import DEFAULT_SIGNAL, over, signal_image
from ..visibility import FragmentSums, Visibility, reduce_to_visibility
from .config import CHUNK_ELEMENTS, CHUNK_SAMPLES, NeRFConfig
from .field import RadianceField
from .volume import camera_rays, ray_box, ray_samples, render_rays, segment_weights

# --------------------------------------------------------------------------- memory

# What one render call holds, in bytes (upper envelopes of the peaks bench/bench_memory.py
# measures): per pixel (its ray, made in float64); per sample of a ray chunk (bins, points, the
# occupancy lookup), per sample and unit (first layer, skip term), per sample and band of the
# position encoding (a PE frequency, or a hash level with its 8 corners); one group of masks
# through the trunk and heads, in tensors of at most CHUNK_ELEMENTS values (or one mask's): about
# five at once, and more again for the heap the allocator keeps around them (phd_core.allocator
# never trims it during a job: 441 MB resident against 176 MB with every block returned, at
# 100x100 with 16 masks); and per mask and pixel, its images as the ray chunks return them and
# once joined.
RAY_PIXEL_BYTES = 128
SAMPLE_BYTES, SAMPLE_UNIT_BYTES = 96, 16
SEEN_SAMPLE_BYTES = 4      # a seen view's full-model density at each sample (NeRFView)
PE_BAND_BYTES, HASH_LEVEL_BYTES = 96, 256
GROUP_TENSORS = 12
MASK_PIXEL_BYTES = 64


def nerf_memory(renderer: "NeRFRenderer", camera: Camera) -> RenderMemory:
    """Bounds of one render of `camera` (the family's `memory`): nothing is prepared, and past
    the rays a render holds one chunk of samples and one group of masks at a time; a view
    prepared to be seen keeps a density for each sample of its rays (`seen`)."""
    c = renderer.config
    bands = c.hash_levels * HASH_LEVEL_BYTES if c.encoding == "hash" else c.pos_freqs * PE_BAND_BYTES
    chunk = CHUNK_SAMPLES * (SAMPLE_BYTES + SAMPLE_UNIT_BYTES * max(c.width, c.color_width) + bands
                             + PE_BAND_BYTES * c.dir_freqs)
    group = GROUP_TENSORS * 4 * max(CHUNK_ELEMENTS, CHUNK_SAMPLES * max(c.width, c.color_width, 3))
    pixels = camera.width * camera.height
    return RenderMemory(fixed=RAY_PIXEL_BYTES * pixels + chunk + group, kept=0, per_mask=MASK_PIXEL_BYTES * pixels,
                        seen=SEEN_SAMPLE_BYTES * c.samples * pixels)


# --------------------------------------------------------------------------- the renderer

@dataclass
class NeRFOutput:
    rgb: Tensor     # [N, H, W, 3] composited on the background
    color: Tensor   # [N, H, W, 3] premultiplied: composited on black
    alpha: Tensor   # [N, H, W] accumulated opacity
    depth: Tensor   # [N, H, W] alpha-weighted distance along the ray (divide by alpha for the mean)


class NeRFView:
    """One camera prepared for NeRF renders. Every sample goes through the masked trunk, so a
    view keeps nothing of the network between renders (the rays are cheap to make again),
    with one exception: a view prepared to be seen (`NeRFRenderer.prepare_seeing`) keeps, from
    its first render, the full model's density at each sample that render evaluated (4 bytes a
    sample): the trunk run once more on the samples and first layer the masks share, so that
    `visibility` needs no render of its own."""

    def __init__(self, renderer: "NeRFRenderer", camera: Camera, seeing: bool = False):
        self.renderer, self.camera, self.seeing = renderer, camera, seeing
        self.densities: list[Tensor] | None = None      # per ray chunk [K] float32, once a render kept them

    @property
    def nbytes(self) -> int:
        return sum(d.numel() * d.element_size() for d in self.densities or [])

    def render(self, keep: Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> Tensor:
        gather: list[Tensor] | None = [] if self.seeing and self.densities is None else None
        color, alpha, _ = self.renderer.over_black(self.camera, keep, gather)
        if gather is not None:
            self.densities = gather
        return signal_image(signal, color, alpha, self.renderer.background)


class NeRFRenderer:
    """A trained radiance field behind the renderer protocol (`phd_core.renderers.Renderer`).

    Dropout units are the first trunk layer's hidden units: keep [N, width]. One mask is
    one sub-network shared by every ray and sample of a render; survivors are not rescaled
    unless `rescale=True` (divide by the kept share, like the public reference code).
    """

    kind = "nerf"

    def __init__(self, model: RadianceField, training_cameras: list[Camera] | None = None, *,
                 rescale: bool = False, use_grid: bool = True, trained_on: TrainedOn | None = None):
        self.model = model.eval()
        self.training_cameras = training_cameras
        self.trained_on = trained_on            # the capture `phd train` fitted it to, when its checkpoint says
        self.rescale = rescale
        self.use_grid = use_grid

    @property
    def num_units(self) -> int:
        return self.model.config.width

    @property
    def config(self) -> NeRFConfig:
        return self.model.config

    @property
    def background(self) -> Tensor:
        return torch.tensor(self.config.background, dtype=torch.float32)

    def ray_chunks(self, camera: Camera) -> list[tuple[Tensor, Tensor]]:
        """The camera's rays (origins, dirs [R, 3]) in the chunks every pass over them takes."""
        origins, dirs = camera_rays(camera)
        rays_per_chunk = max(1, CHUNK_SAMPLES // self.config.samples)
        return list(zip(origins.split(rays_per_chunk), dirs.split(rays_per_chunk)))

    @torch.no_grad()
    def over_black(self, camera: Camera, keep: Tensor | None = None, densities: list[Tensor] | None = None
                   ) -> tuple[Tensor, Tensor, Tensor]:
        """`camera` rendered once per keep-mask over black: colour [N, H, W, 3], alpha and depth [N, H, W].
        With a list `densities`, each ray chunk appends the full model's density at the samples it
        evaluated ([K] float32), from the samples and first layer the masks share."""
        keep = check_keep(keep, self.num_units)
        n = 1 if keep is None else keep.shape[0]
        black = torch.zeros(3)
        parts = []
        for origins, dirs in self.ray_chunks(camera):
            parts.append(render_rays(self.model, origins, dirs, keep=keep, rescale=self.rescale, use_grid=self.use_grid,
                                     background=black, full_density=densities is not None))
            if densities is not None and parts[-1].full_density is not None:
                densities.append(parts[-1].full_density)
        h, w = camera.height, camera.width
        return (torch.cat([p.rgb for p in parts], 1).view(n, h, w, 3),
                torch.cat([p.alpha for p in parts], 1).view(n, h, w),
                torch.cat([p.depth for p in parts], 1).view(n, h, w))

    def render_full(self, camera: Camera, keep: Tensor | None = None) -> NeRFOutput:
        color, alpha, depth = self.over_black(camera, keep)
        return NeRFOutput(over(color, alpha, self.background), color, alpha, depth)

    def render(self, camera: Camera, keep: Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> Tensor:
        color, alpha, _ = self.over_black(camera, keep)
        return signal_image(signal, color, alpha, self.background)

    def prepare(self, camera: Camera) -> "NeRFView":
        return NeRFView(self, camera)

    def prepare_seeing(self, camera: Camera) -> "NeRFView":
        """A view that will be asked what it sees after its masked renders (`visibility.prepare_seeing`):
        its first render also keeps the full model's density at every sample it evaluates."""
        return NeRFView(self, camera, seeing=True)

    @torch.no_grad()
    def visibility(self, view: View, pixel_values: Tensor | None = None) -> Visibility:
        """What `view`'s camera sees of the field, per occupancy-grid cell
        (`phd_core.renderers.visibility`): each sample's weight (transmittance times alpha) and
        alpha summed into its cell; with pixel_values [H, W], the weights times the values too.

        The full model's densities come from the view's renders when it kept them (`prepare_seeing`),
        else from the density network alone at the samples a render evaluates: the same numbers
        either way. The samples, cells and sums are recomputed here (no network: cheap)."""
        camera, grid = view.camera, self.model.grid
        kept = view.densities if isinstance(view, NeRFView) else None
        cells = grid.resolution ** 3
        values = None if pixel_values is None else pixel_values.reshape(-1).double()
        zeros = torch.zeros(cells, dtype=torch.float64)
        weight, footprint = zeros.clone(), zeros.clone()
        valued = None if values is None else zeros.clone()
        left, start = [], 0
        for i, (o, d) in enumerate(self.ray_chunks(camera)):
            _, delta, points, valid = ray_samples(self.model, o, d, use_grid=self.use_grid)
            flat = valid.flatten().nonzero()[:, 0]                                                  # [K]
            density = kept[i] if kept is not None else self.model.density(points.reshape(-1, 3)[flat])
            sigma = density.new_zeros(valid.numel()).index_copy(0, flat, density).view(valid.shape)  # [R, S]
            tau = (sigma * delta).double() * valid                                                  # [R, S]
            w, total = segment_weights(tau)                                                         # [R, S]
            alpha = -torch.expm1(-tau)
            cell = grid.cells(points.reshape(-1, 3))
            weight.index_add_(0, cell, w.reshape(-1))
            footprint.index_add_(0, cell, alpha.reshape(-1))
            if valued is not None and values is not None:          # both set with pixel_values
                valued.index_add_(0, cell, (w * values[start:start + len(o), None]).reshape(-1))
            left.append(torch.exp(-total[:, -1]))
            start += len(o)
        origins, dirs = camera_rays(camera)
        t_in, t_out = ray_box(origins, dirs, grid.lo, grid.lo + grid.size)
        in_box = (t_out > t_in) & (t_out > 0)
        centres = grid.cell_points(torch.full((1, 3), 0.5))
        return reduce_to_visibility(camera, FragmentSums(weight, footprint, valued, torch.cat(left)), centres, in_box,
                                    int(in_box.sum()))

    def describe(self) -> dict[str, Any]:
        c = self.config
        return {
            "kind": self.kind,
            "num_units": self.num_units,
            "encoding": c.encoding,
            "depth": c.depth,
            "width": c.width,
            "parameters": sum(p.numel() for p in self.model.parameters()),
            "samples_per_ray": c.samples,
            "near": c.near,
            "far": c.far,
            "bounds": {"min": c.bounds[0], "max": c.bounds[1]},
            "background": c.background,
            "occupancy_grid": {"resolution": c.grid_resolution, "occupied_fraction": self.model.grid.fraction,
                               "in_use": self.use_grid},
            "freenerf": {"frequency_mask": c.freenerf_frequency, "occlusion": c.freenerf_occlusion},
            "rescale": self.rescale,
            "has_training_cameras": self.training_cameras is not None,
            "trained_on": None if self.trained_on is None else self.trained_on.fields(),
        }


def occupied_cells(renderer: NeRFRenderer) -> Tensor:
    """[C, 3] the centres of the occupancy grid's occupied cells: where a radiance field's
    content lies (the family's `content_points`)."""
    grid = renderer.model.grid
    return grid.cell_points(torch.full((1, 3), 0.5))[grid.occupied.flatten()]
