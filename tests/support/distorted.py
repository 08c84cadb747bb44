"""Captures with lens distortion, made as a camera takes them: a known 3DGS scene rendered
through a pinhole camera and resampled through a COLMAP camera model (each photo pixel takes
the colour its ray sees, from pycolmap's `cam_from_img`), written by pycolmap as a binary COLMAP
model with SfM points and their keypoints. What the loader undistorts can then be compared with
the scene rendered directly at the undistorted camera pycolmap gives."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch
import torch.nn.functional as F

from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.scene import Camera, look_at

# Parameters of every distorted model at 96x72 (focal ~70 px, centre (48, 36)): mild to strong
# distortion, as phones, action cameras and fisheye lenses have.
CAMERA_MODELS = {
    "SIMPLE_RADIAL": [70, 48, 36, 0.12],
    "RADIAL": [70, 48, 36, 0.1, -0.02],
    "OPENCV": [72, 70, 47, 37, 0.1, -0.03, 0.004, -0.003],
    "FULL_OPENCV": [72, 70, 47, 37, 0.1, -0.03, 0.004, -0.003, 0.01, 0.02, 0.01, 0.005],
    "OPENCV_FISHEYE": [60, 60, 48, 36, 0.08, 0.02, -0.01, 0.003],
    "FOV": [60, 60, 48, 36, 0.6],
    "SIMPLE_RADIAL_FISHEYE": [60, 48, 36, 0.05],
    "RADIAL_FISHEYE": [60, 48, 36, 0.05, 0.01],
    "THIN_PRISM_FISHEYE": [60, 60, 48, 36, 0.05, 0.01, 0.002, -0.002, 0.003, 0.001, 0.002, -0.001],
}
WIDTH, HEIGHT = 96, 72


def scene() -> GaussianRenderer:
    """1,500 random splats in [-0.8, 0.8]^3 over a grey background: texture at a few pixels' scale."""
    g = torch.Generator().manual_seed(0)
    n = 1500
    model = GaussianModel(means=(torch.rand(n, 3, generator=g) - 0.5) * 1.6,
                          log_scales=torch.log(0.03 + 0.05 * torch.rand(n, 3, generator=g)),
                          quats=torch.randn(n, 4, generator=g), opacity_logits=torch.rand(n, generator=g) * 4,
                          sh=torch.randn(n, 1, 3, generator=g) * 0.8)
    return GaussianRenderer(model, (0.5, 0.5, 0.5))


def ring_pose(i: int, count: int) -> torch.Tensor:
    """[4, 4] OpenGL camera-to-world on a ring of radius 2.6 around the scene, looking at its centre."""
    a = 2 * math.pi * i / count
    return look_at((2.6 * math.cos(a), 2.6 * math.sin(a), 0.8), (0, 0, 0), width=8, height=8, fov_x=1.0).c2w


def pinhole_render(renderer: GaussianRenderer, c2w: torch.Tensor, fx: float, fy: float, cx: float, cy: float,
                   width: int, height: int) -> torch.Tensor:
    """[height, width, 3] the scene through a pinhole camera."""
    return renderer.render(Camera(c2w, fx, fy, cx, cy, width, height))[0]


def distorted_photo(renderer: GaussianRenderer, c2w: torch.Tensor, camera: pycolmap.Camera,
                    oversample: int = 3) -> torch.Tensor:
    """[H, W, 3] what `camera` sees from `c2w`: each pixel centre's ray (pycolmap's cam_from_img)
    sampled, bilinearly, from a pinhole render `oversample` times as dense that covers every ray."""
    xs, ys = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    rays = camera.cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64))    # [P, 2] x/z, y/z
    focal = oversample * camera.mean_focal_length()
    low, high = rays.min(0) - 2 / focal, rays.max(0) + 2 / focal
    width, height = math.ceil((high[0] - low[0]) * focal), math.ceil((high[1] - low[1]) * focal)
    dense = pinhole_render(renderer, c2w, focal, focal, -low[0] * focal, -low[1] * focal, width, height)
    u, v = (rays[:, 0] - low[0]) * focal, (rays[:, 1] - low[1]) * focal              # pixels of `dense`
    grid = torch.from_numpy(np.stack([2 * u / width - 1, 2 * v / height - 1], -1)).float()
    sampled = F.grid_sample(dense.permute(2, 0, 1)[None], grid.reshape(1, camera.height, camera.width, 2),
                            mode="bilinear", align_corners=False)                          # [1, 3, H, W]
    return sampled[0].permute(1, 2, 0)


@dataclass
class View:
    name: str
    c2w: torch.Tensor                 # [4, 4] OpenGL camera-to-world
    camera: pycolmap.Camera           # at the size COLMAP saw the photo


def write_capture(root: Path, renderer: GaussianRenderer, views: Sequence[View], points: np.ndarray,
                  photo_sizes: Sequence[tuple[int, int]] | None = None) -> Path:
    """root/sparse/0 (binary, written by pycolmap: one camera per view, the SfM `points` [P, 3]
    with the keypoints where each view's camera sees them) and root/images/<name> (PNG, resized
    to `photo_sizes` (width, height) when given: photos at another size than their cameras)."""
    reconstruction = pycolmap.Reconstruction()
    tracks: list[list[tuple[int, int]]] = [[] for _ in points]
    (root / "images").mkdir(parents=True, exist_ok=True)
    for k, view in enumerate(views, start=1):
        camera = pycolmap.Camera(model=view.camera.model, width=view.camera.width, height=view.camera.height,
                                 params=view.camera.params, camera_id=k)
        reconstruction.add_camera_with_trivial_rig(camera)
        w2c = Camera(view.c2w, 1, 1, 0, 0, 1, 1).world_to_camera().numpy()               # [4, 4] OpenCV
        in_camera = points @ w2c[:3, :3].T + w2c[:3, 3]
        pixels = camera.img_from_cam(in_camera)                                          # [P, 2]
        seen = np.flatnonzero((in_camera[:, 2] > 0.1) & (pixels >= 0).all(1)
                              & (pixels < [camera.width, camera.height]).all(1))
        image = pycolmap.Image(name=view.name, keypoints=pixels[seen], camera_id=k, image_id=k)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]),
                                                                             w2c[:3, 3]))
        for index, point in enumerate(seen):
            tracks[point].append((k, index))
        photo = distorted_photo(renderer, view.c2w, camera)
        if photo_sizes is not None:
            width, height = photo_sizes[k - 1]
            photo = F.interpolate(photo.permute(2, 0, 1)[None], size=(height, width), mode="area")[0].permute(1, 2, 0)
        iio.imwrite(root / "images" / view.name, (photo.clamp(0, 1) * 255).round().to(torch.uint8).numpy())
    for point, track in zip(points, tracks):
        if len(track) >= 2:
            reconstruction.add_point3D(point, pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in track]),
                                       np.array([128, 128, 128], np.uint8))
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(sparse))
    return sparse


def undistorted(camera: pycolmap.Camera, photo_size: tuple[int, int] | None = None) -> pycolmap.Camera:
    """pycolmap's undistorted PINHOLE of `camera` at `photo_size` (width, height; default its own):
    the expected camera, computed here independently of the loader."""
    at_size = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=camera.params)
    if photo_size is not None:
        at_size.rescale(*photo_size)
    return pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(max_image_size=4096), at_size)
