"""LLFF captures: poses_bounds.npy with the images folder beside it (forward-facing scenes).

poses_bounds.npy is an [N, 17] float array, one row per image in the order of the sorted
image names: a 3x5 matrix flattened row by row, then the near and far depth bounds of the
scene in that view. The 3x5 matrix is [R | t | hwf]: t is the camera centre in world
coordinates, the columns of R are the camera's axes in the LLFF convention (down, right,
backwards), and hwf holds the image height, width and focal length in pixels of the images
the poses were made for. The project's `Camera` is OpenGL (right, up, backwards), so its
rotation is [R[:, 1], -R[:, 0], R[:, 2]]; the principal point is the image centre. Images
whose size differs from hwf (a downscaled images folder) get intrinsics scaled to match.

poses_bounds.npy has no lens distortion: LLFF's imgs2poses writes it from a COLMAP model and
drops the model's distortion, so distorted photos would be trained on as pinhole ones. When
the COLMAP model that lies beside it (sparse/0) has distortion, loading warns and names the
fix: give the capture folder itself, read as COLMAP, which undistorts the photos.

near/far of the dataset: the smallest near bound and the largest far bound over all views.
Splits as COLMAP: every 8th image is "test", the rest "train", "all" is every image.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..errors import InputError, ModelWarning
from ..scene import Camera
from .colmap import distorted_models
from .formats import FORMATS, DataFormat
from .frames import Dataset, Photo, build_dataset, holdout_split, image_size

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
FILE = "poses_bounds.npy"


def read_poses_bounds(path: Path) -> np.ndarray:
    """[N, 17] float64 rows of a poses_bounds.npy, checked (never unpickles)."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(FILE, f"cannot read {path} as a numpy array: {str(exc).splitlines()[0]}") from None
    if array.ndim != 2 or array.shape[1] != 17 or len(array) == 0 or not np.issubdtype(array.dtype, np.number):
        raise InputError(FILE, f"{path} must be a numeric [N, 17] array (3x5 pose + near, far), got "
                         f"{list(array.shape)} of {array.dtype}")
    array = array.astype(np.float64)
    bad = np.argwhere(~np.isfinite(array))
    if len(bad):
        raise InputError(f"{FILE}[{bad[0][0]}]", "contains NaN or infinite values")
    return array


def cameras_from_poses_bounds(rows: np.ndarray) -> tuple[list[Camera], np.ndarray]:
    """Cameras (at hwf's size) and bounds [N, 2] of poses_bounds rows [N, 17]."""
    cameras = []
    for i, row in enumerate(rows):
        pose = row[:15].reshape(3, 5)
        height, width, focal = pose[:, 4]
        if height <= 0 or width <= 0 or height != int(height) or width != int(width):
            raise InputError(f"{FILE}[{i}].hwf", f"image size must be positive whole pixels, got {width} x {height}")
        down, right, back = pose[:, 0], pose[:, 1], pose[:, 2]
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.from_numpy(np.stack([right, -down, back], axis=1))
        c2w[:3, 3] = torch.from_numpy(pose[:, 3])
        try:
            cameras.append(Camera(c2w, float(focal), float(focal), width / 2, height / 2, int(width), int(height)))
        except InputError as exc:
            raise InputError(f"{FILE}[{i}].{'pose' if exc.field == 'transform_matrix' else exc.field}",
                             exc.reason) from None
    bounds = rows[:, 15:17]
    bad = np.argwhere(~((bounds[:, 0] > 0) & (bounds[:, 1] > bounds[:, 0])))
    if len(bad):
        raise InputError(f"{FILE}[{bad[0][0]}].bounds", f"need 0 < near < far, got {bounds[bad[0][0]].tolist()}")
    return cameras, bounds


def image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def load_llff(path: str | Path, split: str = "train", *, downscale: float = 1,
              views: int | Sequence[int] | None = None, background: Sequence[float] = (1, 1, 1),
              seed: int | None = None, with_images: bool = True) -> Dataset:
    """Load an LLFF scene folder (poses_bounds.npy and images/) or the .npy itself."""
    path = Path(path)
    npy = path if path.is_file() else path / FILE
    root = npy.parent
    cameras, bounds = cameras_from_poses_bounds(read_poses_bounds(npy))
    folder = root / "images"
    paths = image_files(folder) if folder.is_dir() else None
    if paths is not None and len(paths) != len(cameras):
        raise InputError("images", f"{folder} holds {len(paths)} images but {FILE} has {len(cameras)} poses")
    if with_images and paths is None:
        raise InputError("images", f"no images folder beside {npy}")
    if paths:
        height, width = image_size(paths[0], "images")
        if (height, width) != (cameras[0].height, cameras[0].width):
            cameras = [c.resized(width, height) for c in cameras]
    warn_if_distorted_beside(npy)
    chosen = holdout_split(len(cameras), split)
    photos = None
    if with_images and paths is not None:           # with_images and no folder raised above
        size_from = f"the size of {paths[0].name}, the first image"
        photos = [Photo(paths[i], (cameras[i].height, cameras[i].width), f"images/{paths[i].name}", size_from)
                  for i in chosen]
    return build_dataset([cameras[i] for i in chosen], photos, root, split, downscale=downscale, views=views,
                         background=background, seed=seed,
                         near=float(bounds[:, 0].min()), far=float(bounds[:, 1].max()),
                         names=None if paths is None else [paths[i].name for i in chosen])


def warn_if_distorted_beside(npy: Path) -> None:
    """Warn (ModelWarning) when the COLMAP model beside poses_bounds.npy has lens distortion (module docstring)."""
    models = distorted_models(npy.parent)
    if models:
        warnings.warn(f"{npy}: the COLMAP model beside it has lens distortion ({', '.join(models)}), which "
                      f"{FILE} cannot describe: its photos would be trained on as if taken by pinhole cameras. "
                      f"Give the capture folder {npy.parent} instead: read as COLMAP, its photos are undistorted",
                      ModelWarning, stacklevel=3)


def locate(path: Path, split: str) -> Path | None:
    if path.is_file():
        return path if path.name.endswith(".npy") else None
    return path / FILE if (path / FILE).is_file() else None


FORMATS.register(DataFormat("llff", locate, load_llff, order=40, looks_for=FILE))
