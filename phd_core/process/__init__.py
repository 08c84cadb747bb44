"""Photos or a video in, a capture out: structure-from-motion with pycolmap (`run_capture`,
the `phd capture` command), writing the COLMAP folder every other command reads.

`photos` finds, orders and bounds the photos; `video` samples a video's frames; `sfm` runs
COLMAP's stages; `capture` puts them together and reports what they did.
"""

from . import capture
from .capture import CaptureReport, add_photos, run_capture

__all__ = ["CaptureReport", "add_photos", "capture", "run_capture"]
