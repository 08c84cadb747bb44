"""A capture's photos uploaded: `POST /v1/captures` (the first photos, or a video) and
`POST /v1/captures/{id}/photos` (photos added).

Form fields:
- `photos`: one part per photo, named by its file name (JPEG, PNG, ...: what
  `phd_core.process.photos` reads); or `archive`: the photos as one zip; or `video`: one video
  whose frames are sampled (the first upload only).
- `name` (optional): the capture's display name.
- `test` (optional): JSON list of photo names held out of training, to measure each round's
  model on (test PSNR and sigma-max-bar); they still take part in structure-from-motion.
- `matcher`, `camera_model`, `min_registered`, `fps` (optional): as `phd capture`'s flags.

Bounded as model uploads are (`service.multipart`): the bytes by `max_upload_bytes` as they
stream, the photo count by `max_capture_photos` as parts arrive, every name checked to be a
plain file name, a zip by the archive rules before a byte of it is unpacked, and the disk's room
(507). The photos land in one flat folder under the data directory's tmp/.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from starlette.requests import Request

from phd_core.errors import InputError, TooLarge
from phd_core.process.capture import CAMERA_MODELS, MATCHERS
from phd_core.process.photos import PHOTO_SUFFIXES, VIDEO_SUFFIXES

from .errors import JSON_ERRORS, ServiceError, invalid, json_problem
from .folders import CLASHES, relative_path, unpack_zip
from .multipart import Buffer, DiskRoom, FileSink, Part, Sink, boundary, read_parts
from .settings import Settings

PHOTO_PARTS = ("photos", "archive", "video")
TEXT_FIELDS = ("name", "test", "matcher", "camera_model", "min_registered", "fps")
TEXT_BYTES = 64 << 10               # the largest text field (a test list of a few thousand names)


@dataclass
class PhotoUpload:
    """What a photo upload brought: the folder its photos are in, and the form's fields."""

    folder: Path
    kind: str | None = None               # the part that brought them: photos, archive or video
    count: int = 0                        # photos (or the video: 1)
    size: int = 0                         # bytes received
    video: Path | None = None
    archive: Path | None = None
    fields: dict[str, str] = field(default_factory=dict)

    def inputs(self) -> Path:
        """What structure-from-motion takes: the video, else the photos' folder."""
        return self.video if self.video is not None else self.folder

    def test_photos(self) -> list[str]:
        """The `test` field: a JSON list of photo names (422 naming it otherwise)."""
        text = self.fields.get("test")
        if not text:
            return []
        try:
            names = json.loads(text)
        except JSON_ERRORS as exc:
            raise invalid("test", f"not valid JSON: {json_problem(exc)}") from None
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise invalid("test", "must be a JSON list of photo names")
        return list(dict.fromkeys(names))

    def sfm_settings(self) -> dict[str, Any]:
        """The structure-from-motion fields, checked (422 naming the field)."""
        found: dict[str, Any] = {}
        for key, choices in (("matcher", MATCHERS), ("camera_model", CAMERA_MODELS)):
            if key in self.fields:
                if self.fields[key] not in choices:
                    raise invalid(key, f"must be one of {', '.join(choices)}, got {self.fields[key][:40]!r}")
                found[key] = self.fields[key]
        for key, kind in (("min_registered", int), ("fps", float)):
            if key in self.fields:
                try:
                    found[key] = kind(self.fields[key])
                except ValueError:
                    raise invalid(key, f"must be a number, got {self.fields[key][:40]!r}") from None
        return found


