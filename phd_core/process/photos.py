"""The photos structure-from-motion starts from: found in what the user gave, put in capture
order, bounded, and written upright into the capture's `input/` folder.

A folder gives its photo files (not its subfolders'); files that are not photos are skipped
and named in the report. Photos are JPEG or PNG, which Pillow (our reader) and COLMAP both
read.

Capture order: photos whose names differ only in their numbers (`IMG_0001.JPG`, `frame_7.png`,
`1.jpg`, `image_20260209_153633_828.jpg`) are numbered, and their order is the numbers'
(compared as numbers, left to right); other names are one unordered set, sorted by name.
COLMAP's sequential matcher pairs images in the order of their names, so numbered photos whose
names do not already sort in that order (`1.jpg, 10.jpg, 2.jpg`) get their numbers zero-padded
in `input/` (`01.jpg, 02.jpg, 10.jpg`); every other name is kept, with whitespace made `_`
(COLMAP's pair lists are split at spaces). The report maps each name back to its photo.

Each photo is written upright (its EXIF orientation applied, as a phone's viewer shows it) and
at most `max_size` pixels on its longer side (Lanczos); a photo that needs neither is copied
byte for byte. Re-encoded photos keep their EXIF (COLMAP's focal-length prior reads it) and
their format (JPEG at quality 95, PNG lossless).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Sequence

from PIL import ExifTags, Image, ImageOps

from ..errors import InputError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")   # read by video.py
MAX_PIXELS = 100_000_000     # per photo or video frame, checked from its header before it is decoded
JPEG_QUALITY = 95


def is_photo(path: Path) -> bool:
    return path.suffix.lower() in PHOTO_SUFFIXES


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_SUFFIXES


def list_photos(inputs: Sequence[Path]) -> tuple[list[Path], list[str]]:
    """(photos, skipped): the photos of one folder, or the photo files given; skipped names the
    folder's files that are not photos (hidden files are passed over in silence)."""
    if len(inputs) == 1 and inputs[0].is_dir():
        files = sorted(p for p in inputs[0].iterdir() if p.is_file() and not p.name.startswith("."))
        return [p for p in files if is_photo(p)], [p.name for p in files if not is_photo(p)]
    for path in inputs:
        if path.is_dir():
            raise InputError("inputs", f"{path} is a folder: give one folder of photos, or photo files")
        if not path.is_file():
            raise InputError("inputs", f"no such file: {path}")
        if not is_photo(path):
            raise InputError("inputs", f"{path.name} is not a photo ({', '.join(PHOTO_SUFFIXES)})")
    return list(inputs), []


def _pattern(name: str) -> str:
    """The name with each number replaced by '#': names differing only in numbers share it."""
    return re.sub(r"\d+", "#", name.lower())


def _numbers(name: str) -> list[int]:
    return [int(n) for n in re.findall(r"\d+", name)]


def capture_order(photos: list[Path]) -> tuple[list[Path], bool]:
    """(photos in capture order, whether they are numbered): numbered photos by their numbers,
    others by name."""
    numbered = len({_pattern(p.name) for p in photos}) == 1 and bool(re.search(r"\d", photos[0].name))
    key = (lambda p: _numbers(p.name)) if numbered else (lambda p: p.name)
    return sorted(photos, key=key), numbered


def input_names(photos: list[Path], numbered: bool) -> list[str]:
    """The photos' names in `input/`, in the order given (their capture order): kept, with
    whitespace made '_'; numbered photos get their numbers zero-padded when the names do not
    sort in the order given."""
    names = [re.sub(r"\s", "_", p.name) for p in photos]
    if numbered and sorted(names) != names:
        widths = [max(len(n) for n in column) for column in zip(*(re.findall(r"\d+", name) for name in names))]
        names = [_pad(name, widths) for name in names]
    seen: dict[str, Path] = {}
    for name, photo in zip(names, photos):
        if name in seen:
            raise InputError("inputs", f"{seen[name].name} and {photo.name} would both be {name!r} in the capture: "
                             "rename one")
        seen[name] = photo
    return names


def _pad(name: str, widths: list[int]) -> str:
    numbers = iter(widths)
    return re.sub(r"\d+", lambda m: m.group().zfill(next(numbers)), name)


def write_photo(source: Path, target: Path, max_size: int) -> tuple[tuple[int, int], bool]:
    """Write `source` to `target` upright and at most `max_size` px on its longer side:
    ((width, height) written, whether it was downscaled). An unreadable photo is refused."""
    try:
        with Image.open(source) as image:
            if image.width * image.height > MAX_PIXELS:
                raise InputError("inputs", f"{source.name} is {image.width}x{image.height}: more than "
                                 f"{MAX_PIXELS:,} pixels")
            image.load()                                   # decodes: a damaged file fails here
            upright = image.getexif().get(ExifTags.Base.Orientation, 1) in (0, 1)
            downscale = max(image.size) > max_size
            if upright and not downscale:
                shutil.copyfile(source, target)
                return image.size, False
            photo = ImageOps.exif_transpose(image).convert("RGB")
            exif = photo.getexif()
    except InputError:
        raise
    except Exception as exc:        # any decoder failure means this file is no usable photo
        raise InputError("inputs", f"cannot read photo {source}: {str(exc).splitlines()[0]}") from None
    if downscale:
        photo.thumbnail((max_size, max_size), Image.Resampling.LANCZOS)
    photo.save(target, quality=JPEG_QUALITY, exif=exif)
    return photo.size, downscale
