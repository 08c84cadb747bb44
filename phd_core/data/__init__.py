"""Datasets: one module per capture format (blender, nerfstudio) behind `FORMATS`, a registry
that recognises the folder; `frames` holds what they share (Dataset, views, images)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import InputError
from .blender import BLENDER_FAR, BLENDER_NEAR, load_blender
from .formats import FORMATS, DataFormat
from .frames import Dataset, check_split, read_transforms, select_views
from .nerfstudio import load_nerfstudio


def locate(path: str | Path, split: str) -> tuple[DataFormat, Path]:
    """The first registered format that recognises `path`, and the file it would load."""
    check_split(split)
    path = Path(path)
    if not path.exists():
        raise InputError("data", f"no such file or directory: {path}")
    for data_format in FORMATS.values():
        located = data_format.locate(path, split)
        if located is not None:
            return data_format, located
    raise InputError("data", f"{path} has neither transforms_{split}.json nor transforms.json")


def load_dataset(path: str | Path, split: str = "train", **kw: Any) -> Dataset:
    """Load any registered format: a directory with transforms_{split}.json is Blender; a
    transforms.json (or a directory with one) is nerfstudio, whose one frame list is
    served as the "train" (or "all") split."""
    data_format, located = locate(path, split)
    return data_format.load(located, split, **kw)


def split_size(root: str | Path, split: str) -> int:
    """Number of frames in a split, read from the JSON alone (no images)."""
    _, json_path = locate(root, split)
    frames, _ = read_transforms(json_path)
    return len(frames)


__all__ = ["BLENDER_FAR", "BLENDER_NEAR", "FORMATS", "DataFormat", "Dataset", "load_blender", "load_dataset",
           "load_nerfstudio", "select_views", "split_size"]
