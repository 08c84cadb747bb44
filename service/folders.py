"""Models uploaded as the folder their trainer wrote: what `phd train` writes (a PLY and its
sidecar `<stem>.json`) or a trainer's output folder (`phd_core.renderers.outputs`: the
reference 3DGS trainer's, nerfstudio splatfacto's, gsplat's), sent as one part per file
(`files`, each named by its path inside the folder) or as one zip (`archive`).

The folder is unpacked under the data directory's tmp/ and nowhere else: every path is
checked part by part (no absolute paths, no '..', no drive letters), a zip's members are
written as plain files (never links), and the bytes actually written are counted against
the model-file cap whatever a zip's headers declare, so a zip bomb stops at the cap. The
folder is then read with the library's own rules, the ones the CLI and the Python client
use: `read_output` for a trainer's folder, the family's `beside` (a PLY's sidecar) for a
single model file. What comes out is an ordinary upload: one model file with the cameras,
background and pose convention that form fields would carry, checked and stored by the same
code as any other.
"""

from __future__ import annotations

import re
import shutil
import warnings
import zipfile
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from phd_core.data import POSES
from phd_core.renderers import SNIFF_BYTES, accepts_background, family_of, family_titles
from phd_core.renderers.outputs import OUTPUTS, read_output
from phd_core.renderers.splats import write_ply  # trainers' folders hold splats

from .errors import ServiceError, insufficient_storage, invalid

MAX_FOLDER_FILES = 10_000       # files in one uploaded folder or zip
MAX_PATH_PARTS = 32             # folders deep
MAX_ZIP_RATIO = 500             # a member that inflates more than this is refused (a zip bomb's mark;
                                # real PLYs, checkpoints and JSON inflate well below)
SEARCH_DIRS = 2_000             # folders looked at for a trainer's output
SKIPPED = ("__MACOSX", ".DS_Store")   # what archivers add beside a folder
CLASHES = (FileExistsError, NotADirectoryError, IsADirectoryError)   # a path twice, or a file where a folder is
SIDECAR_SOURCE = "the sidecar its trainer wrote"   # a model's background_source when its sidecar set it


@dataclass
class FolderModel:
    """The model found in an uploaded folder, with what its trainer wrote beside it."""

    model: Path                               # the model file to store
    name: str                                 # the display name: the run's (or the file's) name
    cameras: list[dict] | None = None         # training cameras as frames, in the user's frame
    background: list[float] | None = None
    background_source: str | None = None
    camera_format: str | None = None
    notes: list[str] = field(default_factory=list)


def relative_path(name: str | None, where: str) -> PurePosixPath:
    """A path inside the folder from a part's filename or a zip member's name; 422 for anything
    that could point elsewhere."""
    if not name:
        raise invalid(where, "a folder's file came without its name: name each part by its path inside the folder")
    text = name.replace("\\", "/")
    parts = [part for part in text.split("/") if part not in ("", ".")]
    if (text.startswith("/") or re.match(r"^[A-Za-z]:", text) or "\x00" in text or not parts or ".." in parts
            or len(parts) > MAX_PATH_PARTS or any(len(part.encode()) > 255 for part in parts)):
        raise invalid(where, f"'{name}' is not a path inside the folder")
    return PurePosixPath(*parts)


def folder_target(folder: Path, part: str, filename: str | None, count: int) -> Path:
    """Where an upload part of a folder is written: an `archive` beside the folder, each of
    `files` under its own path inside it."""
    if part == "archive":
        return folder.with_name(folder.name + ".zip")
    if count >= MAX_FOLDER_FILES:
        raise invalid("files", f"more than {MAX_FOLDER_FILES} files: upload the model with its cameras only")
    return folder / relative_path(filename, "files")


