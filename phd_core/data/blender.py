"""The Blender (NeRF-synthetic) layout: transforms_{split}.json per split, `camera_angle_x`,
images named by `file_path` without `.png`, near 2 and far 6 unless the JSON says otherwise."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from ..errors import InputError
from .formats import FORMATS, DataFormat
from .frames import Dataset, check_split, count_frames, load_frames

# The NeRF-synthetic scenes fit in [-1.5, 1.5]^3 seen from radius ~4: near 2, far 6.
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0


def load_blender(root: str | Path, split: str = "train", *, downscale: float = 1,
                 views: int | Sequence[int] | None = None, background: Sequence[float] = (1, 1, 1),
                 seed: int | None = None, with_images: bool = True) -> Dataset:
    """Load `root/transforms_{split}.json` and its images (Blender / NeRF-synthetic layout).

    near/far come from top-level "near"/"far" keys when present, else the NeRF-synthetic
    convention of 2 and 6.
    """
    root = Path(root)
    check_split(split)
    if not root.is_dir():
        raise InputError("data", f"dataset directory not found: {root}")
    json_path = root / f"transforms_{split}.json"
    if not json_path.is_file():
        raise InputError("data", f"no transforms_{split}.json in {root}")
    return load_frames(json_path, split, default_near_far=(BLENDER_NEAR, BLENDER_FAR), downscale=downscale,
                 views=views, background=background, seed=seed, with_images=with_images)


def locate(path: Path, split: str) -> Path | None:
    """The split's JSON when `path` is a Blender scene folder."""
    json_path = path / f"transforms_{split}.json"
    return json_path if path.is_dir() and json_path.is_file() else None


FORMATS.register(DataFormat("blender", locate,
                            lambda json_path, split, **kw: load_blender(json_path.parent, split, **kw),
                            order=10, looks_for="transforms_{split}.json", count=count_frames))
