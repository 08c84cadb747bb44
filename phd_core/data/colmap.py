"""COLMAP sparse models, text (cameras.txt, images.txt, points3D.txt) or binary (.bin), with
the images folder beside them: the layout the reference 3DGS trainer reads
(`scene/images/`, `scene/sparse/0/`).

The files are parsed by the project's own bounded reader (`phd_core.data.colmap_files`), not by
pycolmap: the service reads COLMAP models inside uploaded folders, and a C++ reader fed hostile
bytes can take the whole process down. pycolmap does the camera maths
(`phd_core.data.undistort`) and, in the tests, writes the models.

Convention: images.{txt,bin} store the WORLD-TO-CAMERA rotation as a quaternion (qw, qx, qy,
qz) and the translation t, camera axes OpenCV (x right, y down, z forward); a world point X
lands at R X + t. The project's `Camera` is camera-to-world OpenGL, so
c2w = [R^T | -R^T t] @ diag(1, -1, -1, 1). COLMAP puts the centre of the top-left pixel at
(0.5, 0.5), as `Camera` does, so cx, cy carry over unchanged.

Camera models: every one COLMAP writes for cameras and phones. SIMPLE_PINHOLE, PINHOLE, and
the radial and OPENCV models whose distortion coefficients are all exactly 0, are pinholes;
any other (distorted, fisheye, FOV) becomes the undistorted PINHOLE camera pycolmap gives, and
its photos are undistorted when loaded (`phd_core.data.undistort`: cached, with a note).

Photo sizes: the intrinsics (and width, height) of a COLMAP camera are those of the photos
COLMAP saw; the images folder may hold them downscaled (`images_N` folders, photos shrunk
after reconstruction). Each camera's photo size is measured on the header of its first photo
(by name), and its intrinsics are scaled by photo size / camera size per axis, as gsplat's and
nerfstudio's readers do; a photo whose aspect ratio differs from its camera's by more than a
rounding of one pixel per side is refused, naming it, and so is a photo whose size differs
from the other photos of its camera. Poses-only loading (`with_images=False`) reads these
headers too (one per camera: the camera must be the same with or without images) and
decodes no pixels; without an images folder, the cameras keep the model's size. Views may
differ in size (portrait and landscape cameras, per-image cameras after undistortion).

Splits, as LLFF-style evaluation does: images sorted by name, every 8th (0, 8, 16, ...) is
"test", the rest "train"; "all" is every image. points3D gives the SfM points and their
colours (`Dataset.points`), which the 3DGS trainer starts from.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch

from ..errors import InputError, ModelNote
from ..io import write_bytes_atomic
from ..scene import Camera
from ..scene.rotations import quaternion_to_rotation, rotation_to_quaternion
from .colmap_files import (
    MODEL_IDS,
    MODELS,
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    model_files,
    read_cameras_binary,
    read_cameras_text,
    read_model,
)
from .formats import FORMATS, DataFormat
from .frames import Dataset, Photo, build_dataset, holdout_split, image_size
from .poses import POSES, PoseConvention

if TYPE_CHECKING:
    from .undistort import UndistortionCache

# Models that are a pinhole when their distortion coefficients are all zero (fisheyes never are).
PINHOLE_WHEN_UNDISTORTED = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}
_GL_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


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


Intrinsics = tuple[float, float, float, float, int, int]      # fx, fy, cx, cy, width, height


def is_distorted(camera: ColmapCamera) -> bool:
    """Whether a camera is other than a pinhole: a distorted, fisheye or FOV model (a radial or
    OPENCV model with every distortion coefficient exactly 0 is a pinhole)."""
    names = MODELS[MODEL_IDS[camera.model]][1]
    first_distortion = 3 if names[0] == "f" else 4
    return camera.model not in PINHOLE_WHEN_UNDISTORTED or any(p != 0 for p in camera.params[first_distortion:])


def pinhole(camera: ColmapCamera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a camera that is not distorted (`is_distorted`)."""
    values = dict(zip(MODELS[MODEL_IDS[camera.model]][1], camera.params))
    fx = values.get("fx", values.get("f"))
    assert fx is not None and not is_distorted(camera)   # every pinhole-type model has f or fx
    return fx, values.get("fy", fx), values["cx"], values["cy"]


