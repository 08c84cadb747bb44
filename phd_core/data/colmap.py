"""COLMAP sparse models, text (cameras.txt, images.txt, points3D.txt) or binary (.bin), with
the images folder beside them: the layout the reference 3DGS trainer reads
(`scene/images/`, `scene/sparse/0/`).

Convention: images.{txt,bin} store the WORLD-TO-CAMERA rotation as a quaternion (qw, qx, qy,
qz) and the translation t, camera axes OpenCV (x right, y down, z forward); a world point X
lands at R X + t. The project's `Camera` is camera-to-world OpenGL, so
c2w = [R^T | -R^T t] @ diag(1, -1, -1, 1). COLMAP puts the centre of the top-left pixel at
(0.5, 0.5), as `Camera` does, so cx, cy carry over unchanged.

Camera models: SIMPLE_PINHOLE and PINHOLE; the radial and OPENCV models only when every
distortion coefficient is exactly 0. Anything else (a distorted or fisheye model) is
refused with the camera model named: undistort first (`colmap image_undistorter`).

Splits, as LLFF-style evaluation does: images sorted by name, every 8th (0, 8, 16, ...) is
"test", the rest "train"; "all" is every image. points3D gives the SfM points and their
colours (`Dataset.points`), which the 3DGS trainer starts from.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..io import write_bytes_atomic
from ..scene import Camera
from ..scene.camera import MAX_COORDINATE
from ..scene.rotations import quaternion_to_rotation, rotation_to_quaternion
from .formats import FORMATS, DataFormat
from .frames import Dataset, build_dataset, holdout_split
from .poses import POSES, PoseConvention

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
# Models that are a pinhole when their distortion coefficients are all zero (fisheyes never are).
PINHOLE_WHEN_UNDISTORTED = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}
_GL_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
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
    found = _model_files(model_dir)
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


def _model_files(model_dir: Path) -> str | None:
    """'.bin' or '.txt' when `model_dir` holds a COLMAP model in that form, else None."""
    for ext in (".bin", ".txt"):
        if (model_dir / f"cameras{ext}").is_file() and (model_dir / f"images{ext}").is_file():
            return ext
    return None


# ----------------------------------------------------------------------------- conversion

def qvec_to_rotation(qvec: Sequence[float]) -> torch.Tensor:
    """Unit quaternion (w, x, y, z) -> rotation matrix [3, 3] float64 (normalised first)."""
    return quaternion_to_rotation(torch.tensor(qvec, dtype=torch.float64)[None])[0]


def rotation_to_qvec(rotation: torch.Tensor) -> list[float]:
    """Rotation matrix [3, 3] -> unit quaternion [w, x, y, z] with w >= 0 (q and -q are one
    rotation), the inverse of `qvec_to_rotation`."""
    q = rotation_to_quaternion(rotation)
    return (q if q[0] >= 0 else -q).tolist()


def colmap_pose(camera: Camera) -> dict[str, Any]:
    """A camera as COLMAP writes it: world-to-camera qvec [w, x, y, z] and tvec [3] (OpenCV
    axes), and its PINHOLE camera (params fx, fy, cx, cy)."""
    w2c = camera.world_to_camera()                                       # [4, 4] OpenCV
    return {"qvec": rotation_to_qvec(w2c[:3, :3]), "tvec": w2c[:3, 3].tolist(),
            "camera": {"model": "PINHOLE", "width": camera.width, "height": camera.height,
                       "params": [camera.fx, camera.fy, camera.cx, camera.cy]}}


def write_colmap_text(folder: Path, cameras: Sequence[Camera], names: Sequence[str]) -> None:
    """A COLMAP text model in `folder`: one PINHOLE camera per image (ids from 1), the images'
    poses with no keypoints, and no points; numbers in full precision (repr)."""
    camera_lines, image_lines = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"], [
        "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (camera, name) in enumerate(zip(cameras, names), start=1):
        if not name.strip() or "\n" in name:
            raise InputError("export", f"image name {name!r} cannot stand in images.txt")
        pose = colmap_pose(camera)
        numbers = " ".join(repr(float(v)) for v in pose["camera"]["params"])
        camera_lines.append(f"{i} PINHOLE {camera.width} {camera.height} {numbers}")
        image_lines += [f"{i} " + " ".join(repr(float(v)) for v in pose["qvec"] + pose["tvec"]) + f" {i} {name}", ""]
    folder.mkdir(parents=True, exist_ok=True)
    for file, lines in (("cameras.txt", camera_lines), ("images.txt", image_lines),
                        ("points3D.txt", ["# POINT3D_ID X Y Z R G B ERROR TRACK[]"])):
        write_bytes_atomic(folder / file, ("\n".join(lines) + "\n").encode())


def pinhole(camera: ColmapCamera, where: str) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pinhole-type camera; distortion refused with the model named."""
    names = MODELS[MODEL_IDS[camera.model]][1]
    values = dict(zip(names, camera.params))
    if camera.model not in PINHOLE_WHEN_UNDISTORTED or any(values[k] != 0 for k in names[3 if "f" in values else 4:]):
        raise InputError(where, f"camera model {camera.model} with lens distortion is not supported: undistort the "
                         "images first (colmap image_undistorter writes a PINHOLE model)")
    fx = values.get("fx", values.get("f"))
    assert fx is not None                  # every pinhole-type model has f or fx
    return fx, values.get("fy", fx), values["cx"], values["cy"]


