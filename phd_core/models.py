"""Load any supported model by its content, never by its file name.

A 3DGS PLY starts with `ply`; a NeRF checkpoint is a safetensors file marked as ours.
Anything else (a pickle, an archive, random bytes) is refused before it is parsed, so
no file can execute code on load.
"""

from __future__ import annotations

from pathlib import Path

from .cameras import Camera, cameras_from_json
from .errors import InputError
from .gaussian_render import GaussianRenderer
from .gaussians import is_ply, parse_ply, read_sidecar
from .nerf import is_nerf_checkpoint, load_nerf_bytes
from .protocol import Renderer

SNIFF_BYTES = 4096


class UnknownModelError(InputError):
    """The content is neither a 3DGS PLY nor a phd NeRF checkpoint."""

    def __init__(self, name: str):
        super().__init__("model", f"{name} is neither a 3DGS PLY nor a phd NeRF checkpoint "
                                  "(the kind is detected from the content, not the file name)")


def model_kind(head: bytes) -> str | None:
    """'3dgs', 'nerf' or None from the first bytes of a file."""
    if is_ply(head):
        return "3dgs"
    if is_nerf_checkpoint(head):
        return "nerf"
    return None


def load_model_bytes(data: bytes, name: str = "model",
                     training_cameras: list[Camera] | None = None) -> Renderer:
    """Parse a model held in memory. `training_cameras` overrides any stored in the file."""
    kind = model_kind(data[:SNIFF_BYTES])
    if kind == "3dgs":
        return GaussianRenderer(parse_ply(data, name), training_cameras=training_cameras)
    if kind == "nerf":
        renderer = load_nerf_bytes(data, name)
        if training_cameras is not None:
            renderer.training_cameras = training_cameras
        return renderer
    raise UnknownModelError(name)


def load_model(path: str | Path) -> Renderer:
    """Load a model file. A PLY takes its training cameras and background from the
    sidecar `<stem>.json` that `phd train` writes next to it, when there is one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError("model", f"cannot read {path}: {exc.strerror or exc}") from None
    renderer = load_model_bytes(data, path.name)
    if isinstance(renderer, GaussianRenderer):
        sidecar = read_sidecar(path)
        if sidecar is not None:
            renderer = GaussianRenderer(renderer.model, sidecar.get("background", (1.0, 1.0, 1.0)),
                                        cameras_from_json(sidecar["training_cameras"]))
    return renderer
