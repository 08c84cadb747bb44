"""Trainers' output folders taken as is, one module per trainer behind `OUTPUTS`:

    inria       the reference 3DGS trainer (cameras.json + point_cloud/iteration_*): its own frame
    nerfstudio  splatfacto (config.yml + dataparser_transforms.json, with splat.ply or a checkpoint)
    gsplat      gsplat's simple_trainer (ckpts/ckpt_*_rank*.pt) with the COLMAP capture it read

Trainers that normalise the world are mapped back into the user's frame on loading (splats
and cameras), so every pose in and out of the project is in the frame the user holds.
docs/formats.md describes each. A new trainer is one module calling `OUTPUTS.register`.
"""

from .base import OUTPUTS, OutputFormat, TrainerOutput, load_output, read_output
from . import inria, nerfstudio, gsplat  # noqa: E402,F401  (registration; each states its detection order)

__all__ = ["OUTPUTS", "OutputFormat", "TrainerOutput", "load_output", "read_output"]