def unpack_zip(archive: Path, folder: Path, max_bytes: int, room: int) -> int:
    """Write the zip's files under `folder`; the bytes written (at most `max_bytes`, else 413,
    and at most `room`, the disk's free bytes less what is kept free, else 507)."""
    try:
        zipped = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError):
        raise invalid("archive", "the archive is not a zip file") from None
    written = 0
    with zipped:
        members = [m for m in zipped.infolist() if not m.is_dir() and not any(
            part in SKIPPED for part in m.filename.replace("\\", "/").split("/"))]
        if len(members) > MAX_FOLDER_FILES:
            raise invalid("archive", f"the zip holds {len(members)} files, more than {MAX_FOLDER_FILES}: zip the "
                          "model with its cameras only")
        for member in members:
            target = folder / relative_path(member.filename, "archive")
            if member.flag_bits & 0x1:
                raise invalid("archive", f"'{member.filename}' is encrypted: zip the folder without a password")
            ratio = member.file_size // max(member.compress_size, 1)
            if ratio > MAX_ZIP_RATIO and member.file_size > 1 << 20:
                raise invalid("archive", f"'{member.filename}' inflates {ratio} times: refused as a zip bomb")
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                with zipped.open(member) as source, open(target, "xb") as out:
                    while chunk := source.read(1 << 20):
                        written += len(chunk)
                        if written > room:
                            raise insufficient_storage(f"the zip's files (more than {room} bytes)", "archive",
                                                       "the service's disk has no more room outside the space "
                                                       "it keeps free (PHD_KEEP_FREE_BYTES)")
                        if written > max_bytes:
                            raise ServiceError(413, "payload_too_large", f"the zip's files exceed {max_bytes} bytes, "
                                               "the largest this service's memory budget can read (leave out the "
                                               "images: the model and its cameras are enough)", "archive")
                        out.write(chunk)
            except (zipfile.BadZipFile, EOFError, NotImplementedError) as exc:
                raise invalid("archive", f"cannot unpack '{member.filename}': {exc}") from None
            except CLASHES:
                raise invalid("archive", f"'{member.filename}' comes twice or clashes with a folder") from None
    return written


def find_output(folder: Path) -> Path | None:
    """The shallowest folder under `folder` (itself included) that a trainer-output reader
    recognises, or None."""
    queue, seen = deque([folder]), 0
    while queue and seen < SEARCH_DIRS:
        here = queue.popleft()
        seen += 1
        if any(output.detect(here) for output in OUTPUTS.in_order()):
            return here
        queue.extend(sorted(p for p in here.iterdir() if p.is_dir() and p.name not in SKIPPED))
    return None


def model_files(folder: Path) -> list[Path]:
    """The files under `folder` that a model family recognises by their first bytes."""
    found = []
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and not any(s in p.parts for s in SKIPPED)):
        with open(path, "rb") as f:
            if family_of(f.read(SNIFF_BYTES)) is not None:
                found.append(path)
    return found


def upload_relative(text: str, folder: Path) -> str:
    """`text` (a reader's message or note) with the upload folder's server path left out, so a
    message names the upload's own files, never where the server unpacked them."""
    for root in dict.fromkeys((str(folder.resolve()), str(folder))):
        text = text.replace(root + "/", "").replace(root, "the upload")
    return text


def read_folder(folder: Path, name: str, ply: Path) -> FolderModel:
    """The model in an unpacked folder (named `name` when its files sit at the top); splats
    a trainer stored in its own frame are written, moved into the user's, to `ply`."""
    output_folder = find_output(folder)
    if output_folder is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")       # the same notes come back in the output, shown with the model
            output = read_output(output_folder, within=folder)   # a capture it names is read only from the upload
        if output.ply is None:
            write_ply(output.model, ply)
        title = next(o.title for o in OUTPUTS.in_order() if o.detect(output_folder))
        # The run's name as the reader gives it ("<experiment>/<method>", "<folder>/gsplat", ...), as
        # the client names it; a run whose files sit at the upload's top names the upload instead of
        # the server's temp folder.
        run = output.name.replace(folder.resolve().name, name)
        return FolderModel(output.ply or ply, run,
                           [c.to_frame() for c in output.cameras] or None, list(output.background),
                           f"{title}: its trainer's setting", output.camera_format,
                           [upload_relative(n, folder) for n in output.notes + output.warnings])
    models = model_files(folder)
    if len(models) != 1:
        listed = ", ".join(str(p.relative_to(folder)) for p in models[:5]) + (" ..." if len(models) > 5 else "")
        raise invalid("files", f"the folder holds {len(models)} models ({listed}): upload one at a time"
                      if models else f"the folder holds no model: neither {family_titles('nor')} nor a trainer's "
                      "output folder (" + "; ".join(o.title for o in OUTPUTS.in_order()) + ")")
    path = models[0]
    family = family_of(path.read_bytes()[:SNIFF_BYTES])
    assert family is not None                 # model_files sniffed it
    result = FolderModel(path, path.name)
    if family.beside is None:
        return result                         # the file carries what it has (a NeRF checkpoint: its cameras)
    renderer = family.load(path.read_bytes(), path.name, None)
    extra = family.beside(path, renderer)
    if extra is renderer:
        return result                         # nothing beside it: an upload of the bare file
    facts = extra.describe()
    cameras = extra.training_cameras or []
    fmt = facts.get("camera_format")
    result.cameras = [c.to_frame() for c in cameras] or None
    result.camera_format = fmt if fmt in POSES else None
    if accepts_background(extra) and isinstance(facts.get("background"), list):
        result.background, result.background_source = facts["background"], SIDECAR_SOURCE
    return result


def remove_folder(folder: Path) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    folder.with_name(folder.name + ".zip").unlink(missing_ok=True)
