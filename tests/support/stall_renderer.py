"""A renderer whose first render anywhere stalls: for tests that kill the worker running it.

The first `render` call in any process creates `marker` (atomically, so exactly one call
wins), writes its process id there and sleeps; every other call renders at once. A task
killed while it stalls and run again therefore finishes, with the inner renderer's images.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch

from phd_core.renderers import CameraView
from phd_core.scene import Camera

STALL_SECONDS = 120.0


class StallOnceRenderer:
    kind = "toy"

    def __init__(self, inner, marker: Path):
        self.inner = inner
        self.marker = str(marker)
        self.training_cameras = inner.training_cameras

    @property
    def num_units(self) -> int:
        return self.inner.num_units

    def describe(self) -> dict:
        return self.inner.describe()

    def prepare(self, camera: Camera) -> CameraView:
        return CameraView(self, camera)

    def render(self, camera: Camera, keep: torch.Tensor | None = None, signal: str = "composited") -> torch.Tensor:
        try:
            fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return self.inner.render(camera, keep, signal)
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        time.sleep(STALL_SECONDS)           # the test kills this process long before
        return self.inner.render(camera, keep, signal)
