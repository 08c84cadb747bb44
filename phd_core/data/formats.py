"""The capture-format registry: each format says whether a path holds it and loads it.

`locate` tries the formats by their `order`, lowest first, and takes the first that
recognises the path, so which format wins never depends on import order:

    10 blender      transforms_{split}.json: before nerfstudio, since a Blender folder may
                    also hold a transforms.json
    20 nerfstudio   transforms.json
    30 colmap       a COLMAP sparse model
    40 llff         poses_bounds.npy
    50 3dgs-output  a reference-trainer output folder, last: it is the capture's trained
                    result, and a folder that also holds the capture itself is read as the capture

A format registered without an order is tried after these.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..registry import Registry
from .frames import Dataset


@dataclass(frozen=True)
class DataFormat:
    name: str
    locate: Callable[[Path, str], Path | None]      # (path, split) -> the file to load, or None: not this format
    load: Callable[..., Dataset]                    # (located file, split, **loading options) -> Dataset
    order: int = 100                                # detection order, lowest first (module docstring)
    looks_for: str = ""                             # what `locate` finds, for messages ("poses_bounds.npy")
    count: Callable[[Path, str], int] | None = None  # (located file, split) -> its frames, without loading
                                                    # them (None: load the cameras and count)


FORMATS: Registry[DataFormat] = Registry("capture format")
