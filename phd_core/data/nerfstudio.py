"""The nerfstudio layout: one transforms.json (served as the split "all", or "train"), with
`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` at the top level or per frame."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from ..errors import InputError
from .formats import FORMATS, DataFormat
from .frames import Dataset, load_frames

def load_nerfstudio(path: str | Path, *, downscale: float = 1, views: int | Sequence[int] | None = None,
                    background: Sequence[float] = (1, 1, 1), seed: int | None = None,
                    with_images: bool = True) -> Dataset:
    """Load a nerfstudio transforms.json (or a directory holding one) and its images.

    All frames form one split, "all". Only undistorted pinhole cameras are accepted.
    near/far come from top-level "near"/"far" keys when present, else None.
    """
    path = Path(path)
    json_path = path / "transforms.json" if path.is_dir() else path
    if not json_path.is_file():
        raise InputError("data", f"no transforms.json at {path}")
    return load_frames(json_path, "all", default_near_far=(None, None), downscale=downscale,
                 views=views, background=background, seed=seed, with_images=with_images)


def locate(path: Path, split: str) -> Path | None:
    """A transforms.json given directly or inside `path`; its one frame list is "train" or "all"."""
    json_path = path if path.is_file() else path / "transforms.json"
    if not json_path.is_file() or json_path.suffix.lower() != ".json":
        return None
    if split not in ("train", "all"):
        raise InputError("split", f"a nerfstudio transforms.json has no '{split}' split: "
                         "load 'all' and pick frames with views")
    return json_path


FORMATS.add("nerfstudio", DataFormat("nerfstudio", locate,
                                     lambda json_path, split, **kw: load_nerfstudio(json_path, **kw)))
