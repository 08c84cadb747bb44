"""Model uploads: stream a multipart body to a temp file, then check it fully.

Form fields of `POST /v1/models`:
- `file`: the model, a file of a registered family (`phd_core.renderers.FAMILIES`). The
  kind comes from the first bytes, never from the file name; anything else (a pickle named .pt, a
  zip, text) is refused with 415 before any parser sees more than its head.
- instead of `file`, a folder as `phd train` or another trainer wrote it (`service.folders`):
  `files`, one part per file, each named by its path inside the folder (a PLY with its sidecar
  `<stem>.json`, or a reference-trainer / splatfacto / gsplat output folder), or `archive`, the
  folder as one zip. Read with the rules `phd_core` reads folders and sidecars by, so the page,
  the Python client and the CLI take the same files.
- `cameras` (optional): training cameras as JSON, a transforms.json object, a list of
  frames, a reference-trainer cameras.json or the sidecar `phd train` wrote beside its PLY
  (whose background and capture format then apply too), as a text field or a file.
- `name` (optional): a display name; default the uploaded file's name.
- `background` (optional, splat models): the colour the model was trained over, JSON
  `[r, g, b]` in [0, 1] or "white" / "black" / "grey" (a trainer's sidecar or cfg_args says
  it). A bare PLY carries none, so without the field it is guessed by one rule
  (`guess_background`): black when the cameras are a reference-trainer cameras.json (that
  trainer's default), else white. Stored with the model and used by every render.
- `camera_format` (optional): the format of the capture the cameras came from, one of
  `phd_core.data.FORMATS` (blender, nerfstudio, colmap, llff, 3dgs-output: the name `phd rank`
  and the sidecar use); default 3dgs-output for a cameras.json, nerfstudio for frames. Ranked
  poses come back in it too where it has a pose convention (`phd_core.data.POSES`; LLFF has none).
- `other_capture` (optional): "true" stores a model whose training cameras see almost none of
  it (another capture's cameras, or cameras in another frame: refused with 422 otherwise,
  `service.state`); "false" (the default) refuses them.

The body is parsed as it arrives (python-multipart's streaming parser): the model bytes go
straight to `tmp/` in the data directory and are hashed on the way, so an upload never sits
in memory whole. The size cap itself is enforced by `service.guard` on the raw stream.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from starlette.requests import Request

from phd_core.data import FORMATS
from phd_core.data.inria import is_inria_cameras
from phd_core.errors import InputError, check_color
from phd_core.io import fsync_path
from phd_core.renderers import SNIFF_BYTES, family_titles, model_kind

from .errors import JSON_ERRORS, ServiceError, invalid, json_problem
from .folders import CLASHES, SIDECAR_SOURCE, folder_target
from .multipart import Buffer, DiskRoom, FileSink, Part, Sink, boundary, read_parts
from .store import writing

MAX_NAME_BYTES = 256
FIELDS = ("file", "files", "archive", "cameras", "name", "background", "camera_format", "other_capture")
YES, NO = ("true", "1", "yes", "on"), ("false", "0", "no", "off", "")     # `other_capture`, any case
MODEL_PARTS = ("file", "files", "archive")   # one kind per request


@dataclass
class Upload:
    path: Path
    filename: str | None = None
    name: str | None = None
    cameras: bytes | None = None
    background: bytes | None = None
    camera_format: str | None = None
    other_capture: bool = False         # store it even when its cameras see almost none of it
    size: int = 0
    head: bytes = b""
    sha256: str = ""
    has_file: bool = False
    folder: Path | None = None          # `files` parts land here, under their own paths
    archive: Path | None = None         # an `archive` part lands here
    folder_files: int = 0
    note: str | None = None             # set when the upload is answered by a model stored already
    background_source: str | None = None   # who set `background` when it was not the request (a sidecar)
    notes: list[str] = field(default_factory=list)   # what reading a folder noted, shown with the model
    calibrations: list[dict] = field(default_factory=list)   # a folder's stored ones for its model (FolderModel)
    facts: dict[str, Any] = field(default_factory=dict)      # stored with its facts (a capture's model: its link)


async def receive_upload(request: Request, temp_path: Path, max_cameras_bytes: int, max_file_bytes: int,
                         folder_path: Path, keep_free: int = 0) -> Upload:
    """Parse the multipart body of `request`, writing the model to `temp_path` (then fsynced), a
    folder's `files` under `folder_path` and an `archive` to `folder_path`.zip.

    A model past `max_file_bytes` (what the memory budget can parse) is cut off with 413 as it
    streams; so is a folder whose files add up past it. A body that would leave less than
    `keep_free` bytes free on the disk is refused with 507 up front (by its Content-Length) or as
    it streams, and so is a write the full disk refuses. The caller deletes `temp_path` and the
    folder on any failure.
    """
    separator = boundary(request, "upload the model as multipart/form-data with a 'file' part (and optionally "
                         "'cameras' and 'name')", "file")
    room = DiskRoom(temp_path.parent, keep_free)
    room.check(request.headers.get("content-length", ""), "the upload", "file")
    upload = Upload(path=temp_path)
    digest = hashlib.sha256()

    def count(part: str, folder: bool) -> Callable[[int], None]:
        """What each chunk of a model part adds: the cap first, then the disk's room."""
        def add(size: int) -> None:
            upload.size += size
            if upload.size > max_file_bytes:
                raise ServiceError(413, "payload_too_large", (
                    f"the folder's files exceed {max_file_bytes} bytes, the largest this service's memory budget can "
                    "read (leave out the images: the model and its cameras are enough)") if folder else (
                    f"the model file exceeds {max_file_bytes} bytes, the largest this service's memory budget can "
                    "parse"), part)
            room.check(upload.size, "the folder's files" if folder else "the model file", part)
        return add

    def sniff(chunk: bytes) -> None:
        if len(upload.head) < SNIFF_BYTES:
            upload.head += chunk[:SNIFF_BYTES - len(upload.head)]
        digest.update(chunk)

    def open_part(part: Part) -> Sink:
        if part.name not in FIELDS:
            raise invalid(part.name or "file", f"unknown form field '{part.name}': expected one of {', '.join(FIELDS)}")
        if part.name in MODEL_PARTS:
            kinds = {"file": upload.has_file, "files": upload.folder_files > 0, "archive": upload.archive is not None}
            other = next((kind for kind, given in kinds.items() if given and kind != part.name), None)
            if other is not None:
                raise invalid(part.name, f"give the model one way: a '{other}' part came already")
        if part.name in ("files", "archive"):
            if part.name == "archive" and upload.archive is not None:
                raise invalid("archive", "more than one 'archive' part: upload one zip per request")
            where = folder_target(folder_path, part.name, part.filename, upload.folder_files)
            upload.folder_files += part.name == "files"
            upload.folder = folder_path
            if part.name == "archive":
                upload.archive = where
                upload.filename = part.filename
            try:
                where.parent.mkdir(parents=True, exist_ok=True)
                return FileSink(where, count(part.name, folder=True), mode="xb")
            except CLASHES:
                raise invalid(part.name, f"'{part.filename}' comes twice or clashes with a folder") from None
        if part.name == "file":
            if upload.has_file:
                raise invalid("file", "more than one 'file' part: upload one model per request")
            upload.has_file = True
            upload.filename = part.filename
            return FileSink(upload.path, count("file", folder=False), sniff)
        return Buffer(part.name, max_cameras_bytes if part.name == "cameras" else MAX_NAME_BYTES,
                      lambda data: set_field(upload, part.name, data))

    await read_parts(request, separator, open_part, what="the uploaded model file", field="file")
    if upload.folder is not None or upload.archive is not None:
        return upload                   # service.folders finds the model in it
    if not upload.has_file:
        raise invalid("file", "no 'file' part: the request must include the model file (or a folder's 'files' or "
                      "'archive')")
    upload.sha256 = digest.hexdigest()
    with writing("the uploaded model file", "file"):
        await asyncio.to_thread(fsync_path, upload.path)
    return upload


