"""The NeRF model family: our safetensors checkpoint, which carries its training cameras;
trained by `phd_core.train.nerf`."""

from __future__ import annotations

from ...scene import Camera
from ..families import Family
from .checkpoint import is_nerf_checkpoint, load_nerf_bytes
from .renderer import NeRFRenderer, nerf_memory


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> NeRFRenderer:
    renderer = load_nerf_bytes(data, name)
    if cameras is None:
        return renderer
    return NeRFRenderer(renderer.model, cameras, rescale=renderer.rescale, use_grid=renderer.use_grid)


NERF = Family("nerf", "a phd NeRF checkpoint", ".nerf", is_nerf_checkpoint, _load,
              trainer="phd_core.train.nerf:train_nerf", train_options=("encoding", "freenerf"),
              memory=nerf_memory)
