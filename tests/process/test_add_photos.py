"""Photos added to a capture (issue 49): registered into its reconstruction with the earlier
frames and cameras fixed, so every earlier pose, intrinsic and undistorted image stays as it
was; a photo of something else is named and, alone, changes nothing. Real photos: cup_colmap's,
at 300 px."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np
import pytest

from phd_core.data import load_dataset
from phd_core.data.colmap import read_model
from phd_core.errors import InputError
from phd_core.process import add_photos, run_capture
from phd_core.process.capture import REPORT, read_report
from support.alignment import relative_residual
from support.cli import run

CUP = Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap"
OTHER = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "flask_desk" / "images"
FIRST, MORE = range(18, 34), range(34, 41)        # consecutive photos (tests/cli/test_cli_capture_photos.py)


def folder_of(root: Path, numbers: range | list[int], extra: Sequence[Path] = ()) -> Path:
    root.mkdir()
    for n in numbers:
        shutil.copy(CUP / "images" / f"{n}.jpg", root)
    for path in extra:
        shutil.copy(path, root)
    return root


def tree_digest(folder: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(folder)).encode() + path.read_bytes())
    return digest.hexdigest()


@pytest.fixture(scope="module")
def first(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("add")
    out = root / "cup"
    run_capture(folder_of(root / "first", FIRST), out, max_size=300)
    return out


@pytest.fixture(scope="module")
def grown(first, tmp_path_factory) -> tuple[Path, dict, object]:
    root = tmp_path_factory.mktemp("grown")
    capture = root / "cup"
    shutil.copytree(first, capture)
    other = sorted(OTHER.iterdir())[0]
    report = add_photos(capture, folder_of(root / "more", MORE, [other]), max_size=300)
    return capture, {"report": report, "other": other.name}, read_model(first / "sparse" / "0")


def poses(model) -> dict[str, tuple]:
    return {image.name: (image.qvec, image.tvec) for image in model.images}


def test_added_photos_register_and_the_earlier_poses_do_not_move(grown, first) -> None:
    capture, found, before = grown
    report = found["report"]
    assert report.added == [f"{n}.jpg" for n in MORE]                 # measured: all seven
    assert report.not_registered == [found["other"]] and found["other"] in " ".join(report.notes)
    after = read_model(capture / "sparse" / "0")
    old = poses(before)
    for name, (qvec, tvec) in poses(after).items():
        if name in old:
            assert np.allclose(qvec, old[name][0], atol=1e-9) and np.allclose(tvec, old[name][1], atol=1e-9), name
    # The cameras keep their intrinsics (bundle adjustment moved the focal length by 0.4 % before
    # they were held constant), so every earlier photo comes out of undistortion byte for byte.
    for model in ("sparse/0", "distorted/sparse/0"):
        cameras_before, cameras_after = read_model(first / model).cameras, read_model(capture / model).cameras
        assert cameras_after == cameras_before, model
    assert all((capture / "images" / name).read_bytes() == (first / "images" / name).read_bytes() for name in old)
    assert sorted(p.name for p in (capture / "images").iterdir()) == report.registered == sorted(
        [*old, *report.added])
    data = load_dataset(capture, "all")
    assert len(data.cameras) == len(FIRST) + len(MORE) and data.images is not None
    assert json.loads((capture / REPORT).read_text())["added"] == report.added
    assert not [p for p in capture.parent.iterdir() if p.name.startswith(".")]      # no partial folder left


def test_the_new_cameras_sit_where_the_captures_own_colmap_puts_them(grown) -> None:
    """After the best similarity our centres (16 photos, then 7 added) and the published model's
    differ by a few % of their spread, as a from-scratch capture's do (test_cli_capture_photos)."""
    capture, _, _ = grown
    ours = load_dataset(capture, "all", with_images=False)
    theirs = load_dataset(CUP, "all", with_images=False)
    assert ours.names is not None and theirs.names is not None          # COLMAP captures name their images
    centre = {name: camera.c2w[:3, 3].double().numpy() for name, camera in zip(theirs.names, theirs.cameras)}
    a = np.array([camera.c2w[:3, 3].double().numpy() for camera in ours.cameras])
    b = np.array([centre[name] for name in ours.names])
    assert relative_residual(a, b) < 0.1
    added = [i for i, name in enumerate(ours.names) if int(name.split(".")[0]) in MORE]
    assert relative_residual(a[added], b[added]) < 0.1


