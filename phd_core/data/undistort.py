"""COLMAP's distorted cameras and their photos, undistorted by pycolmap (COLMAP's own code).

A distorted camera (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE, FOV,
SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, THIN_PRISM_FISHEYE) becomes the PINHOLE camera
`pycolmap.undistort_camera` gives for it at its photos' size: the pinhole view that the photo
fills without blank pixels (COLMAP's `image_undistorter` defaults: blank_pixels 0, a scale
within [0.2, 2]), its principal point at the centre, its size capped at the project's largest
(DEFAULT_MAX_SIZE). That camera needs no pixels, so poses-only uses (candidates, targets,
export, the page's camera files) pay nothing for it. `pycolmap.undistort_image` warps a photo
onto it (bilinear) with the same options, so the camera and the pixels agree by construction.

Photos are undistorted once. Each view's undistorted photo, at the size it is loaded at (after
the downscale), is kept as an 8-bit PNG in `PHD_CACHE_DIR`, else `$XDG_CACHE_HOME/ph-dropout-service`
(`~/.cache/ph-dropout-service`), under `undistorted/`: never beside the capture, which may be
read-only. An entry is named by a hash of what makes it: the photo's bytes (sha256), the
distorted camera at the photo's size, the undistortion options, the loaded size, pycolmap's
version and CACHE_FORMAT. Hashing the bytes instead of trusting (size, mtime) costs one read
of each photo per load (milliseconds for a phone JPEG, against about a second to decode and
undistort a 12 MP photo) and keeps the cache right when a capture is copied, extracted again
or edited in place. A miss writes its entry atomically and is loaded from the very pixels it
wrote, so a first and a later load give identical images; a folder that cannot be written is
skipped (the photo is undistorted in memory) and the reason given. Colour is warped
premultiplied by alpha (as every resize here is) in 8 bits: exact for the 8-bit photos COLMAP
takes, a rounding to 8 bits for 16-bit ones.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch

from ..errors import InputError
from ..io import png_bytes, write_bytes_atomic
from ..scene import DEFAULT_MAX_SIZE
from .frames import Photo, premultiply, resize_image, rgba_from_pixels

CACHE_FORMAT = 1            # raise when what an entry holds changes: older entries then simply miss
# COLMAP's image_undistorter defaults, with the size capped where the project's Camera caps it.
OPTIONS = pycolmap.UndistortCameraOptions(max_image_size=DEFAULT_MAX_SIZE)


def cache_root() -> Path:
    """The project's cache folder: PHD_CACHE_DIR, else the XDG cache folder."""
    given = os.environ.get("PHD_CACHE_DIR")
    if given:
        return Path(given)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ph-dropout-service"


def distorted_camera(model: str, width: int, height: int, params: Sequence[float],
                     photo_size: tuple[int, int], where: str) -> pycolmap.Camera:
    """The COLMAP camera as pycolmap holds it, rescaled to its photos' size (height, width):
    focal lengths and principal point scale, the distortion (in normalised coordinates) stays."""
    try:
        camera = pycolmap.Camera(model=model, width=width, height=height, params=list(params))
        camera.rescale(photo_size[1], photo_size[0])
    except (ValueError, RuntimeError) as exc:
        raise InputError(where, f"pycolmap refuses the {model} camera: {str(exc).splitlines()[0]}") from None
    return camera


