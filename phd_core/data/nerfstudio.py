"""The nerfstudio layout: one transforms.json (served as the split "all", or "train"), with
`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` at the top level or per frame. Cameras go back out as
the same frames (`write_transforms`), which nerfstudio and this loader read."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from ..errors import InputError
from ..io import write_json_atomic
from ..scene import Camera
from .formats import FORMATS, DataFormat
from .frames import Dataset, count_frames, load_frames
from .poses import POSES, PoseConvention


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


FORMATS.register(DataFormat("nerfstudio", locate, lambda json_path, split, **kw: load_nerfstudio(json_path, **kw),
                            order=20, looks_for="transforms.json", count=count_frames))


def write_transforms(path: Path, cameras: Sequence[Camera], names: Sequence[str]) -> None:
    """A transforms.json whose frames are `cameras` (OpenGL c2w and pinhole intrinsics per
    frame), each naming the image to capture as images/<name>."""
    frames = [{"file_path": f"images/{name}", **camera.to_frame()} for camera, name in zip(cameras, names)]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, {"camera_model": "OPENCV", "frames": frames})


TRANSFORMS_FRAME = "a transforms.json with one frame per camera"
POSES.register(PoseConvention("nerfstudio", Camera.to_frame, write_transforms, TRANSFORMS_FRAME, suffix=".json"))
