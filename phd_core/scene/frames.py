"""Cameras from Blender / nerfstudio frames: a transforms.json, its parsed dict, or a list of
frames. The inverse is `Camera.to_frame()`."""

from __future__ import annotations

import math
from typing import Any

import torch

from ..errors import InputError
from .camera import DEFAULT_MAX_SIZE, Camera, validate_pose

MIN_FIELD_OF_VIEW = 1e-6   # radians; smaller angles give focal lengths past any float


def _number(frame: dict, key: str) -> float:
    """A finite number (NaN, +-inf and 1e309, which JSON parses as inf, are refused)."""
    value = frame[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(key, f"must be a number, got {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # an int too large for a float
        raise InputError(key, "must be a finite number, got an integer too large for a float") from None
    if not math.isfinite(value):
        raise InputError(key, f"must be a finite number, got {value}")
    return value


def _focal_from_angle(frame: dict, key: str, size: int) -> float:
    """The focal length in pixels of a field of view in radians (a tiny angle is refused, not divided by)."""
    angle = _number(frame, key)
    if not MIN_FIELD_OF_VIEW <= angle < math.pi:
        raise InputError(key, f"field of view must lie in [{MIN_FIELD_OF_VIEW:g}, pi) radians, got {angle}")
    return 0.5 * size / math.tan(0.5 * angle)


def _size(value: float, key: str, max_size: int) -> int:
    """An image side in whole pixels within [1, max_size] (checked before int() sees it)."""
    if value != int(value) or not 1 <= value <= max_size:
        raise InputError(key, f"image size must be a whole number of pixels in [1, {max_size}], got {value}")
    return int(value)


def _matrix(value: Any) -> torch.Tensor:
    try:
        c2w = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError("transform_matrix", f"must be a 4x4 list of numbers ({exc})") from None
    validate_pose(c2w)
    if c2w.shape[0] == 3:
        c2w = torch.cat([c2w, torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64)])
    return c2w


def found_keys(entry: dict, most: int = 12) -> str:
    """The first keys of a JSON object, quoted, for a message about the one it lacks: a typo
    ("frame", "transfrom_matrix") is seen at once."""
    keys = [f"'{k}'" for k in list(entry)[:most]]
    return ", ".join(keys) + (", ..." if len(entry) > most else "") if keys else "none"


def camera_from_frame(frame: dict, defaults: dict | None = None, *, width: int | None = None,
                      height: int | None = None, max_size: int = DEFAULT_MAX_SIZE) -> Camera:
    """Build a camera from a Blender or nerfstudio frame.

    Intrinsics are looked up in the frame first, then in `defaults` (the top level of a
    transforms.json). Blender style gives `camera_angle_x` (horizontal field of view) and
    needs the image size from `w`/`h` or the `width`/`height` arguments; nerfstudio style
    gives `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`.
    """
    if not isinstance(frame, dict):
        raise InputError("frame", f"must be an object, got {type(frame).__name__}")
    if "transform_matrix" not in frame:
        raise InputError("transform_matrix", f"missing from the frame (its keys: {found_keys(frame)})")
    merged = {**(defaults or {}), **frame}
    c2w = _matrix(merged["transform_matrix"])
    w = _number(merged, "w") if "w" in merged else width
    h = _number(merged, "h") if "h" in merged else height
    if w is None or h is None:
        raise InputError("w", "image size unknown: give w and h (or load with the images)")
    w, h = _size(w, "w", max_size), _size(h, "h", max_size)
    if "fl_x" in merged:
        fx = _number(merged, "fl_x")
        fy = _number(merged, "fl_y") if "fl_y" in merged else fx
    elif "camera_angle_x" in merged:
        fx = _focal_from_angle(merged, "camera_angle_x", w)
        fy = _focal_from_angle(merged, "camera_angle_y", h) if "camera_angle_y" in merged else fx
    else:
        raise InputError("fl_x", "no focal length: give fl_x (nerfstudio) or camera_angle_x (Blender)")
    cx = _number(merged, "cx") if "cx" in merged else w / 2
    cy = _number(merged, "cy") if "cy" in merged else h / 2
    return Camera(c2w, fx, fy, cx, cy, w, h, max_size)


def cameras_from_json(source: dict | list, *, width: int | None = None,
                      height: int | None = None, max_size: int = DEFAULT_MAX_SIZE) -> list[Camera]:
    """Cameras from parsed JSON: a transforms.json object or a plain list of frames.

    A string is refused, never opened: files are read by `phd_core.data.load_cameras` (the CLI's)."""
    if isinstance(source, list):
        frames, defaults = source, {}
    elif isinstance(source, dict) and isinstance(source.get("frames"), list):
        frames, defaults = source["frames"], {k: v for k, v in source.items() if k != "frames"}
    elif isinstance(source, dict):
        raise InputError("frames", f"no 'frames' list (its keys: {found_keys(source)}): expected a transforms.json "
                                   "with 'frames', a cameras.json or a list of frames")
    else:
        raise InputError("frames", "expected a list of frames or an object with a 'frames' list, got "
                                   f"{type(source).__name__}")
    if not frames:
        raise InputError("frames", "no frames given")
    cameras = []
    for i, frame in enumerate(frames):
        try:
            cameras.append(camera_from_frame(frame, defaults, width=width, height=height, max_size=max_size))
        except InputError as exc:
            raise InputError(f"frames[{i}].{exc.field}", exc.reason) from None
    return cameras
