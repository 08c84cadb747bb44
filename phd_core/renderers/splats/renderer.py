"""The renderer every splat family shares: a trained splat model behind the renderer protocol
(`phd_core.renderers.Renderer`), whose dropout units are the splats.

A family subclasses `SplatRenderer` with its `kind`, model class and differentiable
rasteriser, and how it renders: `render_full` (a keep-mask batch), `prepare` (a camera's
reusable state) and `fragment_rows` (a view's fragments, for visibility). The rest is here:
checking the model, the background, Fisher information, the scene box, visibility and
`describe`; and what the family entries share: `set_background`, `with_sidecar` and
`splat_centres`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Sequence

import torch

from ...errors import InputError
from ...scene import Camera, cameras_from_json, pixels_in_box
from ..composite import COMPOSITORS, DEFAULT_COMPOSITOR
from ..protocol import NO_CAMERAS_NOTE, View
from ..provenance import TrainedOn
from ..signals import DEFAULT_SIGNAL, signal_image
from ..visibility import Visibility, fragment_visibility, reduce_to_visibility, robust_box
from .maths import DEFAULT_TILE, Pairs, tile_layout
from .model import GaussianModel
from .ply import read_sidecar

NEAR_PLANE = 0.2
SOLID_OPACITY = 0.05    # splats at least this opaque say where the scene is (`scene_box`)
FISHER_PROBES = 4       # random projections per view in `SplatRenderer.fisher`


@dataclass
class RenderOutput:
    rgb: torch.Tensor       # [N, H, W, 3] composited on the background
    color: torch.Tensor     # [N, H, W, 3] premultiplied: composited on black (rgb without the background)
    alpha: torch.Tensor     # [N, H, W] accumulated opacity
    depth: torch.Tensor     # [N, H, W] alpha-weighted camera depth (divide by alpha for the mean)
    means2d: torch.Tensor   # [G, 2] screen positions (autograd leaf for densification stats)
    visible: torch.Tensor   # [G] bool, survived culling in this view


class SplatRenderer(ABC):
    """A trained splat model behind the renderer protocol; dropout units are the splats: keep [N, G]."""

    kind: ClassVar[str]
    model_type: ClassVar[type[GaussianModel]]
    rasterizer: Callable[..., RenderOutput]     # the differentiable renderer (training, Fisher information)

    def __init__(self, model: GaussianModel, background: Sequence[float] = (1.0, 1.0, 1.0),
                 training_cameras: list[Camera] | None = None, *, tile: int = DEFAULT_TILE,
                 near: float = NEAR_PLANE, compositor: str = DEFAULT_COMPOSITOR, camera_format: str | None = None,
                 notes: Sequence[str] = (), trained_on: TrainedOn | None = None, name: str | None = None):
        if not isinstance(model, self.model_type) or model.scale_axes != self.model_type.scale_axes:
            raise InputError("model", f"a {self.kind} renderer needs a {self.model_type.__name__}, "
                                      f"got {type(model).__name__}")
        model.validate()
        COMPOSITORS.lookup(compositor, "compositor")
        self.model = model
        self.background = torch.tensor(background, dtype=torch.float32)
        self.training_cameras = training_cameras
        self.camera_format = camera_format      # the source's pose convention (phd_core.data.POSES), when known
        self.notes = list(notes)                # what loading found that the user should know (frames, cameras)
        self.trained_on = trained_on            # the capture `phd train` fitted it to, when its sidecar says
        self.name = name                        # the run's name its sidecar records ("<folder>/<stem>")
        self.tile = tile
        self.near = near
        self.compositor = compositor

    @property
    def num_units(self) -> int:
        return self.model.num_splats

    @abstractmethod
    def prepare(self, camera: Camera) -> View:
        """The camera's mask-independent state, rendered per batch of keep-masks."""

    @abstractmethod
    def render_full(self, camera: Camera, keep: torch.Tensor | None = None) -> RenderOutput:
        """`camera` rendered once per keep-mask (keep: [N, G] bool, None = all splats)."""

    @abstractmethod
    def fragment_rows(self, view: View) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                                 torch.Tensor, Pairs]:
        """The full model's fragments of `view`'s camera, grouped by pixel: (row_ptr [S + 1],
        alpha [E], index [E], units [V]: fragment e is of splat units[index[e]], pixel [S] in tile
        layout, the tile grid); from the view's own lists where it keeps them."""

    def render(self, camera: Camera, keep: torch.Tensor | None = None,
               signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        out = self.render_full(camera, keep)
        return signal_image(signal, out.color, out.alpha, self.background)

    def fisher(self, camera: Camera, probes: int = FISHER_PROBES, seed: int = 0) -> torch.Tensor:
        """[G, 5] float64: the diagonal of J^T J of this view's render (J: d pixels / d parameters),
        summed per splat over each parameter group (means, scales, rotation, opacity, colour).

        Estimated without forming J: for v with independent +-1 entries over the image,
        E[(J^T v)^2] = diag(J^T J), so each probe is one backward pass of the differentiable
        rasteriser (FisherRF's quantity, Jiang et al. 2024, by random projections)."""
        leaves = [t.detach().clone().requires_grad_(True) for t in self.model.tensors()]
        generator = torch.Generator().manual_seed(seed)
        total = torch.zeros(self.num_units, len(leaves), dtype=torch.float64)
        with torch.enable_grad():
            rgb = self.rasterizer(type(self.model)(*leaves), camera, self.background, tile=self.tile,
                                  near=self.near).rgb[0]                                       # [H, W, 3]
            for probe in range(probes):
                signs = torch.randint(0, 2, rgb.shape, generator=generator).float() * 2 - 1
                grads = torch.autograd.grad((rgb * signs).sum(), leaves, retain_graph=probe < probes - 1)
                total += torch.stack([g.double().square().reshape(self.num_units, -1).sum(1) for g in grads], 1)
        return total / probes

    def scene_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The box the model's splats fill ([lo, hi] float64), ignoring nearly transparent
        splats and the farthest floaters (`robust_box`): where empty space counts as unobserved."""
        if getattr(self, "_box", None) is None:
            solid = torch.sigmoid(self.model.opacity_logits.detach()) >= SOLID_OPACITY
            self._box = robust_box(self.model.means.detach()[solid])
        return self._box

    @torch.no_grad()
    def visibility(self, view: View, pixel_values: torch.Tensor | None = None) -> Visibility:
        """What `view`'s camera sees of each splat (`phd_core.renderers.visibility`); with
        pixel_values [H, W], each splat's weights times the values of its pixels as well."""
        camera = view.camera
        row_ptr, alpha, index, units, pixel, grid = self.fragment_rows(view)
        tiled = lambda image: tile_layout(image, grid.tiles_x, grid.tiles_y, self.tile)[pixel]   # noqa: E731
        sums = fragment_visibility(row_ptr, alpha, index, units, self.num_units,
                                   None if pixel_values is None else tiled(pixel_values.double()))
        lo, hi = self.scene_box()
        in_box = pixels_in_box(camera, lo, hi)
        return reduce_to_visibility(camera, sums, self.model.means.detach(), tiled(in_box), int(in_box.sum()))

    def describe(self) -> dict[str, Any]:
        lo, hi = self.model.bounds()
        return {
            "kind": self.kind,
            "num_units": self.num_units,
            "sh_degree": self.model.sh_degree,
            "bounds": {"min": lo, "max": hi},
            "background": self.background.tolist(),
            "has_training_cameras": self.training_cameras is not None,
            "camera_format": self.camera_format,
            "notes": list(self.notes),
            "trained_on": None if self.trained_on is None else self.trained_on.fields(),
            "name": self.name,
        }


def set_background(renderer: SplatRenderer, color: tuple[float, float, float]) -> None:
    """Render a splat model over `color` (checked [r, g, b]): the colour it was trained over
    (a splat family's `set_background`)."""
    renderer.background = torch.tensor(color, dtype=torch.float32)


def splat_centres(renderer: SplatRenderer) -> torch.Tensor:
    """[G, 3] where a splat model's content lies (a splat family's `content_points`)."""
    return renderer.model.means.detach()


def with_sidecar(path: Path, renderer: SplatRenderer) -> SplatRenderer:
    """The renderer rebuilt with the training cameras, background, capture format and capture
    record of the sidecar beside `path` (a splat family's `beside`); without one, and without
    cameras, a note says so."""
    sidecar = read_sidecar(path)
    if sidecar is None:
        if renderer.training_cameras is None:
            renderer.notes.append(NO_CAMERAS_NOTE)
        return renderer
    return type(renderer)(renderer.model, sidecar.get("background", (1.0, 1.0, 1.0)),
                          cameras_from_json(sidecar["training_cameras"]), camera_format=sidecar.get("dataset_format"),
                          notes=renderer.notes, trained_on=TrainedOn.from_fields(sidecar),
                          name=sidecar["name"] if isinstance(sidecar.get("name"), str) else None)
