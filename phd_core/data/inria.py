"""The reference 3DGS trainer's output folder, taken as is:

    output/
      cameras.json                         one entry per camera (below)
      cfg_args                             the training arguments (a Python Namespace repr)
      point_cloud/iteration_7000/point_cloud.ply
      point_cloud/iteration_30000/point_cloud.ply    the latest iteration is used by default

cameras.json entries: {id, img_name, width, height, position, rotation, fx, fy}. `position`
is the camera centre in world coordinates and `rotation` the 3x3 camera-to-world rotation
with OpenCV camera axes (x right, y down, z forward), i.e. the inverse of the COLMAP pose
the trainer read. The project's `Camera` is OpenGL (y up, looking down -z), so
c2w = [rotation | position] @ diag(1, -1, -1, 1); the principal point is the image centre
(the trainer assumes it).

The trainer writes test cameras into cameras.json too when it ran with --eval (every 8th
image by name): cfg_args says so (`eval=True`), and those are left out of the training
cameras. Its background is black unless cfg_args has `white_background=True`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import InputError, shown
from ..io import write_json_atomic
from ..io.configs import InriaArgs, parse_config
from ..io.foreign import MAX_CONFIG_BYTES, read_json, read_text
from ..scene import DEFAULT_MAX_SIZE, Camera
from .formats import FORMATS, DataFormat
from .frames import HOLDOUT, Dataset, build_dataset
from .poses import POSES, PoseConvention

_GL_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
KEYS = ("width", "height", "position", "rotation", "fx", "fy")


def is_inria_cameras(source: Any) -> bool:
    """True for a parsed reference-trainer cameras.json: a list of objects with position and rotation."""
    return (isinstance(source, list) and bool(source) and isinstance(source[0], dict)
            and "rotation" in source[0] and "position" in source[0])


def camera_from_entry(entry: Any, max_size: int = DEFAULT_MAX_SIZE) -> Camera:
    """One cameras.json entry -> Camera. Errors name the key (the caller adds the index)."""
    if not isinstance(entry, dict):
        raise InputError("entry", f"must be an object, got {type(entry).__name__}")
    for key in KEYS:
        if key not in entry:
            raise InputError(key, "missing")
    try:
        rotation = np.array(entry["rotation"], dtype=np.float64)
        position = np.array(entry["position"], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("rotation", "rotation must be 3x3 numbers and position 3 numbers") from None
    if rotation.shape != (3, 3):
        raise InputError("rotation", f"must be a 3x3 matrix, got shape {list(rotation.shape)}")
    if position.shape != (3,):
        raise InputError("position", f"must be 3 numbers, got shape {list(position.shape)}")
    values: dict[str, Any] = {}     # finite numbers; Camera refuses a size that is not a whole number
    for key in ("width", "height", "fx", "fy"):
        value = entry[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(key, f"must be a finite number, got {shown(value)}")
        values[key] = value
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(rotation)
    c2w[:3, 3] = torch.from_numpy(position)
    try:
        return Camera(c2w @ _GL_FLIP, values["fx"], values["fy"], values["width"] / 2, values["height"] / 2,
                      values["width"], values["height"], max_size)
    except InputError as exc:
        raise InputError("rotation" if exc.field == "transform_matrix" else exc.field, exc.reason) from None


def camera_entry(camera: Camera) -> dict[str, Any]:
    """A Camera as a cameras.json entry (without id and img_name), the inverse of
    `camera_from_entry`. The format has no principal point: readers take the image centre."""
    c2w_cv = camera.c2w @ _GL_FLIP                                        # [4, 4] OpenCV camera axes
    return {"width": camera.width, "height": camera.height, "position": c2w_cv[:3, 3].tolist(),
            "rotation": c2w_cv[:3, :3].tolist(), "fx": camera.fx, "fy": camera.fy}


def write_cameras_json(path: Path, cameras: Sequence[Camera], names: Sequence[str]) -> None:
    """A reference-trainer cameras.json: one entry per camera, ids from 0, img_name its name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, [{"id": i, "img_name": name, **camera_entry(camera)}
                             for i, (camera, name) in enumerate(zip(cameras, names))])


def cameras_from_entries(entries: Any, max_size: int = DEFAULT_MAX_SIZE, file: str = "cameras.json"
                         ) -> list[Camera]:
    """Every camera of a parsed cameras.json, errors naming `file[i].key` (as frames[i].key in the service)."""
    if not isinstance(entries, list) or not entries:
        raise InputError(file, "must be a non-empty list of cameras")
    cameras = []
    for i, entry in enumerate(entries):
        try:
            cameras.append(camera_from_entry(entry, max_size))
        except InputError as exc:
            raise InputError(f"{file}[{i}].{exc.field}", exc.reason) from None
    return cameras