def distorted_models(folder: Path) -> list[str]:
    """The distorted camera models of the COLMAP model in `folder` (as `find_model` finds it);
    empty without a readable model."""
    model_dir = find_model(folder)
    if model_dir is None:
        return []
    ext = model_files(model_dir)
    try:
        cameras = (read_cameras_binary if ext == ".bin" else read_cameras_text)(model_dir / f"cameras{ext}")
    except InputError:
        return []
    return sorted({c.model for c in cameras.values() if is_distorted(c)})


def check_photo_size(camera: ColmapCamera, size: tuple[int, int], where: str) -> None:
    """Refuse a photo size (height, width) whose aspect ratio is not its camera's up to a
    rounding of one pixel: some one scale s must give |s W - width| <= 1 and |s H - height| <= 1."""
    (height, width), (cam_w, cam_h) = size, (camera.width, camera.height)
    if max((width - 1) / cam_w, (height - 1) / cam_h) > min((width + 1) / cam_w, (height + 1) / cam_h):
        raise InputError(where, f"the photo is {width}x{height} but its camera is {cam_w}x{cam_h}: their aspect "
                         f"ratios ({width / height:.4f}, {cam_w / cam_h:.4f}) differ by more than a rounding of "
                         "one pixel, so the photo is not the camera's picture downscaled")


def camera_intrinsics(camera: ColmapCamera, size: tuple[int, int] | None, where: str) -> Intrinsics:
    """(fx, fy, cx, cy, width, height) of a COLMAP camera for photos of `size` (height, width;
    None: the camera's own size): a pinhole's intrinsics scaled per axis, or the undistorted
    pinhole pycolmap gives for a distorted camera at that size."""
    if size is not None:
        check_photo_size(camera, size, where)
    height, width = size or (camera.height, camera.width)
    if is_distorted(camera):
        from . import undistort  # pycolmap takes half a second to import: only distorted captures pay it

        distorted = undistort.distorted_camera(camera.model, camera.width, camera.height, camera.params,
                                               (height, width), where)
        return undistort.undistorted_pinhole(distorted, where)
    fx, fy, cx, cy = pinhole(camera)
    sx, sy = width / camera.width, height / camera.height
    return fx * sx, fy * sy, cx * sx, cy * sy, width, height


def image_camera(model: ColmapModel, image: ColmapImage, file: str, intrinsics: Intrinsics | None = None) -> Camera:
    """The project's Camera of one registered image; `intrinsics` from `camera_intrinsics`
    (default: its camera's, at the camera's own size)."""
    where = f"{file}: image {image.name!r}"
    if image.camera_id not in model.cameras:
        raise InputError(where, f"camera_id {image.camera_id} is not in the cameras file")
    if not np.isfinite(image.qvec).all() or not np.isfinite(image.tvec).all() or not any(image.qvec):
        raise InputError(where, "the pose (quaternion, translation) must be finite, with a non-zero quaternion")
    if intrinsics is None:
        intrinsics = camera_intrinsics(model.cameras[image.camera_id], None,
                                       f"{file.replace('images', 'cameras')}: camera {image.camera_id}")
    rotation = qvec_to_rotation(image.qvec)                              # world -> camera
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = -rotation.T @ torch.tensor(image.tvec, dtype=torch.float64)
    try:
        return Camera(c2w @ _GL_FLIP, *intrinsics)
    except InputError as exc:
        raise InputError(f"{where}.{exc.field}", exc.reason) from None


# ----------------------------------------------------------------------------- the format

def find_model(path: Path) -> Path | None:
    """The COLMAP model folder of a scene: `path` itself, `path/sparse/0` or `path/sparse`."""
    for candidate in (path, path / "sparse" / "0", path / "sparse"):
        if candidate.is_dir() and model_files(candidate) is not None:
            return candidate
    return None


def images_dir(model_dir: Path) -> Path | None:
    """The images folder beside the model: scene/images for scene/sparse/0 (or scene/sparse); None without one."""
    for base in (model_dir, model_dir.parent, model_dir.parent.parent):
        if (base / "images").is_dir():
            return base / "images"
    return None


def photo_paths(model: ColmapModel, folder: Path, file: str) -> dict[str, Path]:
    """Image name -> its file in `folder`; a name that points outside the folder is refused."""
    paths = {}
    for image in model.images:
        path = folder / image.name
        if not path.resolve().is_relative_to(folder.resolve()):
            raise InputError(file, f"image name {image.name!r} points outside {folder}")
        paths[image.name] = path
    return paths


