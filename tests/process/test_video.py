"""A video sampled into frames (PyAV): which frames, their order and names, turned upright as
the video's display matrix says, and a file that is no video refused."""

from __future__ import annotations

import av
import numpy as np
import pytest
from PIL import Image

from phd_core.errors import InputError
from phd_core.process.video import sample_video

RATE = 10          # frames per second of the test videos


def write_video(path, frames: list[np.ndarray], rotation: int = 0) -> None:
    """H.264 at RATE frames per second, nearly lossless (crf 1)."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=RATE, options={"crf": "1"})
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        if rotation:
            stream.set_display_rotation(rotation)
        for pixels in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(pixels, format="rgb24")))
        container.mux(stream.encode())


def grey(value: int) -> np.ndarray:
    return np.full((48, 64, 3), value, np.uint8)


def brightness(path) -> float:
    with Image.open(path) as image:
        return float(np.asarray(image.convert("L"), np.float64).mean())


def test_frames_are_sampled_at_fps_or_spread_over_the_video_and_named_in_time_order(tmp_path) -> None:
    """Frame i of the video is grey 5 i, so each written frame says which one it was: 50
    frames (5 s) at 2 per second are every 5th; bounded to 4, one every 1.25 s (the first
    frame at or after 0, 1.25, 2.5, 3.75 s: frames 0, 13, 25, 38)."""
    write_video(tmp_path / "walk.mp4", [grey(5 * i) for i in range(50)])
    for fps, max_frames, expected in ((2, 300, range(0, 50, 5)), (2, 4, (0, 13, 25, 38))):
        folder = tmp_path / f"frames_{max_frames}"
        folder.mkdir()
        sampled = sample_video(tmp_path / "walk.mp4", folder, fps=fps, max_frames=max_frames, max_size=1600)
        assert sampled.names == [f"frame_{k:05d}.jpg" for k in range(1, len(expected) + 1)]
        assert sorted(p.name for p in folder.iterdir()) == sampled.names
        assert sampled.seconds == pytest.approx(5.0, abs=0.11) and sampled.size == (64, 48)
        assert [brightness(folder / name) for name in sampled.names] == pytest.approx([5 * i for i in expected], abs=2)


def test_frames_come_out_upright_and_within_max_size(tmp_path) -> None:
    """Display rotation 90 (counter-clockwise): the stored left half is the bottom half of the
    upright frame, 48 wide and 64 tall; max_size 32 then halves it."""
    stored = np.zeros((48, 64, 3), np.uint8)
    stored[:, :32] = 255
    write_video(tmp_path / "phone.mp4", [stored] * 5, rotation=90)
    sampled = sample_video(tmp_path / "phone.mp4", tmp_path, fps=RATE, max_frames=1, max_size=32)
    with Image.open(tmp_path / sampled.names[0]) as frame:
        assert frame.size == (24, 32)
        pixels = np.asarray(frame.convert("L"), np.float64)
    assert pixels[18:].mean() > 230 and pixels[:14].mean() < 25


def test_a_file_that_is_no_video_is_refused_by_name(tmp_path) -> None:
    (tmp_path / "broken.mp4").write_bytes(b"\x00not a video" * 100)
    with pytest.raises(InputError, match="cannot read video .*broken.mp4"):
        sample_video(tmp_path / "broken.mp4", tmp_path, fps=2, max_frames=10, max_size=1600)
