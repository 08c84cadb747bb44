"""The Blender (NeRF-synthetic) layout: transforms_{split}.json per split, `camera_angle_x`,
images named by `file_path` without `.png`, near 2 and far 6 unless the JSON says otherwise.
Cameras go back out in the same layout (`write_blender`): one `camera_angle_x` for every
frame, OpenGL camera-to-world `transform_matrix` (the project's own axes), `./images/<name>`."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

from ..errors import InputError
from ..io import write_json_atomic
from ..scene import Camera
from .formats import FORMATS, DataFormat
from .frames import Dataset, check_split, count_frames, load_frames
from .poses import POSES, PoseConvention

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


def blender_intrinsics(camera: Camera) -> dict[str, Any]:
    """The camera's lens as a Blender JSON states it: `camera_angle_x` = 2 atan(w / (2 fx)) and
    the image size `w`, `h` (NeRF-synthetic leaves the size to its images, which a pose to be
    captured has not yet); `camera_angle_y` only for non-square pixels and `cx`, `cy` only off
    the image centre, the two things the format otherwise assumes."""
    lens: dict[str, Any] = {"camera_angle_x": 2 * math.atan(camera.width / (2 * camera.fx)),
                            "w": camera.width, "h": camera.height}
    if camera.fy != camera.fx:
        lens["camera_angle_y"] = 2 * math.atan(camera.height / (2 * camera.fy))
    if (camera.cx, camera.cy) != (camera.width / 2, camera.height / 2):
        lens["cx"], lens["cy"] = camera.cx, camera.cy
    return lens


def blender_pose(camera: Camera) -> dict[str, Any]:
    """One camera in Blender terms: its OpenGL camera-to-world matrix and its lens."""
    return {"transform_matrix": camera.c2w.tolist(), **blender_intrinsics(camera)}


def write_blender(path: Path, cameras: Sequence[Camera], names: Sequence[str]) -> None:
    """A transforms_<split>.json as NeRF-synthetic writes it: the lens once at the top (the format
    has one `camera_angle_x` for all frames, so cameras whose lenses differ are refused), each
    frame's `transform_matrix` and `file_path` ./images/<name> without its suffix (the loader
    adds .png)."""
    lens = blender_intrinsics(cameras[0])
    for i, camera in enumerate(cameras):
        if blender_intrinsics(camera) != lens:
            raise InputError(f"cameras[{i}]", "its image size or focal length differs from the first pose's, and "
                             "a Blender transforms JSON has one camera_angle_x for every frame: export these poses "
                             "as nerfstudio (a focal length per frame)")
    frames = [{"file_path": f"./images/{Path(name).stem}", "transform_matrix": camera.c2w.tolist()}
              for camera, name in zip(cameras, names)]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, {**lens, "frames": frames})


POSES.register(PoseConvention("blender", blender_pose, write_blender,
                              "a Blender transforms_train.json: one camera_angle_x, a transform_matrix per frame",
                              file_name="transforms_train.json"))