def set_field(upload: Upload, name: str, data: bytes) -> None:
    """A text field of the form, once all of it is in."""
    if name == "cameras":
        upload.cameras = data
    elif name == "name":
        upload.name = data.decode("utf-8", "replace").strip() or None
    elif name == "background":
        upload.background = data
    elif name == "camera_format":
        upload.camera_format = data.decode("utf-8", "replace").strip() or None
    elif name == "other_capture":
        upload.other_capture = parse_yes(data, "other_capture")


def sniff_kind(head: bytes) -> str:
    """The model family's kind from a file's first bytes; 415 for anything else."""
    kind = model_kind(head)
    if kind is not None:
        return kind
    what = "an empty file" if not head else f"neither {family_titles('nor')}"
    if head[:1] == b"\x80" or head[:2] == b"PK":
        what = ("a Python pickle or zip archive (e.g. a torch.save file); such files can run code when loaded "
                "and are never opened (a nerfstudio or gsplat run: upload its folder with the Python client, which "
                "reads checkpoints without running code and sends the splats as a PLY)")
    raise ServiceError(415, "unsupported_model", f"the uploaded file is {what}", "file")


def parse_yes(raw: bytes, field: str) -> bool:
    """A form field that says yes or no: true/1/yes/on or false/0/no/off (empty: no)."""
    text = raw.decode("utf-8", "replace").strip().lower()
    if text not in YES + NO:
        raise invalid(field, f"must be true or false, got {text!r}")
    return text in YES


