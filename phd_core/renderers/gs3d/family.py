"""The 3DGS model family: a standard 3DGS PLY, with the training cameras and background from
the sidecar `phd train` writes next to it; trained by `phd_core.train.gs3d`."""

from __future__ import annotations

from ...scene import Camera
from ..families import SNIFF_BYTES, Family
from ..splats.ply import frame_notes, parse_ply
from ..splats.renderer import set_background, splat_centres, with_sidecar
from .ply import is_3dgs_ply
from .render import GaussianRenderer, view_memory


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> GaussianRenderer:
    return GaussianRenderer(parse_ply(data, name), training_cameras=cameras, notes=frame_notes(data[:SNIFF_BYTES]))


GS3D = Family("3dgs", "a 3DGS PLY", ".ply", is_3dgs_ply, _load, with_sidecar,
              trainer="phd_core.train.gs3d:train_gaussians", memory=view_memory, set_background=set_background,
              units="splats", content_points=splat_centres)
