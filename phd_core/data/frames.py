"""What every capture format shares: the Dataset, frame selection, transforms JSON, images.

The transforms layouts (Blender, nerfstudio) are a JSON with one frame per image: an OpenGL
camera-to-world `transform_matrix`, intrinsics (Blender: `camera_angle_x`; nerfstudio: `fl_x`, `fl_y`,
`cx`, `cy`, `w`, `h`, at the top level or per frame) and a `file_path` relative to the
JSON's directory (Blender leaves off the `.png`).

Images become float32 RGB in [0, 1], composited on a solid background. Downscaling
averages PREMULTIPLIED colour (rgb * alpha) and alpha, then composites, so object edges
blend with the background exactly as a lower-resolution render would, without dark or
light fringes. An integer factor that divides the image size averages exact pixel blocks;
any other factor uses antialiased bilinear resampling. Each view has its own size (its
camera's): `Dataset.images` is a list of per-view tensors, one size or several (portrait and
landscape photos, per-image cameras after undistortion). Pillow reads 16-bit grayscale PNGs
at full depth but reduces 16-bit colour PNGs to 8 bits; both come out in [0, 1].
"""

from __future__ import annotations

import math
import operator
import os
import random
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError, check_color, shown
from ..io.foreign import read_json
from ..scene import Camera, camera_from_frame

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")  # OPENCV only with zero distortion


@dataclass
class Dataset:
    """Cameras and (optionally) images of the selected frames of one split.

    `images` and `alphas` hold one tensor per view, each at its camera's size (views may
    differ in size); `torch.stack(images)` gives [V, H, W, 3] when they do not. Both are None
    when loaded with `with_images=False` (PH-Dropout calibration needs training poses, not
    training pixels); `alphas` is also None when the image files have no alpha channel.
    """

    cameras: list[Camera]                 # at the loaded (downscaled) resolution
    images: list[torch.Tensor] | None     # per view [H_v, W_v, 3] float32 in [0, 1], composited on `background`
    alphas: list[torch.Tensor] | None     # per view [H_v, W_v] float32 in [0, 1]
    indices: list[int]             # which frames of the split these are
    root: Path
    split: str
    background: tuple[float, float, float]
    near: float | None
    far: float | None
    points: torch.Tensor | None = None        # [P, 3] float64 SfM points (COLMAP), else None
    point_colors: torch.Tensor | None = None  # [P, 3] float32 in [0, 1]
    names: list[str] | None = None            # image names of the loaded frames, when the format has them


