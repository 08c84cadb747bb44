"""Photos for the capture-loop tests, rendered by the project (bench.loop_scene's generated
scene): a ring of 12 as the first photos, 8 of them held out as test photos, 2 more between
them to add, and a photo of something else (lego)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from bench.loop_scene import GeneratedScene

LEGO = Path(__file__).resolve().parents[3] / "shared" / "data" / "lego_200" / "train" / "r_0.png"
SEED = 0                 # every photo registers (seeds 0-9: 8 register all 12; bench/loop_scene.py)


@dataclass
class LoopPhotos:
    initial: Path            # a folder: the capture's first photos
    test: list[str]          # of them, those held out
    more: Path               # a folder: photos to add
    other: Path              # one photo of something else
    max_size: int            # the service's capture_max_size for them

    @property
    def sfm(self) -> dict[str, object]:
        """Structure-from-motion's settings for them: renders have no lens distortion (SIMPLE_PINHOLE,
        tests/bench/test_loop_scene.py), and 4 photos registered are enough for these tests."""
        return {"min_registered": 4, "camera_model": "SIMPLE_PINHOLE"}

    @property
    def initial_count(self) -> int:
        return len(list(self.initial.iterdir()))

    @property
    def more_count(self) -> int:
        return len(list(self.more.iterdir()))


def loop_photos(root: Path) -> LoopPhotos:
    scene = GeneratedScene(SEED)
    names = [f"view_{k:02d}.png" for k in range(12)]
    scene.write_photos(scene.ring(12), root / "initial", names)
    scene.write_photos(scene.ring(12, phase=0.5)[:2], root / "more", ["new_00.png", "new_01.png"])
    other = root / "lego.png"
    shutil.copy(LEGO, other)
    return LoopPhotos(root / "initial", [name for k, name in enumerate(names) if k % 3], root / "more", other, 300)
