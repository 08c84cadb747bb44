"""`phd capture` through the real `phd` entry on real photos: 23 consecutive hand-held photos
of cup_colmap (800x600, downscaled to 300 px by --max-size) and a video made of them. What it
writes loads as a capture with PINHOLE cameras, and its camera centres match the capture's own
COLMAP model up to a similarity. Bad input is refused with exit 2 and nothing written."""

from __future__ import annotations

import json
import re
import shutil
from contextlib import redirect_stderr, redirect_stdout
from io import StringIO
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from phd_cli import main
from phd_core.data import load_dataset
from phd_core.data.colmap import read_model
from phd_core.process.capture import REPORT, STAGES
from support.alignment import relative_residual, umeyama
from support.cli import run

CUP = Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap"
PHOTOS = [f"{n}.jpg" for n in range(18, 41)]      # consecutive photos with no jump in the capture's path
MAX_SIZE = 300


def phd(*argv) -> tuple[int, str, str]:
    """`phd ARGV...` in this process (for module fixtures, where capsys is not available)."""
    out, err = StringIO(), StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("photos")
    for name in PHOTOS:
        shutil.copy(CUP / "images" / name, folder / name)
    return folder


@pytest.fixture(scope="module")
def captured(photos, tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("captures") / "cup"
    code, stdout, stderr = phd("capture", photos, "--out", out, "--max-size", MAX_SIZE, "--progress")
    assert code == 0, stderr
    return {"out": out, "stdout": stdout, "stderr": stderr, "report": json.loads((out / REPORT).read_text())}


def test_the_alignment_recovers_a_known_similarity() -> None:
    """The check below is only as good as this: s R a + t is found again, reflections refused."""
    g = np.random.default_rng(0)
    a = g.normal(size=(20, 3))
    q, _ = np.linalg.qr(g.normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    b = 2.5 * a @ rotation.T + [1.0, -2.0, 0.5]
    scale, found, translation = umeyama(a, b)
    assert scale == pytest.approx(2.5) and np.allclose(found, rotation) and np.allclose(translation, [1, -2, 0.5])
    assert relative_residual(a, b) < 1e-12
    assert relative_residual(a * [1, 1, -1], b) > 0.1                  # a mirror image is no similarity


def test_real_photos_become_a_capture_that_loads_with_pinhole_cameras(captured) -> None:
    report, out = captured["report"], captured["out"]
    registered = report["registered"]
    assert f"registered {len(registered)} of {len(PHOTOS)} photos" in captured["stdout"]
    assert len(registered) >= 20                              # measured: 23 of 23
    assert report["matcher"] == "sequential" and report["source"] == "photos"
    assert sorted(p.name for p in (out / "images").iterdir()) == registered
    model = read_model(out / "sparse" / "0")
    assert {camera.model for camera in model.cameras.values()} == {"PINHOLE"}
    assert [image.name for image in model.images] == registered
    assert {camera.model for camera in read_model(out / "distorted" / "sparse" / "0").cameras.values()} == {
        "SIMPLE_RADIAL"}
    assert (out / "distorted" / "database.db").is_file()
    for name in report["origins"]:                            # the photos as COLMAP saw them: downscaled
        with Image.open(out / "input" / name) as photo:
            assert max(photo.size) == MAX_SIZE
    train = load_dataset(out, "train")
    assert train.images is not None and len(train.cameras) == len(registered) - len(range(0, len(registered), 8))
    assert train.points is not None and len(train.points) == report["points"] > 100
    assert "downscaled 23 photos to 300 px" in captured["stderr"]
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]      # no partial folder left


def test_each_stage_shows_a_progress_bar_and_reports_its_seconds(captured) -> None:
    for stage in STAGES[:-1]:                                         # the load check is quick: no bar
        assert re.search(rf"(?:^|\r){stage}: +\d+%\|", captured["stderr"], re.MULTILINE), stage
    assert list(captured["report"]["seconds"]) == list(STAGES)
    assert all(seconds >= 0 for seconds in captured["report"]["seconds"].values())


def test_recovered_cameras_match_the_captures_own_colmap_poses(captured) -> None:
    """The capture's own model (COLMAP at 800x600, all 77 photos, a camera per photo) and ours
    (23 photos at 300 px, one shared camera) place the cameras alike: after the best
    similarity the centres differ by 3 % of their spread (measured), against ~100 % for
    centres that do not correspond."""
    ours = load_dataset(captured["out"], "all", with_images=False)
    theirs = load_dataset(CUP, "all", with_images=False)
    assert ours.names is not None and theirs.names is not None
    centre = {name: camera.c2w[:3, 3].double().numpy() for name, camera in zip(theirs.names, theirs.cameras)}
    origins = captured["report"]["origins"]
    a = np.array([camera.c2w[:3, 3].double().numpy() for camera in ours.cameras])
    b = np.array([centre[Path(origins[name]).name] for name in ours.names])
    assert len(a) >= 20
    assert relative_residual(a, b) < 0.1
    assert relative_residual(a, np.roll(b, 5, axis=0)) > 0.5          # the same centres, mismatched


def make_video(photos: Path, path: Path) -> None:
    """The photos as an H.264 video at 2 frames per second, 320x240 (crf 12: what a phone keeps)."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=2, options={"crf": "12"})
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuv420p"
        for name in PHOTOS:
            with Image.open(photos / name) as photo:
                frame = av.VideoFrame.from_image(photo.convert("RGB").resize((320, 240), Image.Resampling.LANCZOS))
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


def test_a_video_is_sampled_and_captured_over_an_earlier_capture(captured, photos, tmp_path, capsys) -> None:
    """--overwrite replaces an earlier capture (a copy of the photos' one) with the video's."""
    make_video(photos, tmp_path / "cup.mp4")
    out = tmp_path / "cup"
    shutil.copytree(captured["out"], out)
    code, stdout, stderr = run(capsys, "capture", tmp_path / "cup.mp4", "--out", out, "--fps", 2, "--overwrite",
                               "--quiet")
    assert code == 0, stderr
    report = json.loads((out / REPORT).read_text())
    assert report["source"] == "video" and report["inputs"] == len(PHOTOS) and report["matcher"] == "sequential"
    assert f"registered {len(report['registered'])} of {len(PHOTOS)} frames" in stdout
    assert len(report["registered"]) >= 20
    assert sorted(p.name for p in (out / "input").iterdir()) == [f"frame_{k:05d}.jpg" for k in range(1, 24)]
    assert "%|" not in stderr                                                   # --quiet: no bars
    assert len(load_dataset(out, "all", with_images=False).cameras) == len(report["registered"])


# ----------------------------------------------------------------------------- refusals

def refused(capsys, *argv) -> str:
    """stderr of a `phd capture` that must exit 2 (InputError) and leave nothing behind."""
    out = Path(argv[argv.index("--out") + 1])
    existed = out.exists()
    code, _, err = run(capsys, "capture", *argv)
    assert code == 2 and err.startswith("phd capture: error: "), err
    assert out.exists() == existed and not [p for p in out.parent.iterdir() if ".partial-" in p.name]
    return err


def test_too_few_photos_an_empty_folder_and_an_unreadable_photo_are_refused(photos, tmp_path, capsys) -> None:
    few = tmp_path / "few"
    few.mkdir()
    for name in PHOTOS[:5]:
        shutil.copy(photos / name, few / name)
    assert "5 images, and at least 8 must register" in refused(capsys, few, "--out", tmp_path / "a")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("a note")
    assert "holds no photos" in refused(capsys, empty, "--out", tmp_path / "b")
    (few / "0.jpg").write_bytes(b"not a photo")
    for name in PHOTOS[5:8]:
        shutil.copy(photos / name, few / name)
    assert "cannot read photo" in refused(capsys, few, "--out", tmp_path / "c")
    assert "more than max_images (5)" in refused(capsys, few, "--out", tmp_path / "d", "--max-images", 5)


def test_an_output_folder_that_holds_files_is_refused(captured, photos, tmp_path, capsys) -> None:
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "thesis.tex").write_text("mine")
    assert "exists and is not empty" in refused(capsys, photos, "--out", taken)
    assert "did not write" in refused(capsys, photos, "--out", taken, "--overwrite")
    assert (taken / "thesis.tex").read_text() == "mine"
    assert "exists and is not empty" in refused(capsys, photos, "--out", captured["out"])
    assert "lies inside" in refused(capsys, captured["out"] / "input", "--out", captured["out"], "--overwrite")


def test_an_unreadable_video_is_refused(tmp_path, capsys) -> None:
    (tmp_path / "clip.mov").write_bytes(b"\x00\x01 no video here" * 64)
    assert "cannot read video" in refused(capsys, tmp_path / "clip.mov", "--out", tmp_path / "out")


def test_photos_that_do_not_register_are_refused_after_structure_from_motion(tmp_path, capsys) -> None:
    """Ten photos of unrelated noise: SIFT finds features, no pair verifies, none registers."""
    noise = tmp_path / "noise"
    noise.mkdir()
    g = np.random.default_rng(1)
    for i in range(10):
        Image.fromarray(g.integers(0, 256, (96, 128, 3), dtype=np.uint8)).save(noise / f"n{i:02d}.png")
    err = refused(capsys, noise, "--out", tmp_path / "out")
    assert "registered 0 of 10 images, and at least 8 must" in err and "nothing was written" in err
