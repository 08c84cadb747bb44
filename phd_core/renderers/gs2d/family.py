"""The 2DGS model family: a PLY in the 2DGS reference layout (two scale columns), with the
training cameras and background from the sidecar `phd train` writes next to it; trained by
`phd_core.train.gs2d`."""

from __future__ import annotations

from ...scene import Camera
from ..families import Family
from ..gs3d.family import with_sidecar
from .ply import is_2dgs_ply, parse_surfel_ply
from .render import SurfelRenderer, surfel_memory


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> SurfelRenderer:
    return SurfelRenderer(parse_surfel_ply(data, name), training_cameras=cameras)


GS2D = Family("2dgs", "a 2DGS PLY", ".ply", is_2dgs_ply, _load, with_sidecar,
              trainer="phd_core.train.gs2d:train_surfels", train_options=("depth_distortion", "normal_consistency"),
              memory=surfel_memory)
