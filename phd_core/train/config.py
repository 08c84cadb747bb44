"""The splat loop's settings (`TrainConfig`) and what differs between the families it trains
(`Recipe`), shared by the loop (`splats`) and where a run starts (`seeding`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence, cast

import torch

from ..errors import check_color, check_float, check_int
from ..renderers.composite import COMPOSITORS, DEFAULT_COMPOSITOR
from ..renderers.splats import GaussianModel
from ..renderers.splats.renderer import RenderOutput, SplatRenderer
from ..scene import Camera
from .clock import TrainStep

StepCallback = Callable[[TrainStep], None]     # after every step: steps done, in the run, time left


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
