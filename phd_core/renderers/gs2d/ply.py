"""The PLY layout of the 2DGS reference trainer: the 3DGS one with two scale columns,

    x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0 scale_1 rot_0..3

read and written by the splat PLY code (`phd_core.renderers.splats.ply`) with the surfel model.
A file is a 2DGS PLY when its header declares exactly two scale columns; the 3DGS sniff
takes every other PLY, so no file is claimed by both families.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

from ..splats.ply import is_ply, parse_ply, read_ply, scale_axes, write_ply
from .model import SurfelModel


def is_2dgs_ply(head: bytes) -> bool:
    """True if `head` (the first bytes of a file) is a PLY header with exactly two scale columns."""
    return is_ply(head) and scale_axes(head) == 2


def parse_surfel_ply(data: bytes, name: str = "model") -> SurfelModel:
    """Read a 2DGS PLY held in memory; a 3DGS PLY is refused naming `ply.scale_2`."""
    return cast(SurfelModel, parse_ply(data, name, SurfelModel))     # an instance of the model_type given


def read_surfel_ply(path: str | Path) -> SurfelModel:
    return cast(SurfelModel, read_ply(path, SurfelModel))


def write_surfel_ply(model: SurfelModel, path: str | Path) -> None:
    """Write `model` in the 2DGS reference layout (atomic, binary little-endian)."""
    if not isinstance(model, SurfelModel):
        raise TypeError("write_surfel_ply takes a SurfelModel")
    write_ply(model, path)
