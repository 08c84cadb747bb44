"""Cameras handed back in the convention of the source a model's cameras came from.

A capture rig or a trainer cannot act on an index into a list of candidates: it needs the
pose, in its own terms. One `PoseConvention` per source format, registered in `POSES` under
the source's name (the names of `FORMATS`), says how one camera reads in that convention
and how a batch of cameras is written as the files that source's tools read:

    convention    one pose                                          a batch on disk
    nerfstudio    a transforms.json frame: OpenGL c2w, fl_x, fl_y,   transforms.json with frames
    blender         cx, cy, w, h (our `Camera.to_frame()`)
    colmap        qvec (w, x, y, z) and tvec, world-to-camera,       a text model folder: cameras.txt,
                  OpenCV axes; a PINHOLE camera                        images.txt, points3D.txt (empty)
    3dgs-output   a cameras.json entry: OpenCV c2w rotation,         cameras.json
                  position (the centre), fx, fy, width, height

The converters live beside their format's loader (`colmap.py`, `inria.py`, `nerfstudio.py`),
which reads each back; a new source is one more `POSES.register`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from ..errors import InputError
from ..registry import Registry
from ..scene import Camera


@dataclass(frozen=True)
class PoseConvention:
    name: str
    pose: Callable[[Camera], dict[str, Any]]                          # one camera in the source's own terms
    write: Callable[[Path, Sequence[Camera], Sequence[str]], None]    # a batch, with image names, as its file(s)
    writes: str                                                       # what `write` makes, for messages
    file_name: str | None = None       # a file of this name is written in this convention ("cameras.json")
    suffix: str | None = None          # else a file with this suffix (".json"); a path without one is a folder


POSES: Registry[PoseConvention] = Registry("pose convention")


def source_pose(camera: Camera, convention: str | None) -> dict[str, Any] | None:
    """`{"format": name, ...}`: the camera in the named convention; None when the source is
    unknown or has no converter (the camera itself is always in the project's convention)."""
    if convention is None or convention not in POSES:
        return None
    return {"format": convention, **POSES[convention].pose(camera)}


def export_convention(path: str | Path, convention: str | None = None) -> PoseConvention:
    """The convention to write `path` in: the one named, else the one its name says (a file
    named cameras.json: 3dgs-output; another .json: nerfstudio; no suffix: a COLMAP folder)."""
    if convention is not None:
        return POSES.lookup(convention, "export_format")
    path = Path(path)
    by_name = [c for c in POSES.values() if c.file_name == path.name.lower()]
    by_suffix = [c for c in POSES.values() if c.suffix is not None and c.suffix == path.suffix.lower()]
    if by_name or by_suffix:
        return (by_name or by_suffix)[0]
    raise InputError("export", f"cannot tell the format of {path.name!r} from its name: give the format ("
                     + ", ".join(f"{c.name}: {c.writes}" for c in POSES.values()) + ")")


def candidate_name(rank: int, index: int) -> str:
    """The image a ranked candidate asks for: sorts in capture order and names the candidate
    (`phd rank --export` and the service's pose download name them alike)."""
    return f"rank{rank:03d}_candidate{index:04d}.png"


def export_cameras(path: str | Path, cameras: Sequence[Camera], names: Sequence[str],
                   convention: str | None = None) -> PoseConvention:
    """Write `cameras` (image `names`, one each) at `path` as the convention's file(s)."""
    if len(cameras) != len(names) or not cameras:
        raise InputError("export", f"need one name per camera and at least one camera, got {len(cameras)} "
                         f"cameras and {len(names)} names")
    chosen = export_convention(path, convention)
    chosen.write(Path(path), cameras, names)
    return chosen
