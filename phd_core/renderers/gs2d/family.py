"""The 2DGS model family: a PLY in the 2DGS reference layout (two scale columns), with the
training cameras and background from the sidecar `phd train` writes next to it; trained by
`phd_core.train.gs2d` with the options below."""

from __future__ import annotations

from dataclasses import dataclass

from ...errors import check_float
from ...scene import Camera
from ..families import Family, option
from ..splats.renderer import set_background, splat_centres, with_sidecar
from .ply import is_2dgs_ply, parse_surfel_ply
from .render import SurfelRenderer, surfel_memory


@dataclass(frozen=True)
class SurfelOptions:
    """The 2DGS regularisers' weights (Huang et al. 2024; 0 turns one off), checked when built."""

    depth_distortion: float = option(1.0, "depth distortion weight (default 1; 0 off)")
    normal_consistency: float = option(0.05, "normal consistency weight (default 0.05; 0 off)")

    def __post_init__(self) -> None:
        check_float(self.depth_distortion, "depth_distortion", minimum=0.0)
        check_float(self.normal_consistency, "normal_consistency", minimum=0.0)


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> SurfelRenderer:
    return SurfelRenderer(parse_surfel_ply(data, name), training_cameras=cameras)


GS2D = Family("2dgs", "a 2DGS PLY", ".ply", is_2dgs_ply, _load, with_sidecar,
              trainer="phd_core.train.gs2d:train_surfels", train_options=SurfelOptions, memory=surfel_memory,
              set_background=set_background, units="splats", content_points=splat_centres)
