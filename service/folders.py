"""Models uploaded as the folder their trainer wrote: what `phd train` writes (a PLY and its
sidecar `<stem>.json`) or a trainer's output folder (`phd_core.renderers.outputs`: the
reference 3DGS trainer's, nerfstudio splatfacto's, gsplat's), sent as one part per file
(`files`, each named by its path inside the folder) or as one zip (`archive`).

The folder is unpacked under the data directory's tmp/ and nowhere else: every path is
checked part by part (no absolute paths, no '..', no drive letters, at most MAX_PATH_BYTES),
a zip is opened only once its directory and every member's declared sizes keep the archive
rules (`phd_core.io.archives`: entries, inflation ratio, total), its members are written as
plain files (never links), and the bytes actually written are counted against the model-file
cap whatever its headers declare. Before anything is read, the folder's torch checkpoints
(zips themselves) are checked by the same rules and counted by what they inflate to
(`folder_bytes`): that, not the bytes on disk, is what the memory budget reserves for the
read, and past the model cap it is 413. The folder is then read with the library's own rules,
the ones the CLI and the Python client use: `read_output` for a trainer's folder, the
family's `beside` (a PLY's sidecar) for a single model file; a model from a checkpoint is
refused (413) before it is written out when its PLY would be past the cap. What comes out is
an ordinary upload: one model file with the cameras, background and pose convention that form
fields would carry, checked and stored by the same code as any other. Every failure is a 4xx
naming the file and the rule.
"""

from __future__ import annotations

import re
import shutil
import zipfile
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Iterator

from phd_core.data import FORMATS
from phd_core.errors import InputError, TooLarge, shown
from phd_core.io.archives import DAMAGED, ZipRules, open_zip
from phd_core.io.cache import ModelCache, calibration_entries, content_digest
from phd_core.io.foreign import CHECKPOINT_SUFFIXES, checkpoint_bytes
from phd_core.renderers import SNIFF_BYTES, accepts_background, family_of, family_titles
from phd_core.renderers.outputs import OUTPUTS, read_output
from phd_core.renderers.splats import ply_bytes, write_ply  # trainers' folders hold splats

from .errors import insufficient_storage, invalid

MAX_FOLDER_FILES = 10_000       # files in one uploaded folder, entries in one zip
MAX_PATH_PARTS = 32             # folders deep
MAX_PATH_BYTES = 1024           # a path inside the folder (each name at most 255, the file systems' limit): with
                                # the server's data directory before it, within the system's 4,096
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
    # Calibrations `phd` stored beside the model (its .phd-cache/) for this model file's content;
    # used when one was made on the training cameras and background stored (service.state).
    calibrations: list[dict] = field(default_factory=list)


def relative_path(name: str | None, where: str) -> PurePosixPath:
    """A path inside the folder from a part's filename or a zip member's name; 422 for anything
    that could point elsewhere."""
    if not name:
        raise invalid(where, "a folder's file came without its name: name each part by its path inside the folder")
    text = name.replace("\\", "/")
    parts = [part for part in text.split("/") if part not in ("", ".")]
    if len(text.encode()) > MAX_PATH_BYTES or any(len(part.encode()) > 255 for part in parts):
        raise invalid(where, f"{shown(name)} is longer than a path inside the folder may be ({MAX_PATH_BYTES} bytes, "
                             "255 for each folder or file name)")
    if len(parts) > MAX_PATH_PARTS:
        raise invalid(where, f"{shown(name)} lies more than {MAX_PATH_PARTS} folders deep")
    if text.startswith("/") or re.match(r"^[A-Za-z]:", text) or "\x00" in text or not parts or ".." in parts:
        raise invalid(where, f"{shown(name)} is not a path inside the folder")
    return PurePosixPath(*parts)


def folder_target(folder: Path, part: str, filename: str | None, count: int) -> Path:
    """Where an upload part of a folder is written: an `archive` beside the folder, each of
    `files` under its own path inside it."""
    if part == "archive":
        return folder.with_name(folder.name + ".zip")
    if count >= MAX_FOLDER_FILES:
        raise invalid("files", f"more than {MAX_FOLDER_FILES} files: upload the model with its cameras only")
    return folder / relative_path(filename, "files")


def unpack_zip(archive: Path, folder: Path, max_bytes: int, room: int, name: str = "the zip") -> int:
    """Write the files of the zip (called `name`) under `folder`; the bytes written. Refused
    before anything is written: a zip past the archive rules (InputError; TooLarge when it
    declares more than `max_bytes`), one that holds no files, a path not inside the folder.
    While writing: past `max_bytes` really inflated (TooLarge), past `room` (the disk's free
    bytes less what is kept free: 507), a damaged member (InputError naming it)."""
    with open_zip(archive, ZipRules(max_entries=MAX_FOLDER_FILES, max_bytes=max_bytes), name) as zipped:
        members = [m for m in zipped.infolist() if not m.is_dir() and not any(
            part in SKIPPED for part in m.filename.replace("\\", "/").split("/"))]
        if not members:
            raise InputError(name, "holds no files: zip the trainer's output folder")
        targets = [folder / relative_path(member.filename, "archive") for member in members]
        written = 0
        for member, target in zip(members, targets):
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                out = open(target, "xb")
            except CLASHES:
                raise InputError(name, f"{shown(member.filename)} comes twice or clashes with a folder") from None
            with out:
                for chunk in _inflated(zipped, member, name):
                    written += len(chunk)
                    if written > room:
                        raise insufficient_storage(f"the zip's files (more than {room} bytes)", "archive",
                                                   "the service's disk has no more room outside the space it keeps "
                                                   "free (PHD_KEEP_FREE_BYTES)")
                    if written > max_bytes:
                        raise TooLarge(name, f"its files inflate past {max_bytes} bytes, the most this service's "
                                             "memory budget can read (leave out the images: the model and its "
                                             "cameras are enough)")
                    out.write(chunk)
    return written


