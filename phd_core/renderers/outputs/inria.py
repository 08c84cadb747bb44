"""The reference 3DGS trainer's output folder (cameras.json, cfg_args,
point_cloud/iteration_N/point_cloud.ply): it trains in the capture's own frame, so the
latest PLY is used as is (`phd_core.data.inria` reads the folder)."""

from __future__ import annotations

from pathlib import Path

from ...data.inria import is_output_folder, read_cfg_args, read_output_folder
from ..gs3d import read_ply
from .base import OUTPUTS, OutputFormat, TrainerOutput, data_candidates


def read(folder: Path, within: Path | None = None) -> TrainerOutput:
    found = read_output_folder(folder)
    # cfg_args' source_path: the capture it trained on; its own splits are the run's (--eval holds out every 8th)
    source = read_cfg_args(folder).source_path
    capture = next((p for p in data_candidates(folder, source, within) if p.is_dir()), None) if source else None
    return TrainerOutput(read_ply(found.ply), found.cameras, found.background, found.ply, ply=found.ply,
                         camera_format="3dgs-output", capture=capture, name=f"{folder.resolve().name}/3dgs")


OUTPUTS.register(OutputFormat("3dgs-output", "a reference 3DGS output folder (cameras.json + point_cloud/iteration_*)",
                              is_output_folder, read, order=10))