def image_camera(model: ColmapModel, image: ColmapImage, file: str) -> Camera:
    """The project's Camera of one registered image."""
    where = f"{file}: image {image.name!r}"
    if image.camera_id not in model.cameras:
        raise InputError(where, f"camera_id {image.camera_id} is not in the cameras file")
    colmap_camera = model.cameras[image.camera_id]
    fx, fy, cx, cy = pinhole(colmap_camera, f"{file.replace('images', 'cameras')}: camera {image.camera_id}")
    if not np.isfinite(image.qvec).all() or not np.isfinite(image.tvec).all() or not any(image.qvec):
        raise InputError(where, "the pose (quaternion, translation) must be finite, with a non-zero quaternion")
    rotation = qvec_to_rotation(image.qvec)                              # world -> camera
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = -rotation.T @ torch.tensor(image.tvec, dtype=torch.float64)
    try:
        return Camera(c2w @ _GL_FLIP, fx, fy, cx, cy, colmap_camera.width, colmap_camera.height)
    except InputError as exc:
        raise InputError(f"{where}.{exc.field}", exc.reason) from None


# ----------------------------------------------------------------------------- the format

def find_model(path: Path) -> Path | None:
    """The COLMAP model folder of a scene: `path` itself, `path/sparse/0` or `path/sparse`."""
    for candidate in (path, path / "sparse" / "0", path / "sparse"):
        if candidate.is_dir() and _model_files(candidate) is not None:
            return candidate
    return None


def images_dir(model_dir: Path) -> Path:
    """The images folder beside the model: scene/images for scene/sparse/0 (or scene/sparse)."""
    for base in (model_dir, model_dir.parent, model_dir.parent.parent):
        if (base / "images").is_dir():
            return base / "images"
    raise InputError("images", f"no images folder beside the COLMAP model {model_dir} (expected scene/images "
                     "next to scene/sparse/0)")


def load_colmap(path: str | Path, split: str = "train", *, downscale: float = 1,
                views: int | Sequence[int] | None = None, background: Sequence[float] = (1, 1, 1),
                seed: int | None = None, with_images: bool = True) -> Dataset:
    """Load a COLMAP scene (its folder, its sparse/ or sparse/0 folder): cameras, images and SfM points.

    near/far: the 1st and 99th percentile of the SfM points' depths in front of the cameras
    (widened by 10%), None without points3D.
    """
    path = Path(path)
    model_dir = find_model(path)
    if model_dir is None:
        raise InputError("data", f"no COLMAP model in {path} (looked in ., sparse/0 and sparse)")
    model = read_model(model_dir)
    ext = _model_files(model_dir)
    chosen = [model.images[i] for i in holdout_split(len(model.images), split)]
    cameras = [image_camera(model, image, f"images{ext}") for image in chosen]
    paths = None
    if with_images:
        folder = images_dir(model_dir)
        paths = [folder / image.name for image in chosen]
        for image, file in zip(chosen, paths):
            if not file.resolve().is_relative_to(folder.resolve()):
                raise InputError(f"images{ext}", f"image name {image.name!r} points outside {folder}")
    points = colors = None
    near = far = None
    if model.points is not None and len(model.points):
        points = torch.from_numpy(model.points)
        assert model.colors is not None  # read_model reads points and colors together
        colors = torch.from_numpy(model.colors.astype(np.float32) / 255)
        near, far = _depth_range(cameras, points)
    return build_dataset(cameras, paths, path, split,
                         downscale=downscale, views=views, background=background, seed=seed, near=near, far=far,
                         points=points, point_colors=colors, names=[image.name for image in chosen])


def _depth_range(cameras: list[Camera], points: torch.Tensor) -> tuple[float | None, float | None]:
    depths = torch.cat([c.to_camera(points)[:, 2] for c in cameras])
    depths = depths[depths > 0]
    if len(depths) < 2:
        return None, None
    near, far = torch.quantile(depths[:: max(1, len(depths) // 100_000)], torch.tensor([0.01, 0.99],
                                                                                     dtype=torch.float64)).tolist()
    return 0.9 * near, 1.1 * far


def locate(path: Path, split: str) -> Path | None:
    return path if path.is_dir() and find_model(path) is not None else None


FORMATS.register(DataFormat("colmap", locate, load_colmap, order=30, looks_for="a COLMAP sparse model"))
POSES.register(PoseConvention("colmap", colmap_pose, write_colmap_text,
                              "a COLMAP text model folder (cameras.txt, images.txt, points3D.txt)", suffix=""))
