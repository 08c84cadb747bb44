"""The 3DGS model family: a standard 3DGS PLY, with the training cameras and background from
the sidecar `phd train` writes next to it; trained by `phd_core.train.gs3d`."""

from __future__ import annotations

from pathlib import Path

from ...scene import Camera, cameras_from_json
from ..families import Family
from .ply import is_3dgs_ply, parse_ply, read_sidecar
from .render import GaussianRenderer, view_memory


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> GaussianRenderer:
    return GaussianRenderer(parse_ply(data, name), training_cameras=cameras)


def with_sidecar(path: Path, renderer: GaussianRenderer) -> GaussianRenderer:
    """The renderer rebuilt with the training cameras, background and capture format of the
    sidecar beside `path` (any splat renderer class built like `GaussianRenderer`)."""
    sidecar = read_sidecar(path)
    if sidecar is None:
        return renderer
    return type(renderer)(renderer.model, sidecar.get("background", (1.0, 1.0, 1.0)),
                          cameras_from_json(sidecar["training_cameras"]), camera_format=sidecar.get("dataset_format"))


GS3D = Family("3dgs", "a 3DGS PLY", ".ply", is_3dgs_ply, _load, with_sidecar,
              trainer="phd_core.train.gs3d:train_gaussians", memory=view_memory)