Measured = tuple[str, tuple[int, int]]                         # a photo's name and its (height, width)


def photo_sizes(model: ColmapModel, cameras: set[int], paths: dict[str, Path]) -> dict[int, Measured]:
    """Camera id -> (name, (height, width)) of the camera's first photo (by name) found in the
    images folder, read from its header: the size of that camera's photos (module docstring)."""
    sizes: dict[int, Measured] = {}
    for image in model.images:                                     # sorted by name
        if image.camera_id in cameras and image.camera_id not in sizes and paths[image.name].is_file():
            sizes[image.camera_id] = (image.name, image_size(paths[image.name], f"images/{image.name}"))
    return sizes


def load_colmap(path: str | Path, split: str = "train", *, downscale: float = 1,
                views: int | Sequence[int] | None = None, background: Sequence[float] = (1, 1, 1),
                seed: int | None = None, with_images: bool = True) -> Dataset:
    """Load a COLMAP scene (its folder, its sparse/ or sparse/0 folder): cameras, images and SfM points.

    Cameras at their photos' size, undistorted when the COLMAP camera has distortion (module
    docstring). near/far: the 1st and 99th percentile of the SfM points' depths in front of
    the cameras (widened by 10%), None without points3D.
    """
    path = Path(path)
    model_dir = find_model(path)
    if model_dir is None:
        raise InputError("data", f"no COLMAP model in {path} (looked in ., sparse/0 and sparse)")
    model = read_model(model_dir)
    file = f"images{model_files(model_dir)}"
    chosen = [model.images[i] for i in holdout_split(len(model.images), split)]
    used = {image.camera_id for image in chosen} & model.cameras.keys()      # a missing one: image_camera says so
    folder = images_dir(model_dir)
    if with_images and folder is None:
        raise InputError("images", f"no images folder beside the COLMAP model {model_dir} (expected scene/images "
                         "next to scene/sparse/0)")
    paths = {} if folder is None else photo_paths(model, folder, file)
    sizes = {} if folder is None else photo_sizes(model, used, paths)
    intrinsics = {cid: camera_intrinsics(model.cameras[cid], sizes[cid][1] if cid in sizes else None,
                                         f"images/{sizes[cid][0]}" if cid in sizes else
                                         f"{file.replace('images', 'cameras')}: camera {cid}")
                  for cid in sorted(used)}
    cameras = [image_camera(model, image, file, intrinsics.get(image.camera_id)) for image in chosen]
    distorted = sorted({model.cameras[cid].model for cid in used if is_distorted(model.cameras[cid])})
    photos = cache = None
    if with_images:
        if distorted:
            from .undistort import UndistortionCache

            cache = UndistortionCache()
        photos = [_photo(model, image, paths[image.name], sizes.get(image.camera_id), cache) for image in chosen]
    points = colors = None
    near = far = None
    if model.points is not None and len(model.points):
        points = torch.from_numpy(model.points)
        assert model.colors is not None  # read_model reads points and colors together
        colors = torch.from_numpy(model.colors.astype(np.float32) / 255)
        near, far = _depth_range(cameras, points)
    dataset = build_dataset(cameras, photos, path, split,
                            downscale=downscale, views=views, background=background, seed=seed, near=near, far=far,
                            points=points, point_colors=colors, names=[image.name for image in chosen])
    if cache is not None and cache.used:
        warnings.warn(cache.note(path, distorted), ModelNote, stacklevel=2)
    return dataset


def _photo(model: ColmapModel, image: ColmapImage, path: Path, measured: Measured | None,
           cache: UndistortionCache | None) -> Photo:
    """The Photo of one image: the size its camera's photos were measured to have (else the
    camera's own), undistorted through `cache` when its camera is distorted."""
    camera = model.cameras[image.camera_id]
    if measured is None:
        size, size_from = (camera.height, camera.width), f"the size of its camera {image.camera_id}"
    else:
        size, size_from = measured[1], f"the size of camera {image.camera_id}'s photos, measured on {measured[0]}"
    field = f"images/{image.name}"
    if not is_distorted(camera):
        return Photo(path, size, field, size_from)
    from .undistort import UndistortedPhoto, distorted_camera

    assert cache is not None                 # load_colmap makes one when a camera is distorted
    return UndistortedPhoto(path, size, field, size_from, cache=cache,
                            camera=distorted_camera(camera.model, camera.width, camera.height, camera.params, size,
                                                    field))


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