async def receive_photos(request: Request, folder: Path, settings: Settings, *, video: bool) -> PhotoUpload:
    """Parse the multipart body into `folder` (created here; the caller removes it on failure)."""
    allowed = PHOTO_PARTS if video else PHOTO_PARTS[:2]
    separator = boundary(request, f"upload the photos as multipart/form-data, one '{allowed[0]}' part per photo "
                         f"(or {' or '.join(repr(p) for p in allowed[1:])})", "photos")
    room = DiskRoom(folder.parent, settings.keep_free_bytes)
    room.check(request.headers.get("content-length", ""), "the upload", "photos")
    folder.mkdir(parents=True)
    upload = PhotoUpload(folder)

    def count(part: str) -> Callable[[int], None]:
        def add(size: int) -> None:
            upload.size += size
            if upload.size > settings.max_upload_bytes:
                raise ServiceError(413, "payload_too_large", f"the photos exceed {settings.max_upload_bytes} bytes, "
                                   "the upload cap (PHD_MAX_UPLOAD_BYTES): send fewer or smaller photos", part)
            room.check(upload.size, "the photos", part)
        return add

    def open_part(part: Part) -> Sink:
        if part.name in TEXT_FIELDS:
            return Buffer(part.name, TEXT_BYTES, lambda data: upload.fields.__setitem__(
                part.name, data.decode("utf-8", "replace").strip()))
        if part.name not in allowed:
            raise invalid(part.name or "photos", f"unknown form field '{part.name}': expected one of "
                          f"{', '.join(allowed + TEXT_FIELDS)}")
        if upload.kind is not None and (upload.kind != part.name or part.name != "photos"):
            raise invalid(part.name, f"give the photos one way: a '{upload.kind}' part came already")
        upload.kind = part.name
        name = photo_name(part.filename, part.name)
        upload.count += 1
        if upload.count > settings.max_capture_photos:
            raise invalid("photos", f"more than {settings.max_capture_photos} photos, the most a capture may hold "
                          "(PHD_MAX_CAPTURE_PHOTOS)")
        suffix = PurePosixPath(name).suffix.lower()
        target = folder / name if part.name == "photos" else folder.with_name(f"{folder.name}-{part.name}{suffix}")
        if part.name == "video":
            if suffix not in VIDEO_SUFFIXES:
                raise invalid("video", f"{name!r} is not a video ({', '.join(VIDEO_SUFFIXES)})")
            upload.video = target
        elif part.name == "archive":
            upload.archive = target
        try:
            return FileSink(target, count(part.name), mode="xb")
        except CLASHES:
            raise invalid(part.name, f"'{name}' comes twice") from None

    await read_parts(request, separator, open_part, what="the uploaded photos", field="photos")
    if upload.archive is not None:
        try:
            unpack_zip(upload.archive, folder, settings.max_upload_bytes,
                       room.free - settings.keep_free_bytes - upload.size, "archive")
        except TooLarge as exc:
            raise ServiceError(413, "payload_too_large", exc.reason, "archive") from None
        except InputError as exc:
            raise invalid("archive", exc.reason) from None
        upload.archive.unlink()
        flatten(folder, settings.max_capture_photos)
    if upload.count == 0:
        raise invalid("photos", f"no photos: send one '{allowed[0]}' part per photo ({', '.join(PHOTO_SUFFIXES)})"
                      + (", an 'archive' zip of them or a 'video'" if video else " or an 'archive' zip of them"))
    return upload


def photo_name(filename: str | None, part: str) -> str:
    """A part's file name as a photo's name in the capture: its last path part, checked."""
    return relative_path(filename, part).name


def flatten(folder: Path, cap: int) -> None:
    """A zip's photos moved to the top of `folder` (archivers keep the folder they zipped); two
    with one name, or more than `cap` photos, are refused naming the archive."""
    files = [p for p in sorted(folder.rglob("*")) if p.is_file()]
    if len(files) > cap:
        raise invalid("archive", f"holds {len(files)} files, more than {cap} photos (PHD_MAX_CAPTURE_PHOTOS)")
    names = [p.name for p in files]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise invalid("archive", f"two photos are named {twice[0]!r} (in different folders): rename one")
    for path in files:
        if path.parent != folder:
            path.rename(folder / path.name)
    for path in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        path.rmdir()
