"""What every capture format shares: the Dataset, frame selection, transforms JSON, images.

The transforms layouts (Blender, nerfstudio) are a JSON with one frame per image: an OpenGL
camera-to-world `transform_matrix`, intrinsics (Blender: `camera_angle_x`; nerfstudio: `fl_x`, `fl_y`,
`cx`, `cy`, `w`, `h`, at the top level or per frame) and a `file_path` relative to the
JSON's directory (Blender leaves off the `.png`).

Images become float32 RGB in [0, 1], composited on a solid background. Downscaling
averages PREMULTIPLIED colour (rgb * alpha) and alpha, then composites, so object edges
blend with the background exactly as a lower-resolution render would, without dark or
light fringes. An integer factor that divides the image size averages exact pixel blocks;
any other factor uses antialiased bilinear resampling. All images of a dataset must have
one size. Pillow reads 16-bit grayscale PNGs at full depth but reduces 16-bit colour PNGs
to 8 bits; both come out in [0, 1].
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

    `images` and `alphas` are None when loaded with `with_images=False` (PH-Dropout
    calibration needs training poses, not training pixels); `alphas` is also None when the
    image files have no alpha channel.
    """

    cameras: list[Camera]          # at the loaded (downscaled) resolution
    images: torch.Tensor | None    # [V, H, W, 3] float32 in [0, 1], composited on `background`
    alphas: torch.Tensor | None    # [V, H, W] float32 in [0, 1]
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


def build_dataset(cameras: list[Camera], paths: list[Path] | None, root: Path, split: str, *, downscale: float,
                  views: int | Sequence[int] | None, background: Sequence[float], seed: int | None,
                  near: float | None, far: float | None, points: torch.Tensor | None = None,
                  point_colors: torch.Tensor | None = None, names: list[str] | None = None) -> Dataset:
    """A Dataset from full-resolution cameras of a split and their image files (None: no images):
    select views, downscale, read the images as the transforms layouts do."""
    bg = check_color(background, "background")
    _check_downscale(downscale)
    indices = select_views(len(cameras), views, seed=seed)
    full_res = [cameras[i] for i in indices]
    scaled = [camera.scaled(downscale) for camera in full_res] if downscale != 1 else full_res
    images = alphas = None
    if paths is not None:
        for i in indices:
            if not paths[i].is_file():
                raise InputError("images", f"image not found: {paths[i]}")
        images, alphas = _read_images([paths[i] for i in indices], indices, full_res, scaled[0], bg)
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
        height, width = _image_size(first, f"frames[{indices[0]}].file_path")
    full_res = []
    for i in indices:
        try:
            full_res.append(camera_from_frame(frames[i], defaults, width=width, height=height))
        except InputError as exc:
            raise InputError(f"frames[{i}].{exc.field}", exc.reason) from None
    cameras = [camera.scaled(downscale) for camera in full_res] if downscale != 1 else full_res

    images = alphas = None
    if paths is not None:           # with_images
        images, alphas = _read_images(paths, indices, full_res, cameras[0], bg)
    names = [frames[i].get("file_path") for i in indices]
    return Dataset(cameras, images, alphas, indices, base, split, bg, near, far,
                   names=names if all(isinstance(n, str) for n in names) else None)


def _read_images(paths: list[Path], indices: list[int], full_res: list[Camera], target: Camera,
                 background: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Read each view, check its size against its camera, resize premultiplied RGBA to the
    target camera's size and composite on `background`.

    Returns images [V, h, w, 3] and alphas [V, h, w] (None when no file has alpha), float32 in [0, 1].
    """
    size = (full_res[0].height, full_res[0].width)
    bg = torch.tensor(background, dtype=torch.float32)
    images = torch.empty(len(paths), target.height, target.width, 3)
    alphas = torch.empty(len(paths), target.height, target.width)
    has_alpha = False
    for v, (path, i, camera) in enumerate(zip(paths, indices, full_res)):  # one view at a time: low peak memory
        if (camera.height, camera.width) != size:
            raise InputError(f"frames[{i}]", f"size {camera.width}x{camera.height} differs from frame "
                             f"{indices[0]}'s {size[1]}x{size[0]}: all images of a dataset must have one size")
        rgba, file_alpha = _read_rgba(path, f"frames[{i}].file_path")
        if rgba.shape[:2] != size:
            raise InputError(f"frames[{i}]", f"image {path} is {rgba.shape[1]}x{rgba.shape[0]}, expected "
                             f"{size[1]}x{size[0]} (the JSON's w/h, else the size of frame {indices[0]}'s image)")
        has_alpha |= file_alpha
        rgba_t = torch.from_numpy(rgba)                                                        # [H, W, 4]
        premult = torch.cat([rgba_t[..., :3] * rgba_t[..., 3:], rgba_t[..., 3:]], dim=-1)      # [H, W, 4]
        premult = _resize(premult.permute(2, 0, 1)[None], target.height, target.width)[0].permute(1, 2, 0)
        alpha = premult[..., 3:].clamp(0, 1)                                                   # [h, w, 1]
        images[v] = (premult[..., :3] + bg * (1 - alpha)).clamp(0, 1)
        alphas[v] = alpha[..., 0]
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


def _image_size(path: Path, field: str) -> tuple[int, int]:
    """(height, width) of an image file."""
    try:
        shape = iio.improps(path, plugin="pillow").shape
    except Exception as exc:  # any decoder failure means this file is not a usable image
        raise InputError(field, f"cannot read image {path} with Pillow: {str(exc).splitlines()[0]}") from None
    return int(shape[0]), int(shape[1])


def _resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """[1, C, H, W] -> [1, C, height, width]: exact block means when the size divides
    evenly, antialiased bilinear otherwise (both are non-negative weightings, so no overshoot)."""
    in_h, in_w = x.shape[-2:]
    if (in_h, in_w) == (height, width):
        return x
    if in_h % height == 0 and in_w % width == 0:
        return F.interpolate(x, size=(height, width), mode="area")
    return F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
