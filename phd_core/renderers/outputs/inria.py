"""The reference 3DGS trainer's output folder (cameras.json, cfg_args,
point_cloud/iteration_N/point_cloud.ply): it trains in the capture's own frame, so the
latest PLY is used as is (`phd_core.data.inria` reads the folder)."""

from __future__ import annotations

from pathlib import Path

from ...data.inria import is_output_folder, read_output_folder
from ..gs3d import read_ply
from .base import OUTPUTS, OutputFormat, TrainerOutput


def read(folder: Path) -> TrainerOutput:
    found = read_output_folder(folder)
    return TrainerOutput(read_ply(found.ply), found.cameras, found.background, found.ply, ply=found.ply,
                         camera_format="3dgs-output", name=f"{folder.resolve().name}/3dgs")


OUTPUTS.register(OutputFormat("3dgs-output", "a reference 3DGS output folder (cameras.json + point_cloud/iteration_*)",
                              is_output_folder, read, order=10))
