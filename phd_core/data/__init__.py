"""Datasets: one module per capture format behind `FORMATS`, a registry that recognises the
folder from its content (the formats are tried in the order `formats` documents); `frames`
holds what they share (Dataset, views, images). docs/formats.md lists every format with its
axis convention."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

from ..errors import InputError
from ..io.foreign import read_json
from ..scene import DEFAULT_MAX_SIZE, Camera, cameras_from_json
from .blender import BLENDER_FAR, BLENDER_NEAR, load_blender
from .formats import FORMATS, DataFormat
from .frames import Dataset, check_split, select_views
from .nerfstudio import load_nerfstudio
from .colmap import load_colmap
from .llff import load_llff
from .inria import cameras_from_entries, is_inria_cameras, load_inria, read_output_folder
from .poses import POSES, PoseConvention, candidate_name, export_cameras, export_convention, source_pose


def locate(path: str | Path, split: str) -> tuple[DataFormat, Path]:
    """The first format, in detection order (`formats`), that recognises `path`, and the file
    it would load."""
    check_split(split)
    path = Path(path)
    if not path.exists():
        raise InputError("data", f"no such file or directory: {path}")
    tried = FORMATS.in_order()
    for data_format in tried:
        located = data_format.locate(path, split)
        if located is not None:
            return data_format, located
    looked_for = [f.looks_for.format(split=split) for f in tried if f.looks_for]
    raise InputError("data", f"{path} is no capture this project reads ({', '.join(FORMATS)}): it has neither "
                     f"{', '.join(looked_for[:-1])} nor {looked_for[-1]}")


def load_dataset(path: str | Path, split: str = "train", **kw: Any) -> Dataset:
    """Load any registered format, recognised from the content: a directory with
    transforms_{split}.json is Blender; a transforms.json (or a directory with one) is
    nerfstudio, whose one frame list is served as the "train" (or "all") split; a COLMAP
    model, an LLFF poses_bounds.npy and a 3DGS output folder have "train", "test" and "all"."""
    data_format, located = locate(path, split)
    return data_format.load(located, split, **kw)


def split_size(root: str | Path, split: str) -> int:
    """Number of frames in a split (cameras only, no images)."""
    data_format, located = locate(root, split)
    if data_format.count is not None:
        return data_format.count(located, split)
    return len(data_format.load(located, split, with_images=False).cameras)


def load_cameras(source: str | Path | dict | list, *, split: str = "train", width: int | None = None,
                 height: int | None = None, max_size: int = DEFAULT_MAX_SIZE) -> list[Camera]:
    """Cameras from anything a user may hold: a transforms-style JSON (file, dict or list of
    frames), a reference-trainer cameras.json (file or parsed list), or a capture folder or
    file of any registered format (its `split`)."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.is_file() and path.suffix.lower() == ".json":
            try:
                source = read_json(path)
            except InputError as exc:
                raise InputError("cameras", exc.reason) from None
            if isinstance(source, dict) and isinstance(source.get("training_cameras"), list):
                source = source["training_cameras"]          # a `phd train` sidecar
        else:
            return load_dataset(path, split, with_images=False).cameras
    if is_inria_cameras(source):
        return cameras_from_entries(source, max_size, file="frames")
    # What a JSON file held is any JSON value: cameras_from_json refuses all but a dict or list.
    return cameras_from_json(cast(dict | list, source), width=width, height=height, max_size=max_size)


__all__ = ["BLENDER_FAR", "BLENDER_NEAR", "FORMATS", "POSES", "DataFormat", "Dataset", "PoseConvention",
           "candidate_name", "export_cameras", "export_convention", "source_pose", "load_blender", "load_cameras",
           "load_colmap", "load_dataset", "load_inria", "load_llff", "load_nerfstudio", "read_output_folder",
           "select_views", "split_size"]