# ----------------------------------------------------------------------------- the output folder

@dataclass
class OutputFolder:
    """What a reference-trainer output folder holds, resolved."""

    ply: Path                                  # the chosen iteration's point_cloud.ply
    iteration: int
    cameras: list[Camera]                      # training cameras (test ones dropped when cfg_args says eval)
    names: list[str]
    background: tuple[float, float, float]


def iterations(folder: Path) -> dict[int, Path]:
    """iteration number -> its point_cloud.ply, for every point_cloud/iteration_N that has one."""
    found = {}
    base = folder / "point_cloud"
    if base.is_dir():
        for sub in base.iterdir():
            match = re.fullmatch(r"iteration_(\d+)", sub.name)
            if match and (sub / "point_cloud.ply").is_file():
                found[int(match.group(1))] = sub / "point_cloud.ply"
    return found


def is_output_folder(path: Path) -> bool:
    return path.is_dir() and (path / "cameras.json").is_file() and bool(iterations(path))


def read_cfg_args(folder: Path) -> InriaArgs:
    """The arguments of cfg_args (a Namespace repr) that the readers use, checked; the
    trainer's defaults when it is absent."""
    path = folder / "cfg_args"
    text = read_text(path, MAX_CONFIG_BYTES) if path.is_file() else ""
    return parse_config(InriaArgs, dict(re.findall(r"(\w+)=('[^']*'|\"[^\"]*\"|[^,()]+)", text)), "cfg_args")


def read_output_folder(folder: str | Path, iteration: int | None = None,
                       max_size: int = DEFAULT_MAX_SIZE) -> OutputFolder:
    """Resolve a reference-trainer output folder: the PLY of `iteration` (default the latest),
    the training cameras of cameras.json and the background."""
    folder = Path(folder)
    found = iterations(folder)
    if not found:
        raise InputError("model", f"{folder} has no point_cloud/iteration_*/point_cloud.ply")
    if iteration is None:
        iteration = max(found)
    elif iteration not in found:
        raise InputError("iteration", f"{folder} has iterations {sorted(found)}, not {iteration}")
    entries = read_json(folder / "cameras.json")
    cameras = cameras_from_entries(entries, max_size)
    names = [str(e.get("img_name", i)) for i, e in enumerate(entries)]
    cfg = read_cfg_args(folder)
    if cfg.eval:                      # the trainer held out every HOLDOUT-th image by name
        order = sorted(range(len(names)), key=lambda i: names[i])
        test = {order[k] for k in range(0, len(order), HOLDOUT)}
        keep = [i for i in range(len(names)) if i not in test] or list(range(len(names)))
        cameras, names = [cameras[i] for i in keep], [names[i] for i in keep]
    background = (1.0, 1.0, 1.0) if cfg.white_background else (0.0, 0.0, 0.0)
    return OutputFolder(found[iteration], iteration, cameras, names, background)


def load_inria(path: str | Path, split: str = "train", *, downscale: float = 1,
               views: int | Sequence[int] | None = None, background: Sequence[float] = (1, 1, 1),
               seed: int | None = None, with_images: bool = True) -> Dataset:
    """The cameras of a reference-trainer output folder as a Dataset (no images: the folder has
    none). "train" is the training cameras, "all" every camera of cameras.json."""
    if with_images:
        raise InputError("data", f"{path} is a 3DGS output folder: it holds cameras but no images; load "
                         "the capture it was trained from")
    folder = read_output_folder(path)
    cameras, names = folder.cameras, folder.names
    if split == "all":
        entries = read_json(Path(path) / "cameras.json")
        cameras, names = cameras_from_entries(entries), [str(e.get("img_name", i)) for i, e in enumerate(entries)]
    elif split != "train":
        raise InputError("split", f"a 3DGS output folder has the splits train and all, not {split!r}")
    return build_dataset(cameras, None, Path(path), split, downscale=downscale, views=views, background=background,
                         seed=seed, near=None, far=None, names=names)


def locate(path: Path, split: str) -> Path | None:
    return path if is_output_folder(path) else None


FORMATS.register(DataFormat("3dgs-output", locate, load_inria, order=50,
                            looks_for="cameras.json with point_cloud/iteration_*"))
POSES.register(PoseConvention("3dgs-output", camera_entry, write_cameras_json,
                              "a reference-trainer cameras.json", file_name="cameras.json"))