def test_photos_of_another_size_get_cameras_of_their_own(first, tmp_path) -> None:
    """At 360 px the new photos cannot share the capture's 300 px camera: each gets its own,
    whose focal length is estimated (from COLMAP's prior of 1.2 x 360 = 432 px to about the
    capture's 188 px x 360 / 300), while the capture's camera stays as it was."""
    capture = tmp_path / "cup"
    shutil.copytree(first, capture)
    report = add_photos(capture, [CUP / "images" / "34.jpg", CUP / "images" / "35.jpg"], max_size=360)
    assert report.added == ["34.jpg", "35.jpg"] and report.cameras == 3
    before, after = read_model(first / "distorted" / "sparse" / "0"), read_model(capture / "distorted" / "sparse" / "0")
    (shared,) = before.cameras
    assert after.cameras[shared] == before.cameras[shared]
    new = [camera for camera_id, camera in after.cameras.items() if camera_id != shared]
    expected = before.cameras[shared].params[0] * 360 / 300
    assert all((camera.width, camera.height) == (360, 270) for camera in new)
    assert all(abs(camera.params[0] / expected - 1) < 0.1 for camera in new), [camera.params for camera in new]
    assert len(load_dataset(capture, "all", with_images=False).cameras) == len(FIRST) + 2


def test_a_photo_of_something_else_alone_is_refused_and_nothing_changes(first, tmp_path) -> None:
    capture = tmp_path / "cup"
    shutil.copytree(first, capture)
    before = tree_digest(capture)
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    shutil.copy(sorted(OTHER.iterdir())[0], stranger / "desk.jpg")
    with pytest.raises(InputError) as refused:
        add_photos(capture, stranger, max_size=300)
    assert refused.value.field == "photos" and "desk.jpg" in refused.value.reason
    assert tree_digest(capture) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    with pytest.raises(InputError) as twice:                     # a name the capture holds already
        add_photos(capture, [CUP / "images" / "20.jpg"], max_size=300)
    assert twice.value.field == "photos" and "20.jpg" in twice.value.reason
    with pytest.raises(InputError) as full:
        add_photos(capture, [CUP / "images" / "50.jpg"], max_size=300, max_images=len(FIRST))
    assert full.value.field == "photos"
    with pytest.raises(InputError) as nowhere:
        add_photos(tmp_path, stranger)
    assert nowhere.value.field == "capture"
    assert tree_digest(capture) == before


def test_a_report_written_before_photos_could_be_added_still_reads(first, tmp_path) -> None:
    """phd_capture.json files from before `added` and `not_registered` existed load with both
    empty; a damaged one is refused by field."""
    written = json.loads((first / REPORT).read_text())
    del written["added"], written["not_registered"]
    (tmp_path / REPORT).write_text(json.dumps(written))
    report = read_report(tmp_path)
    assert report.added == [] and report.not_registered == [] and report.registered == written["registered"]
    (tmp_path / REPORT).write_text(json.dumps({**written, "unknown": 1}))
    with pytest.raises(InputError) as damaged:
        read_report(tmp_path)
    assert damaged.value.field == "capture" and "unknown" in damaged.value.reason


def test_phd_capture_add_to(first, tmp_path, capsys) -> None:
    capture = tmp_path / "cup"
    shutil.copytree(first, capture)
    code, stdout, stderr = run(capsys, "capture", CUP / "images" / "34.jpg", CUP / "images" / "35.jpg", "--add-to",
                               capture, "--max-size", 300, "--quiet")
    assert code == 0, stderr
    assert f"registered 2 of 2 photos into {capture} ({len(FIRST) + 2} in all)" in stdout
    code, _, stderr = run(capsys, "capture", OTHER / sorted(p.name for p in OTHER.iterdir())[0], "--add-to", capture,
                          "--quiet")
    assert code == 2 and "did not" not in stderr and "registered" in stderr
