"""A video sampled into frames for structure-from-motion, with PyAV (FFmpeg's decoders in
process; phones' H.264 and HEVC included).

At most `fps` frames per second of video and at most `max_frames` frames, spread evenly over
the whole video: frame k is the first decoded frame at or after k * step seconds, where step
is 1 / fps, or longer when the video would give more than `max_frames`. Frames are written
upright (a phone's rotation metadata applied) as `frame_00001.jpg`, ... in time order, so the
names sort in capture order, at most `max_size` px on the longer side (Lanczos), JPEG quality 95.

Everything is bounded from the container's header before a frame is decoded: the frame size
(photos.MAX_PIXELS) and the number of frames; a video whose length is unknown, that holds no
video stream, or that fails to decode is refused, naming the file and FFmpeg's reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import av
import numpy as np
from PIL import Image

from ..errors import InputError
from .photos import JPEG_QUALITY, MAX_PIXELS


@dataclass(frozen=True)
class Sampled:
    names: list[str]              # the frames written, in time order
    seconds: float                # the video's length
    size: tuple[int, int]         # its frame size (width, height) as stored
    step: float                   # seconds between sampled frames


def sample_video(path: Path, folder: Path, *, fps: float, max_frames: int, max_size: int,
                 progress: Callable[[float], None] | None = None) -> Sampled:
    """Write the sampled frames of the video at `path` into `folder` (the module docstring)."""
    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError) as exc:
        raise InputError("inputs", f"cannot read video {path}: {exc}") from None
    with container:
        if not container.streams.video:
            raise InputError("inputs", f"{path} holds no video stream")
        stream = container.streams.video[0]
        width, height = stream.codec_context.width, stream.codec_context.height
        if not 0 < width * height <= MAX_PIXELS:
            raise InputError("inputs", f"{path}'s frames are {width}x{height}: expected 1 to {MAX_PIXELS:,} pixels")
        seconds = _length(container, stream)
        if seconds is None:
            raise InputError("inputs", f"{path} does not say how long it is: re-encode it (e.g. ffmpeg -i IN OUT.mp4)")
        count = max(1, min(max_frames, math.ceil(seconds * fps)))
        step = max(1 / fps, seconds / count)
        start = float(stream.start_time * stream.time_base) if stream.start_time and stream.time_base else 0.0
        stream.thread_type = "AUTO"
        names: list[str] = []
        try:
            for frame in container.decode(stream):
                if frame.time is None or frame.time - start < len(names) * step - 1e-6:
                    continue
                names.append(f"frame_{len(names) + 1:05d}.jpg")
                _upright(frame, max_size).save(folder / names[-1], quality=JPEG_QUALITY)
                if progress is not None:
                    progress(len(names) / count)
                if len(names) == count:
                    break
        except av.FFmpegError as exc:
            raise InputError("inputs", f"cannot decode video {path} after {len(names)} sampled frames: {exc}") from None
    if not names:
        raise InputError("inputs", f"no frame of video {path} could be decoded")
    return Sampled(names, seconds, (width, height), step)


def _length(container: av.container.InputContainer, stream: av.video.stream.VideoStream) -> float | None:
    """The video stream's length in seconds, else the container's; None when neither says."""
    if stream.duration is not None and stream.time_base is not None:
        return float(stream.duration * stream.time_base)
    if container.duration is not None:
        return container.duration / av.time_base
    return None


def _upright(frame: av.VideoFrame, max_size: int) -> Image.Image:
    """The frame as an RGB image, turned as the video's display matrix says, within max_size."""
    pixels = frame.to_ndarray(format="rgb24")                        # [H, W, 3] uint8
    turns = round(frame.rotation / 90) % 4                           # counter-clockwise quarter turns
    image = Image.fromarray(np.ascontiguousarray(np.rot90(pixels, turns)))
    if max(image.size) > max_size:
        image.thumbnail((max_size, max_size), Image.Resampling.LANCZOS)
    return image