def parse_background(raw: bytes) -> tuple[float, float, float]:
    """The `background` field: a JSON colour or a bare name ("white", "black", "grey")."""
    text = raw.decode("utf-8", "replace").strip()
    try:
        value = json.loads(text)
    except JSON_ERRORS:
        value = text
    try:
        return check_color(value, "background")
    except InputError as exc:
        raise invalid("background", exc.reason) from None


def parse_camera_json(raw: bytes) -> Any:
    try:
        return json.loads(raw)
    except JSON_ERRORS as exc:
        raise invalid("cameras", f"not valid JSON: {json_problem(exc)}") from None


def unwrap_sidecar(source: Any, upload: Upload) -> Any:
    """Cameras given as the sidecar `phd train` wrote beside its PLY: its training cameras, and
    its name, background and capture format where the request gave none (the Python client's rule)."""
    if not (isinstance(source, dict) and isinstance(source.get("training_cameras"), list)):
        return source                   # a sidecar is known by its list, as phd_core.data.load_cameras knows it
    frames = source["training_cameras"]
    if upload.name is None and isinstance(source.get("name"), str):
        upload.name = source["name"]
    background = source.get("background")
    if upload.background is None and isinstance(background, list):
        upload.background, upload.background_source = json.dumps(background).encode(), SIDECAR_SOURCE
    if upload.camera_format is None and source.get("dataset_format") in FORMATS:
        upload.camera_format = source["dataset_format"]
    return frames


def guess_background(camera_format: str | None) -> tuple[tuple[float, float, float], str]:
    """The colour a splat model without a `background` field is rendered over, and why: the
    reference 3DGS trainer trains over black unless told otherwise, so its cameras.json says
    black; everything else the Blender convention's white."""
    if camera_format == "3dgs-output":
        return (0.0, 0.0, 0.0), "guessed: black, the reference trainer's default (its cameras.json came with it)"
    return (1.0, 1.0, 1.0), "guessed: white, the default for a model without a background"


def parse_camera_format(name: str | None, cameras: Any) -> str | None:
    """The `camera_format` field, checked against the capture formats; else read off the
    cameras (a reference cameras.json or transforms frames); None without cameras."""
    if name is not None:
        if name not in FORMATS:
            raise invalid("camera_format", FORMATS.unknown(name))
        return name
    if cameras is None:
        return None
    return "3dgs-output" if is_inria_cameras(cameras) else "nerfstudio"