def undistorted_pinhole(camera: pycolmap.Camera, where: str) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height) of the PINHOLE camera pycolmap undistorts `camera` to."""
    try:
        pinhole = pycolmap.undistort_camera(OPTIONS, camera)
    except (ValueError, RuntimeError) as exc:
        raise InputError(where, f"pycolmap cannot undistort the {camera.model.name} camera: "
                         f"{str(exc).splitlines()[0]}") from None
    fx, fy, cx, cy = (float(v) for v in pinhole.params)
    return fx, fy, cx, cy, int(pinhole.width), int(pinhole.height)


class UndistortionCache:
    """The folder of undistorted photos (module docstring), and what one load did with it."""

    def __init__(self, root: Path | None = None) -> None:
        self.dir = (root or cache_root()) / "undistorted"
        self.reused = self.written = 0
        self.skipped: str | None = None          # why an entry was not written, if one was not

    @property
    def used(self) -> bool:
        """Whether a photo went through it (a load may select none of the distorted views)."""
        return bool(self.reused or self.written or self.skipped)

    def entry(self, recipe: dict) -> Path:
        return self.dir / f"{hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:32]}.png"

    def load(self, entry: Path) -> np.ndarray | None:
        """The entry's pixels, uint8 [h, w, 3 or 4], or None when there is none (or it cannot be read)."""
        try:
            pixels = iio.imread(entry, plugin="pillow")
        except Exception:  # absent, or damaged by something outside this project: undistort again
            return None
        self.reused += 1
        return pixels

    def store(self, entry: Path, pixels: np.ndarray) -> None:
        try:
            entry.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(entry, png_bytes(pixels))
            self.written += 1
        except OSError as exc:
            self.skipped = f"{self.dir} cannot be written ({exc.strerror or exc})"

    def note(self, capture: Path, models: Sequence[str]) -> str:
        """What this load did, for the note the CLI prints."""
        kept = (f"not kept: {self.skipped}" if self.skipped else
                f"kept in {self.dir} ({self.written} undistorted now, {self.reused} reused)")
        return (f"the photos of {capture} have lens distortion ({', '.join(models)}): loaded undistorted onto "
                f"pinhole cameras by pycolmap; {kept}")


@dataclass(frozen=True)
class UndistortedPhoto(Photo):
    """A photo of a distorted camera: read as any photo, warped onto its undistorted pinhole
    camera by pycolmap, resized, and kept in the cache."""

    camera: pycolmap.Camera = field(kw_only=True)        # the distorted camera at the photo's size
    cache: UndistortionCache = field(kw_only=True)

    def premultiplied(self, height: int, width: int) -> tuple[torch.Tensor, bool]:
        entry = self.cache.entry(self.recipe(height, width))
        pixels = self.cache.load(entry)
        if pixels is None:
            pixels = self.undistort(height, width)
            self.cache.store(entry, pixels)
        rgba, has_alpha = rgba_from_pixels(pixels, entry, self.file_field)
        return premultiply(torch.from_numpy(rgba)), has_alpha

    def recipe(self, height: int, width: int) -> dict:
        """Everything the undistorted photo depends on: the cache entry's key (module docstring)."""
        with open(self.path, "rb") as f:
            photo = hashlib.file_digest(f, "sha256").hexdigest()
        return {"format": CACHE_FORMAT, "pycolmap": pycolmap.__version__, "photo": photo,
                "camera": [self.camera.model.name, self.camera.width, self.camera.height,
                           [float(p) for p in self.camera.params]],
                "options": str(OPTIONS.todict()), "size": [height, width]}

    def undistort(self, height: int, width: int) -> np.ndarray:
        """Straight uint8 RGB(A) [height, width, 3 or 4]: the photo warped by pycolmap onto its
        undistorted camera, then resized (premultiplied) to height x width."""
        rgba, has_alpha = self.read()                                             # [H, W, 4] straight
        premult = premultiply(torch.from_numpy(rgba)).numpy()
        colour = self._warp(premult[..., :3])                                     # [H', W', 3]
        alpha = self._warp(premult[..., 3:]) if has_alpha else np.ones_like(colour[..., :1])
        small = resize_image(torch.from_numpy(np.concatenate([colour, alpha], -1)), height, width)   # [h, w, 4]
        opacity = small[..., 3:]
        straight = torch.where(opacity > 0, small[..., :3] / opacity.clamp_min(1e-12), 0.0).clamp(0, 1)
        out = torch.cat([straight, opacity], -1) if has_alpha else straight
        return (out * 255).round().to(torch.uint8).numpy()

    def _warp(self, values: np.ndarray) -> np.ndarray:
        """[H, W, C] float in [0, 1], C 3 or 1 -> [H', W', C] float32 on the undistorted camera (8 bits)."""
        levels = np.round(values * 255).astype(np.uint8)
        bitmap = pycolmap.Bitmap.from_array(levels if levels.shape[-1] == 3 else levels[..., 0])
        warped, _ = pycolmap.undistort_image(OPTIONS, bitmap, self.camera)
        out = warped.to_array().astype(np.float32) / 255
        return out if out.ndim == 3 else out[..., None]
