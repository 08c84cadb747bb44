"""COLMAP sparse model files, text (cameras.txt, images.txt, points3D.txt) or binary (.bin),
parsed by hand: every read is checked against the file's end and names the file and the
record, and no C++ code sees the bytes. The service reads COLMAP models inside uploaded
folders, where a reader fed hostile bytes must give a clear error, never take the process
down; pycolmap does only the camera maths (`phd_core.data.undistort`). Widths, heights and
parameters are bounded here, before any maths sees them. `phd_core.data.colmap` turns the
model into the project's cameras.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import InputError
from ..scene.camera import MAX_COORDINATE

# model id -> (name, parameter names); the first parameters are the pinhole ones.
MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
}
MODEL_IDS = {name: model_id for model_id, (name, _) in MODELS.items()}
MAX_SIZE = 100_000         # pixels a side of a COLMAP camera: above any sensor's
_OBSERVATION = np.dtype([("xy", "<f8", 2), ("point3d_id", "<i8")])
_POINT = "q3d3BdQ"     # points3D.bin's record up to its track: id (signed, as observed ids), xyz, rgb, error, length


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass
class ColmapImage:
    image_id: int
    qvec: tuple[float, float, float, float]     # (qw, qx, qy, qz), world-to-camera
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    xys: np.ndarray = field(repr=False)          # [K, 2] observed keypoints, pixels
    point3d_ids: np.ndarray = field(repr=False)  # [K] the SfM point each one is, -1 for none


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]                     # sorted by name
    points: np.ndarray | None                     # [P, 3] float64, or None without points3D
    colors: np.ndarray | None                     # [P, 3] uint8
    point_ids: np.ndarray | None                  # [P] int64


# ----------------------------------------------------------------------------- reading

class _Bytes:
    """Bounded reads from a binary file: running past the end names the file and the record."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, _read(path, binary=True), 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise InputError(self.path.name, f"{self.path} ends early, inside {what}")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        size = dtype.itemsize * count
        if count < 0 or self.pos + size > len(self.data):
            raise InputError(self.path.name, f"{self.path} ends early, inside {what}")
        out = np.frombuffer(self.data, dtype, count, self.pos)
        self.pos += size
        return out

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise InputError(self.path.name, f"{self.path} ends early, inside {what}")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(self.path.name, f"{what}: the image name is not UTF-8") from None


def _read(path: Path, binary: bool = False) -> Any:
    try:
        return path.read_bytes() if binary else path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path.name, f"cannot read {path}: {exc}") from None


