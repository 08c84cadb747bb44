"""The NeRF model family: our safetensors checkpoint, which carries its training cameras, its
background and the capture it was trained on; trained by `phd_core.train.nerf` with the
options below."""

from __future__ import annotations

from dataclasses import dataclass

from ...errors import check_bool
from ...scene import Camera
from ..families import Family, option
from .checkpoint import is_nerf_checkpoint, load_nerf_bytes
from .config import ENCODINGS, check_encoding
from .renderer import NeRFRenderer, nerf_memory, occupied_cells


@dataclass(frozen=True)
class NeRFOptions:
    """The NeRF trainer's `phd train` options, checked when built."""

    encoding: str = option("pe", "input encoding (default pe)", choices=ENCODINGS)
    freenerf: bool = option(False, "FreeNeRF frequency and occlusion regularisation")

    def __post_init__(self) -> None:
        check_encoding(self.encoding)
        check_bool(self.freenerf, "freenerf")


def _load(data: bytes, name: str, cameras: list[Camera] | None) -> NeRFRenderer:
    renderer = load_nerf_bytes(data, name)
    if cameras is None:
        return renderer
    return NeRFRenderer(renderer.model, cameras, rescale=renderer.rescale, use_grid=renderer.use_grid,
                        trained_on=renderer.trained_on)


NERF = Family("nerf", "a phd NeRF checkpoint", ".nerf", is_nerf_checkpoint, _load,
              trainer="phd_core.train.nerf:train_nerf", train_options=NeRFOptions, memory=nerf_memory,
              units="first-layer hidden units", network=("encoding", "depth", "width", "parameters", "samples_per_ray"),
              content_points=occupied_cells)