def _inflated(zipped: zipfile.ZipFile, member: zipfile.ZipInfo, name: str) -> Iterator[bytes]:
    """The member's bytes as they inflate, 1 MiB at a time; a damaged member is an InputError
    naming it (a failed write of these bytes is the caller's: the disk's, 507)."""
    try:
        with zipped.open(member) as source:
            while chunk := source.read(1 << 20):
                yield chunk
    except DAMAGED as exc:
        raise InputError(name, f"cannot unpack {shown(member.filename)}: its data is damaged ({exc})") from None


def folder_bytes(folder: Path) -> int:
    """What reading the model in `folder` may hold in memory at most: its files' bytes, a torch
    checkpoint counted by what its records inflate to (checked by the archive rules first)."""
    return sum(checkpoint_bytes(path) if path.suffix in CHECKPOINT_SUFFIXES else path.stat().st_size
               for path in folder.rglob("*") if path.is_file())


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


def read_folder(folder: Path, name: str | None, ply: Path, max_bytes: int) -> FolderModel:
    """The model in an unpacked folder (named `name`, the zip's, when its files sit at the top); splats
    a trainer stored in its own frame are written, moved into the user's, to `ply`, unless
    that file would be past `max_bytes` (TooLarge)."""
    output_folder = find_output(folder)
    if output_folder is not None:
        # A capture the run names is read only from the upload; its notes come back in the output
        # (shown with the model), never issued as Python warnings.
        output = read_output(output_folder, within=folder, warn=False)
        if output.ply is None:
            size = ply_bytes(output.model)
            if size > max_bytes:
                raise TooLarge(str(output.source.relative_to(folder)), f"its model of {output.model.num_splats} splats "
                               f"takes {size} bytes as a PLY, more than the {max_bytes} this service's memory "
                               "budget can load")
            write_ply(output.model, ply)
        title = next(o.title for o in OUTPUTS.in_order() if o.detect(output_folder))
        # The run's name as the reader gives it ("<experiment>/<method>", "<folder>/gsplat", ...), as
        # the client names it; a run whose files sit at the upload's top names the upload instead of
        # the server's temp folder.
        run = output.name.replace(folder.resolve().name, name or "folder")
        return with_calibrations(FolderModel(output.ply or ply, run,
                                             [c.to_frame() for c in output.cameras] or None, list(output.background),
                                             f"{title}: its trainer's setting", output.camera_format,
                                             [upload_relative(n, folder) for n in output.notes + output.warnings]),
                                 ModelCache(output_folder).dir, output.source)
    models = model_files(folder)
    if len(models) != 1:
        listed = ", ".join(str(p.relative_to(folder)) for p in models[:5]) + (" ..." if len(models) > 5 else "")
        raise invalid("files", f"the folder holds {len(models)} models ({listed}): upload one at a time"
                      if models else f"the folder holds no model: neither {family_titles('nor')} nor a trainer's "
                      "output folder (" + "; ".join(o.title for o in OUTPUTS.in_order()) + ")")
    path = models[0]
    family = family_of(path.read_bytes()[:SNIFF_BYTES])
    assert family is not None                 # model_files sniffed it
    # Named as the Name field promises: the folder the model sits in; at the upload's top, the zip's
    # name, else the sidecar's run (below), else the file's (`phd train` calls it model.ply every time).
    at_top = path.parent == folder
    result = with_calibrations(FolderModel(path, (name or path.name) if at_top else path.parent.name),
                               ModelCache(path).dir, path)
    if family.beside is None:
        return result                         # the file carries what it has (a NeRF checkpoint: its cameras)
    renderer = family.load(path.read_bytes(), path.name, None)
    extra = family.beside(path, renderer)
    if extra is renderer:
        return result                         # nothing beside it: an upload of the bare file
    facts = extra.describe()
    if at_top and name is None and isinstance(facts.get("name"), str):
        result.name = facts["name"]
    cameras = extra.training_cameras or []
    fmt = facts.get("camera_format")
    result.cameras = [c.to_frame() for c in cameras] or None
    result.camera_format = fmt if fmt in FORMATS else None
    if accepts_background(extra) and isinstance(facts.get("background"), list):
        result.background, result.background_source = facts["background"], SIDECAR_SOURCE
    return result


def with_calibrations(found: FolderModel, cache_dir: Path, source: Path) -> FolderModel:
    """`found` with the calibrations its cache folder holds for the content of `source` (the file
    the model was read from), and a note of those it holds for another."""
    found.calibrations, others = calibration_entries(cache_dir, content_digest(source))
    if others:
        found.notes.append(f"{others} calibration{'s' if others > 1 else ''} in {cache_dir.name}/ made for another "
                           "model file (or by a phd that did not record which): not used")
    return found


def remove_folder(folder: Path) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    folder.with_name(folder.name + ".zip").unlink(missing_ok=True)
