"""Photos for the capture-loop tests: a first set with held-out test photos, photos to add, and
a photo of something else."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

CUP = Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap" / "images"
LEGO = Path(__file__).resolve().parents[3] / "shared" / "data" / "lego_200" / "train" / "r_0.png"


@dataclass
class LoopPhotos:
    initial: Path            # a folder: the capture's first photos
    test: list[str]          # of them, those held out
    more: Path               # a folder: photos to add
    other: Path              # one photo of something else
    max_size: int            # the service's capture_max_size for them

    @property
    def initial_count(self) -> int:
        return len(list(self.initial.iterdir()))

    @property
    def more_count(self) -> int:
        return len(list(self.more.iterdir()))


def loop_photos(root: Path) -> LoopPhotos:
    initial, more = root / "initial", root / "more"
    initial.mkdir()
    more.mkdir()
    for n in range(18, 30):
        shutil.copy(CUP / f"{n}.jpg", initial)
    for n in range(30, 33):
        shutil.copy(CUP / f"{n}.jpg", more)
    other = root / "other.png"
    shutil.copy(LEGO, other)
    return LoopPhotos(initial, ["21.jpg", "25.jpg"], more, other, 300)