def select_views(total: int, views: int | Sequence[int] | None, *, seed: int | None = None) -> list[int]:
    """Frame indices to load out of `total`.

    None: all frames. An int n: n evenly spaced frames, index round(i * total / n) with
    halves rounded up, or n distinct random frames (sorted) when `seed` is given (the
    seed matters only here). A sequence: those frames in the given order, each in range
    and none twice.
    """
    if views is None:
        return list(range(total))
    if isinstance(views, (np.ndarray, torch.Tensor)):
        views = views.tolist()
    if isinstance(views, (bool, str)):
        raise InputError("views", f"must be a count or a list of frame indices, got {views!r}")
    if isinstance(views, Sequence):
        return _validated_indices(views, total)
    try:
        count = operator.index(views)
    except TypeError:
        raise InputError("views", f"must be a count or a list of frame indices, got {views!r}") from None
    if not 1 <= count <= total:
        raise InputError("views", f"count must be between 1 and {total} (the split's frames), got {count}")
    if seed is not None:
        return sorted(random.Random(seed).sample(range(total), count))
    # Integer form of floor(i * total / count + 0.5): exact, and strictly increasing since total >= count.
    return [(2 * i * total + count) // (2 * count) for i in range(count)]


def _validated_indices(views: Sequence[Any], total: int) -> list[int]:
    indices = []
    for value in views:
        if isinstance(value, bool):
            raise InputError("views", f"frame indices must be integers, got {value!r}")
        try:
            index = operator.index(value)
        except TypeError:
            raise InputError("views", f"frame indices must be integers, got {value!r}") from None
        if not 0 <= index < total:
            raise InputError("views", f"frame index {index} is out of range [0, {total})")
        indices.append(index)
    if not indices:
        raise InputError("views", "the list of frame indices is empty")
    if len(set(indices)) != len(indices):
        raise InputError("views", "frame indices must be unique")
    return indices


HOLDOUT = 8   # LLFF-style evaluation: every 8th image (sorted by name) is a test view


def holdout_split(total: int, split: str) -> list[int]:
    """Frames of a split of a capture with one image list (COLMAP, LLFF): "test" is every
    HOLDOUT-th frame from 0, "train" the rest, "all" every frame."""
    check_split(split)
    chosen = {"all": range(total), "test": range(0, total, HOLDOUT),
              "train": [i for i in range(total) if i % HOLDOUT]}.get(split)
    if chosen is None:
        raise InputError("split", f"this capture has the splits train, test (every {HOLDOUT}th image) and all, "
                         f"not {split!r}")
    if not chosen:
        raise InputError("split", f"split {split!r} of a {total}-image capture is empty")
    return list(chosen)


def build_dataset(cameras: list[Camera], photos: list[Photo] | None, root: Path, split: str, *, downscale: float,
                  views: int | Sequence[int] | None, background: Sequence[float], seed: int | None,
                  near: float | None, far: float | None, points: torch.Tensor | None = None,
                  point_colors: torch.Tensor | None = None, names: list[str] | None = None) -> Dataset:
    """A Dataset from full-resolution cameras of a split and their photos (None: no images):
    select views, downscale, read the images as the transforms layouts do."""
    bg = check_color(background, "background")
    _check_downscale(downscale)
    indices = select_views(len(cameras), views, seed=seed)
    full_res = [cameras[i] for i in indices]
    scaled = [camera.scaled(downscale) for camera in full_res] if downscale != 1 else full_res
    images = alphas = None
    if photos is not None:
        for i in indices:
            if not photos[i].path.is_file():
                raise InputError(photos[i].file_field, f"image not found: {photos[i].path}")
        images, alphas = _read_images([photos[i] for i in indices], scaled, bg)
    return Dataset(scaled, images, alphas, indices, root, split, bg, near, far, points, point_colors,
                   None if names is None else [names[i] for i in indices])


def check_split(split: str) -> None:
    if not isinstance(split, str) or not re.fullmatch(r"[A-Za-z0-9_-]+", split):
        raise InputError("split", f"must be a name of letters, digits, '_' or '-', got {split!r}")


def load_frames(json_path: Path, split: str, *, default_near_far: tuple[float | None, float | None],
          downscale: float, views: int | Sequence[int] | None, background: Sequence[float],
          seed: int | None, with_images: bool) -> Dataset:
    """Shared loader of the transforms layouts: select frames, build cameras, read and downscale images."""
    bg = check_color(background, "background")
    _check_downscale(downscale)
    frames, defaults = read_transforms(json_path)
    near, far = _near_far(defaults, default_near_far)
    indices = select_views(len(frames), views, seed=seed)
    base = json_path.parent
    for i in indices:
        if not isinstance(frames[i], dict):
            raise InputError(f"frames[{i}]", f"must be an object, got {type(frames[i]).__name__}")
        _check_pinhole(frames[i], defaults, f"frames[{i}]")
    paths = [_image_path(base, frames[i], i) for i in indices] if with_images else None

    # Blender JSONs carry no image size: take it from the first image.
    height = width = None
    if with_images or any(not {"w", "h"} <= (defaults.keys() | frames[i].keys()) for i in indices):
        first = paths[0] if paths else _image_path(base, frames[indices[0]], indices[0])
        height, width = image_size(first, f"frames[{indices[0]}].file_path")
    full_res = []
    for i in indices:
        try:
            full_res.append(camera_from_frame(frames[i], defaults, width=width, height=height))
        except InputError as exc:
            raise InputError(f"frames[{i}].{exc.field}", exc.reason) from None
    cameras = [camera.scaled(downscale) for camera in full_res] if downscale != 1 else full_res

    images = alphas = None
    if paths is not None:           # with_images
        size_from = f"the JSON's w/h, else the size of frame {indices[0]}'s image"
        photos = [Photo(path, (camera.height, camera.width), f"frames[{i}]", size_from, f"frames[{i}].file_path")
                  for path, i, camera in zip(paths, indices, full_res)]
        images, alphas = _read_images(photos, cameras, bg)
    names = [frames[i].get("file_path") for i in indices]
    return Dataset(cameras, images, alphas, indices, base, split, bg, near, far,
                   names=names if all(isinstance(n, str) for n in names) else None)


@dataclass(frozen=True)
class Photo:
    """One view's image file and the size its camera was made for: what `_read_images` reads.

    A format whose pixels need more than reading and resizing (COLMAP's distorted cameras:
    `phd_core.data.undistort`) subclasses it and overrides `premultiplied`.
    """

    path: Path
    size: tuple[int, int]          # (height, width) the file must have
    field: str                     # names the view in errors ("frames[3]", "images/a.jpg")
    size_from: str                 # where `size` came from, for the error when the file differs
    file_field: str = ""           # names the file in read errors (default: `field`)

    def __post_init__(self) -> None:
        if not self.file_field:
            object.__setattr__(self, "file_field", self.field)

    def read(self) -> tuple[np.ndarray, bool]:
        """[H, W, 4] straight RGBA float32 in [0, 1] and whether the file has alpha; a file of
        another size than `size` is refused."""
        rgba, has_alpha = _read_rgba(self.path, self.file_field)
        if rgba.shape[:2] != self.size:
            raise InputError(self.field, f"image {self.path} is {rgba.shape[1]}x{rgba.shape[0]}, expected "
                             f"{self.size[1]}x{self.size[0]} ({self.size_from})")
        return rgba, has_alpha

    def premultiplied(self, height: int, width: int) -> tuple[torch.Tensor, bool]:
        """Premultiplied RGBA [height, width, 4] (resized from the file's size) and whether the file has alpha."""
        rgba, has_alpha = self.read()
        return resize_image(premultiply(torch.from_numpy(rgba)), height, width), has_alpha


def premultiply(rgba: torch.Tensor) -> torch.Tensor:
    """Straight RGBA [H, W, 4] -> premultiplied RGBA [H, W, 4] (colour times alpha)."""
    return torch.cat([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], dim=-1)


def _read_images(photos: list[Photo], targets: list[Camera], background: tuple[float, float, float]
                 ) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
    """Each view's photo, resized (premultiplied) to its target camera's size and composited on `background`.

    Returns images, per view [h, w, 3], and alphas, per view [h, w] (None when no file has
    alpha), float32 in [0, 1].
    """
    bg = torch.tensor(background, dtype=torch.float32)
    images, alphas, has_alpha = [], [], False
    for photo, target in zip(photos, targets):          # one view at a time: low peak memory
        premult, file_alpha = photo.premultiplied(target.height, target.width)              # [h, w, 4]
        has_alpha |= file_alpha
        alpha = premult[..., 3:].clamp(0, 1)                                                   # [h, w, 1]
        images.append((premult[..., :3] + bg * (1 - alpha)).clamp(0, 1).contiguous())
        alphas.append(alpha[..., 0].contiguous())
    return images, (alphas if has_alpha else None)


def read_transforms(json_path: Path) -> tuple[list, dict]:
    """(frames, top-level defaults) of a transforms JSON."""
    data = read_json(json_path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise InputError(json_path.name, "must be an object with a non-empty 'frames' list")
    return data["frames"], {k: v for k, v in data.items() if k != "frames"}


def count_frames(json_path: Path, split: str) -> int:
    """The frames of a transforms JSON, counted without loading them (a format's `count`)."""
    return len(read_transforms(json_path)[0])


def _near_far(defaults: dict, fallback: tuple[float | None, float | None]) -> tuple[float | None, float | None]:
    near, far = defaults.get("near", fallback[0]), defaults.get("far", fallback[1])
    for name, value in (("near", near), ("far", far)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or not math.isfinite(value) or value < 0):
            raise InputError(name, f"must be a non-negative finite number, got {shown(value)}")
    if near is not None and far is not None and not near < far:
        raise InputError("far", f"must exceed near ({near}), got {far}")
    return (None if near is None else float(near)), (None if far is None else float(far))


def _check_pinhole(frame: dict, defaults: dict, field: str) -> None:
    """Reject lens models we cannot render: we would silently misplace every pixel."""
    merged = {**defaults, **frame}
    model = merged.get("camera_model", "PINHOLE")
    if model not in _PINHOLE_MODELS:
        raise InputError(f"{field}.camera_model", f"only pinhole cameras are supported, got {shown(model)}")
    for key in _DISTORTION_KEYS:
        if merged.get(key, 0) != 0:
            raise InputError(f"{field}.{key}", "lens distortion is not supported: undistort the images first")


def _check_downscale(downscale: float) -> None:
    if isinstance(downscale, bool) or not isinstance(downscale, (int, float)) \
            or not math.isfinite(downscale) or downscale <= 0:
        raise InputError("downscale", f"must be a positive number, got {downscale!r}")


def _image_path(base: Path, frame: dict, i: int) -> Path:
    """The image file of frame i: `file_path` under `base`, as given or with `.png` added."""
    field = f"frames[{i}].file_path"
    file_path = frame.get("file_path")
    if not isinstance(file_path, str) or not file_path:
        raise InputError(field, "missing or not a string")
    base = Path(os.path.normpath(base))
    path = Path(os.path.normpath(base / file_path))
    if not path.is_relative_to(base):
        raise InputError(field, f"{file_path} points outside the dataset directory {base}")
    for candidate in (path, path.with_name(path.name + ".png")):
        if candidate.is_file():
            return candidate
    raise InputError(field, f"image not found: {path} (nor with .png added)")


def _read_rgba(path: Path, field: str) -> tuple[np.ndarray, bool]:
    """[H, W, 4] float32 straight RGBA in [0, 1] (alpha 1 when absent), and whether the file had alpha."""
    try:
        pixels = iio.imread(path, plugin="pillow")
    except Exception as exc:  # any decoder failure means this file is not a usable image
        raise InputError(field, f"cannot read image {path} with Pillow: {str(exc).splitlines()[0]}") from None
    return rgba_from_pixels(pixels, path, field)


def rgba_from_pixels(pixels: np.ndarray, path: Path, field: str) -> tuple[np.ndarray, bool]:
    """A decoded image ([H, W] or [H, W, C], integer or float) -> [H, W, 4] float32 straight
    RGBA in [0, 1] (alpha 1 when absent), and whether it had alpha."""
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[-1] not in (1, 2, 3, 4):
        raise InputError(field, f"{path} is not a single grey/RGB(A) image (array shape {list(pixels.shape)})")
    if np.issubdtype(pixels.dtype, np.integer):
        values = pixels.astype(np.float32) / np.iinfo(pixels.dtype).max  # 8 bit: 255, 16 bit: 65535
    elif np.issubdtype(pixels.dtype, np.floating):
        values = pixels.astype(np.float32)
    else:
        raise InputError(field, f"{path} has unsupported pixel type {pixels.dtype}")
    channels = values.shape[-1]
    has_alpha = channels in (2, 4)
    color = values[..., :3] if channels >= 3 else np.repeat(values[..., :1], 3, axis=-1)
    alpha = values[..., -1:] if has_alpha else np.ones_like(values[..., :1])
    return np.concatenate([color, alpha], axis=-1), has_alpha


def image_size(path: Path, field: str) -> tuple[int, int]:
    """(height, width) of an image file, from its header (no pixels decoded)."""
    try:
        shape = iio.improps(path, plugin="pillow").shape
    except Exception as exc:  # any decoder failure means this file is not a usable image
        raise InputError(field, f"cannot read image {path} with Pillow: {str(exc).splitlines()[0]}") from None
    return int(shape[0]), int(shape[1])


def resize_image(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """[H, W, C] -> [height, width, C]: exact block means when the size divides evenly,
    antialiased bilinear otherwise (both are non-negative weightings, so no overshoot)."""
    in_h, in_w = image.shape[:2]
    if (in_h, in_w) == (height, width):
        return image
    x = image.permute(2, 0, 1)[None]                                                     # [1, C, H, W]
    if in_h % height == 0 and in_w % width == 0:
        x = F.interpolate(x, size=(height, width), mode="area")
    else:
        x = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return x[0].permute(1, 2, 0)
