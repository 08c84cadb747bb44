"""What `phd capture` makes of the photos it is given, before structure-from-motion: their
capture order and names (COLMAP's sequential matcher pairs by name), the matcher rule, and
each photo written upright and bounded, or refused when it cannot be read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import ExifTags, Image

from phd_core.errors import InputError
from phd_core.process.capture import EXHAUSTIVE_MAX, choose_matcher
from phd_core.process.photos import capture_order, input_names, write_photo


def ordered(*names: str) -> tuple[list[str], bool]:
    photos, numbered = capture_order([Path("photos") / name for name in names])
    return [p.name for p in photos], numbered


def test_numbered_photos_follow_their_numbers_and_get_names_that_sort_so() -> None:
    names, numbered = ordered("10.jpg", "2.jpg", "1.jpg", "9.jpg")
    assert numbered and names == ["1.jpg", "2.jpg", "9.jpg", "10.jpg"]
    written = input_names([Path(n) for n in names], numbered)
    assert written == ["01.jpg", "02.jpg", "09.jpg", "10.jpg"] == sorted(written)


def test_names_that_already_sort_in_capture_order_are_kept() -> None:
    names, numbered = ordered("IMG_0010.JPG", "IMG_0002.JPG", "IMG_0100.JPG")
    assert numbered and input_names([Path(n) for n in names], numbered) == ["IMG_0002.JPG", "IMG_0010.JPG",
                                                                              "IMG_0100.JPG"]


def test_several_numbers_in_a_name_order_left_to_right() -> None:
    names, numbered = ordered("image_20260209_153634_308.jpg", "image_20260209_153633_828.jpg",
                              "image_20260209_153633_9.jpg")
    assert numbered and names == ["image_20260209_153633_9.jpg", "image_20260209_153633_828.jpg",
                                  "image_20260209_153634_308.jpg"]
    assert input_names([Path(n) for n in names], numbered) == [
        "image_20260209_153633_009.jpg", "image_20260209_153633_828.jpg", "image_20260209_153634_308.jpg"]


def test_names_that_differ_in_more_than_numbers_are_an_unordered_set() -> None:
    names, numbered = ordered("side view.jpg", "front2.jpg", "back.jpg")
    assert not numbered and names == ["back.jpg", "front2.jpg", "side view.jpg"]
    assert input_names([Path(n) for n in names], numbered) == ["back.jpg", "front2.jpg", "side_view.jpg"]


def test_two_photos_that_would_get_one_name_are_refused_by_name() -> None:
    names, numbered = ordered("7.jpg", "007.jpg", "12.jpg")
    with pytest.raises(InputError, match="7.jpg and 007.jpg|007.jpg and 7.jpg"):
        input_names([Path(n) for n in names], numbered)


def test_the_matcher_rule() -> None:
    assert choose_matcher("auto", video=True, ordered=True, count=300)[0] == "sequential"
    assert choose_matcher("auto", video=False, ordered=True, count=300)[0] == "sequential"
    assert choose_matcher("auto", video=False, ordered=False, count=EXHAUSTIVE_MAX)[0] == "exhaustive"
    with pytest.raises(InputError, match="no known order") as refused:
        choose_matcher("auto", video=False, ordered=False, count=EXHAUSTIVE_MAX + 1)
    assert refused.value.field == "matcher"
    assert choose_matcher("exhaustive", video=False, ordered=False, count=EXHAUSTIVE_MAX + 1)[0] == "exhaustive"
    assert choose_matcher("sequential", video=False, ordered=False, count=3)[0] == "sequential"


def half_white(width: int, height: int) -> np.ndarray:
    """[height, width, 3] uint8: the left half white, the right half black."""
    pixels = np.zeros((height, width, 3), np.uint8)
    pixels[:, : width // 2] = 255
    return pixels


def test_a_photo_is_written_upright_as_its_exif_orientation_says(tmp_path) -> None:
    """EXIF orientation 6: the stored pixels are shown turned 90 degrees clockwise, so the
    stored left half is the top half of the upright photo."""
    exif = Image.Exif()
    exif[ExifTags.Base.Orientation] = 6
    exif[ExifTags.Base.Make] = "test"
    Image.fromarray(half_white(40, 20)).save(tmp_path / "in.jpg", exif=exif, quality=100)
    size, downscaled = write_photo(tmp_path / "in.jpg", tmp_path / "out.jpg", max_size=1600)
    with Image.open(tmp_path / "out.jpg") as out:
        pixels = np.asarray(out.convert("L"), np.float64)
        assert size == out.size == (20, 40) and not downscaled
        assert out.getexif().get(ExifTags.Base.Orientation, 1) == 1
        assert out.getexif().get(ExifTags.Base.Make) == "test"            # the rest of the EXIF kept
    assert pixels[:18].mean() > 240 and pixels[22:].mean() < 15


def test_a_large_photo_is_downscaled_and_a_small_one_copied_byte_for_byte(tmp_path) -> None:
    Image.fromarray(half_white(400, 300)).save(tmp_path / "large.png")
    assert write_photo(tmp_path / "large.png", tmp_path / "large_out.png", max_size=100) == ((100, 75), True)
    with Image.open(tmp_path / "large_out.png") as out:
        assert out.format == "PNG" and out.size == (100, 75)
    Image.fromarray(half_white(80, 60)).save(tmp_path / "small.jpg")
    assert write_photo(tmp_path / "small.jpg", tmp_path / "small_out.jpg", max_size=100) == ((80, 60), False)
    assert (tmp_path / "small_out.jpg").read_bytes() == (tmp_path / "small.jpg").read_bytes()


def test_an_unreadable_photo_is_refused_by_name(tmp_path) -> None:
    Image.fromarray(half_white(80, 60)).save(tmp_path / "whole.jpg")
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "whole.jpg").read_bytes()[:300])
    (tmp_path / "text.jpg").write_text("not a photo")
    for name in ("cut.jpg", "text.jpg"):
        with pytest.raises(InputError, match=f"cannot read photo .*{name}"):
            write_photo(tmp_path / name, tmp_path / "out.jpg", max_size=100)