def _text_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, words) of every non-comment line; blank lines kept (images.txt needs them)."""
    return [(n, line.split()) for n, line in enumerate(_read(path).splitlines(), 1) if not line.startswith("#")]


def _numbers(words: Sequence[str], kind: type, path: Path, line: int, what: str) -> list:
    try:
        return [kind(w) for w in words]
    except ValueError:
        raise InputError(path.name, f"line {line}: {what} must be numbers, got {' '.join(words)!r}") from None


def _camera(model: str, width: int, height: int, params: Sequence[float], where: str) -> ColmapCamera:
    if model not in MODEL_IDS:
        raise InputError(where, f"unknown camera model {model!r}")
    expected = len(MODELS[MODEL_IDS[model]][1])
    if len(params) != expected:
        raise InputError(where, f"camera model {model} has {expected} parameters, got {len(params)}")
    # Bounded before any maths sees them: pycolmap's undistortion walks the image border.
    if not (0 < width <= MAX_SIZE and 0 < height <= MAX_SIZE):
        raise InputError(where, f"width and height must be 1 to {MAX_SIZE} pixels, got {width}x{height}")
    if not all(math.isfinite(p) for p in params):
        raise InputError(where, f"the parameters must be finite numbers, got {list(params)}")
    return ColmapCamera(model, int(width), int(height), tuple(float(p) for p in params))


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for n, words in _text_lines(path):
        if not words:
            continue
        if len(words) < 4:
            raise InputError(path.name, f"line {n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id, width, height = _numbers([words[0], *words[2:4]], int, path, n, "CAMERA_ID, WIDTH, HEIGHT")
        params = _numbers(words[4:], float, path, n, "PARAMS")
        cameras[camera_id] = _camera(words[1], width, height, params, f"{path.name}: camera {camera_id}")
    return cameras


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    f = _Bytes(path)
    cameras = {}
    (count,) = f.take("Q", "the camera count")
    for i in range(count):
        camera_id, model_id, width, height = f.take("iiQQ", f"camera record {i}")
        if model_id not in MODELS:
            raise InputError(path.name, f"camera {camera_id}: unknown camera model id {model_id}")
        name, params = MODELS[model_id]
        values = f.take("d" * len(params), f"camera {camera_id}'s parameters")
        cameras[camera_id] = _camera(name, width, height, values, f"{path.name}: camera {camera_id}")
    return cameras


def read_images_text(path: Path) -> list[ColmapImage]:
    lines = _text_lines(path)
    # The first line of a record is never blank; its POINTS2D line may be.
    while lines and not lines[-1][1]:
        lines.pop()
    images = []
    i = 0
    while i < len(lines):
        n, words = lines[i]
        if not words:
            i += 1
            continue
        if len(words) < 10:
            raise InputError(path.name, f"line {n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        image_id, camera_id = _numbers([words[0], words[8]], int, path, n, "IMAGE_ID and CAMERA_ID")
        pose = _numbers(words[1:8], float, path, n, "QW QX QY QZ TX TY TZ")
        points = lines[i + 1][1] if i + 1 < len(lines) else []
        if len(points) % 3:
            raise InputError(path.name, f"line {n + 1}: POINTS2D must be triples X Y POINT3D_ID")
        values = np.array(_numbers(points, float, path, n + 1, "POINTS2D"), dtype=np.float64).reshape(-1, 3)
        images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, " ".join(words[9:]),
                                  values[:, :2], values[:, 2].astype(np.int64)))
        i += 2
    return images


def read_images_binary(path: Path) -> list[ColmapImage]:
    f = _Bytes(path)
    images = []
    (count,) = f.take("Q", "the image count")
    for i in range(count):
        record = f.take("i7di", f"image record {i}")
        name = f.name(f"image {record[0]}'s name")
        (num_points,) = f.take("Q", f"image {record[0]}'s keypoint count")
        obs = f.array(_OBSERVATION, num_points, f"image {record[0]}'s keypoints")
        images.append(ColmapImage(record[0], record[1:5], record[5:8], record[8], name,
                                  obs["xy"].copy(), obs["point3d_id"].copy()))
    return images


def read_points_text(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids, xyz, rgb = [], [], []
    for n, words in _text_lines(path):
        if not words:
            continue
        if len(words) < 8 or (len(words) - 8) % 2:
            raise InputError(path.name, f"line {n}: expected POINT3D_ID X Y Z R G B ERROR TRACK[] (pairs)")
        ids.append(_numbers(words[:1], int, path, n, "POINT3D_ID")[0])
        if not -2**63 <= ids[-1] < 2**63:
            raise InputError(path.name, f"line {n}: POINT3D_ID must be a 64-bit integer, got {words[0]}")
        xyz.append(_numbers(words[1:4], float, path, n, "X Y Z"))
        rgb.append([min(max(c, 0), 255) for c in _numbers(words[4:7], int, path, n, "R G B")])
    colours = np.array(rgb, dtype=np.uint8).reshape(-1, 3)
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), colours, np.array(ids, dtype=np.int64)


def read_points_binary(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = _Bytes(path)
    (count,) = f.take("Q", "the point count")
    if count * struct.calcsize("<" + _POINT) > len(f.data) - f.pos:       # before allocating what it declares
        raise InputError(path.name, f"{path} ends early: it declares {count} points, more than its size holds")
    ids, xyz, rgb = np.empty(count, np.int64), np.empty((count, 3)), np.empty((count, 3), np.uint8)
    for i in range(count):
        record = f.take(_POINT, f"point record {i}")
        ids[i], xyz[i], rgb[i] = record[0], record[1:4], record[4:7]
        f.array(np.dtype("<i4"), 2 * record[8], f"point {record[0]}'s track")
    return xyz, rgb, ids


def read_model(model_dir: str | Path, *, with_points: bool = True) -> ColmapModel:
    """Read a COLMAP sparse model folder, binary files preferred over text when both exist."""
    model_dir = Path(model_dir)
    found = model_files(model_dir)
    if found is None:
        raise InputError("data", f"{model_dir} holds no COLMAP model (cameras.bin/.txt with images.bin/.txt)")
    ext = found
    readers = {".bin": (read_cameras_binary, read_images_binary, read_points_binary),
               ".txt": (read_cameras_text, read_images_text, read_points_text)}[ext]
    cameras = readers[0](model_dir / f"cameras{ext}")
    images = sorted(readers[1](model_dir / f"images{ext}"), key=lambda im: im.name)
    if not images:
        raise InputError(f"images{ext}", f"{model_dir / f'images{ext}'} registers no image")
    points = colors = ids = None
    if with_points and (model_dir / f"points3D{ext}").is_file():
        points, colors, ids = readers[2](model_dir / f"points3D{ext}")
        if not (np.abs(points) <= MAX_COORDINATE).all():                  # NaN fails it too
            raise InputError(f"points3D{ext}", f"{model_dir / f'points3D{ext}'} holds a point whose position is not "
                                               f"three numbers within +-{MAX_COORDINATE:g}, as cameras' are")
    return ColmapModel(cameras, images, points, colors, ids)


def model_files(model_dir: Path) -> str | None:
    """'.bin' or '.txt' when `model_dir` holds a COLMAP model in that form, else None."""
    for ext in (".bin", ".txt"):
        if (model_dir / f"cameras{ext}").is_file() and (model_dir / f"images{ext}").is_file():
            return ext
    return None
