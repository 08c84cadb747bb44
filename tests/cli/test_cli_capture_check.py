"""The wrong capture caught: a model `phd train` fitted to lego_200 is refused donut_200 (the same
kind of cameras around another object) by every command that takes --data, with both captures
and the measured fit named, and so is a capture with lego's names and poses but donut's photos;
the same capture moved elsewhere is known by its fingerprint; --other-capture goes on with a
note; a command without --data uses the capture the sidecar names; a sidecar written before the
fingerprint is checked by its path and a fit measured now. `phd candidates frames` writes a
capture's own frames, exactly, for `phd rank`."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from phd_cli import main
from phd_core.data import load_dataset, select_views
from phd_core.renderers import load_model
from phd_core.renderers.provenance import FIT_MARGIN, measure_fit
from support.cli import run
from support.fixtures import LEGO

DONUT = LEGO.parent / "donut_200"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """4 lego views at 50 px, 100 iterations (about 20 s): it fits its training views some 9 dB
    better than donut's photos, past FIT_MARGIN."""
    out = tmp_path_factory.mktemp("capture_check") / "lego.ply"
    assert main(["train", "--data", str(LEGO), "--views", "4", "--downscale", "4", "--iterations", "100",
                 "--out", str(out), "--quiet"]) == 0
    return out


def sidecar(model: Path) -> dict:
    return json.loads(model.with_suffix(".json").read_text())


def fits_named(err: str) -> tuple[str, str]:
    """The given capture's fit and the model's own, as the refusal states them (in dB, to 0.1)."""
    found = re.search(r"render at ([\d.]+) dB PSNR against its photos, [\d.]+ dB below the ([\d.]+) dB", err)
    assert found, err
    return found.group(1), found.group(2)


def moved_copy(root: Path, images: bool) -> Path:
    """lego_200 at another path: its transforms files, with its image folders linked (or only the
    first training image, from which Blender frames take their size)."""
    root.mkdir()
    for split in ("train", "val", "test"):
        shutil.copy(LEGO / f"transforms_{split}.json", root)
        if images:
            (root / split).symlink_to(LEGO / split)
    if not images:
        (root / "train").mkdir()
        shutil.copy(LEGO / "train" / "r_0.png", root / "train")
    return root


def test_another_capture_is_refused_by_every_command_naming_both_and_the_fit(model, capsys, tmp_path) -> None:
    recorded = sidecar(model)
    assert Path(recorded["dataset"]) == LEGO.resolve() and recorded["training_fit"]["frames"]
    given = measure_fit(load_model(model), DONUT)
    assert given.psnr < recorded["training_fit"]["psnr"] - FIT_MARGIN          # what the margin is for
    for argv in (["render", "--views", 1, "--out", tmp_path / "render"],
                 ["uq", "--views", 1, "--dropout-ratio", 0.3, "--samples", 2, "--out", tmp_path / "uq"],
                 ["calibrate", "--views", 2, "--samples", 2]):
        code, _, err = run(capsys, argv[0], "--model", model, "--data", DONUT, *argv[1:])
        assert code == 2 and "error: data:" in err, err
        assert f"{DONUT} is not the capture {model} was trained on ({LEGO.resolve()}): it holds none of the " \
               "model's 4 training views" in err
        assert fits_named(err) == (f"{given.psnr:.1f}", f"{recorded['training_fit']['psnr']:.1f}")
        assert "--other-capture" in err
    assert not (tmp_path / "render").exists() and not (tmp_path / "uq").exists()


def test_other_photos_at_the_models_own_names_and_poses_are_refused_by_their_fit(model, capsys, tmp_path) -> None:
    """lego's transforms with donut's photos: the fingerprint (names and poses) is lego's, the fit is not."""
    swapped = tmp_path / "swapped"
    swapped.mkdir()
    shutil.copy(LEGO / "transforms_train.json", swapped)
    (swapped / "train").symlink_to(DONUT / "train")
    code, _, err = run(capsys, "calibrate", "--model", model, "--data", swapped, "--views", 2, "--samples", 2)
    assert code == 2 and f"error: data: {swapped} has the image names and poses of {LEGO.resolve()}" in err, err
    given, own = fits_named(err)
    assert float(given) < float(own) - FIT_MARGIN and own == f"{sidecar(model)['training_fit']['psnr']:.1f}"


def test_the_same_capture_moved_is_known_by_its_fingerprint(model, capsys, tmp_path) -> None:
    # Only the first image is there: a photo fit could not be measured, so the fingerprint decided.
    poses_only = moved_copy(tmp_path / "poses_only", images=False)
    code, out, err = run(capsys, "calibrate", "--model", model, "--data", poses_only, "--views", 2, "--samples", 2)
    assert code == 0 and "r_drop" in out and "note" not in err, err
    moved = moved_copy(tmp_path / "moved", images=True)
    code, _, err = run(capsys, "render", "--model", model, "--data", moved, "--views", 1, "--out", tmp_path / "r")
    assert code == 0 and "note" not in err, err
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["data"] == str(moved)


def test_other_capture_goes_on_with_a_note(model, capsys, tmp_path) -> None:
    code, _, err = run(capsys, "render", "--model", model, "--data", DONUT, "--views", 1, "--other-capture",
                       "--out", tmp_path / "r")
    assert code == 0 and "note:" in err and "is not the capture" in err and "--other-capture: going on" in err
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["data"] == str(DONUT)


def test_commands_without_data_use_the_capture_the_sidecar_names(model, capsys, tmp_path) -> None:
    code, _, err = run(capsys, "render", "--model", model, "--views", 2, "--out", tmp_path / "r")
    assert code == 0, err
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["data"] == str(LEGO.resolve()) and metrics["split"] == "test" and len(metrics["views"]) == 2
    code, _, err = run(capsys, "uq", "--model", model, "--views", 1, "--dropout-ratio", 0.3, "--samples", 2,
                       "--no-heatmaps", "--out", tmp_path / "uq")
    assert code == 0, err
    assert json.loads((tmp_path / "uq" / "report.json").read_text())["data"] == str(LEGO.resolve())


def test_an_old_sidecar_is_checked_by_its_path_and_a_fit_measured_now(model, capsys, tmp_path) -> None:
    """A sidecar from before the fingerprint names its capture by path alone: that capture is
    accepted, and the model's own fit is measured on it now, as the trainer measures it."""
    old = tmp_path / "old.ply"
    shutil.copy(model, old)
    fields = {k: v for k, v in sidecar(model).items() if k not in ("dataset_fingerprint", "training_fit")}
    old.with_suffix(".json").write_text(json.dumps(fields))
    code, _, err = run(capsys, "render", "--model", old, "--data", LEGO, "--views", 1, "--out", tmp_path / "r")
    assert code == 0 and "note" not in err, err
    code, _, err = run(capsys, "render", "--model", old, "--data", DONUT, "--views", 1, "--out", tmp_path / "d")
    assert code == 2 and fits_named(err)[1] == f"{sidecar(model)['training_fit']['psnr']:.1f}", err

    # Its capture gone: a copy elsewhere holds its training views, but no fit is there to compare
    # photos with, which a note says; another capture holds none of them; without --data, what to give.
    old.with_suffix(".json").write_text(json.dumps({**fields, "dataset": str(tmp_path / "gone")}))
    moved = moved_copy(tmp_path / "moved", images=True)
    code, _, err = run(capsys, "render", "--model", old, "--data", moved, "--views", 1, "--out", tmp_path / "m")
    assert code == 0 and "records no fit" in err and "checked by its cameras alone" in err, err
    code, _, err = run(capsys, "render", "--model", old, "--data", DONUT, "--views", 1, "--out", tmp_path / "n")
    assert code == 2 and "holds none of the model's 4 training views" in err and "dB" not in err, err
    code, _, err = run(capsys, "render", "--model", old, "--out", tmp_path / "x")
    assert code == 2 and "error: data: give --data" in err and "no longer there" in err, err


def test_calibrate_refuses_cameras_that_see_none_of_the_model(model, capsys, tmp_path) -> None:
    """Cameras in another frame (lego's, moved 100 units away) render empty images, on which any ratio
    passes: r_drop would be the cap and blame epsilon."""
    frames = json.loads((LEGO / "transforms_train.json").read_text())
    for frame in frames["frames"][:8]:
        frame["transform_matrix"][0][3] += 100.0
    cameras = tmp_path / "elsewhere.json"
    cameras.write_text(json.dumps({**frames, "frames": frames["frames"][:8], "w": 200, "h": 200}))
    code, _, err = run(capsys, "calibrate", "--model", model, "--cameras", cameras, "--samples", 2)
    assert code == 2 and "error: cameras: 8 of the 8 cameras see almost none of" in err, err
    code, out, err = run(capsys, "calibrate", "--model", model, "--cameras", cameras, "--samples", 2,
                         "--other-capture")
    assert code == 0 and "r_drop" in out and "--other-capture: going on" in err, err


def test_candidates_frames_writes_a_captures_own_frames_that_rank_takes(model, capsys, tmp_path) -> None:
    code, _, err = run(capsys, "candidates", "frames", "--data", LEGO, "--split", "test", "--out", tmp_path / "t.json")
    assert code == 0, err
    written = json.loads((tmp_path / "t.json").read_text())["frames"]
    loaded = load_dataset(LEGO, "test", with_images=False).cameras
    assert len(written) == len(loaded) == 200
    for frame, camera in zip(written, loaded):
        assert max(abs(a - b) for row, ref in zip(frame["transform_matrix"], camera.c2w.tolist())
                   for a, b in zip(row, ref)) <= 1e-9
        assert (frame["fl_x"], frame["fl_y"], frame["cx"], frame["cy"], frame["w"], frame["h"]) == \
            (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)

    # With --model: the capture it was trained on; frames:3 takes three, evenly spaced.
    code, _, err = run(capsys, "candidates", "frames:3", "--model", model, "--split", "test",
                       "--out", tmp_path / "three.json")
    three = json.loads((tmp_path / "three.json").read_text())["frames"]
    assert code == 0 and three == [written[i] for i in select_views(200, 3)], err
    code, out, err = run(capsys, "rank", "--model", model, "--candidates", tmp_path / "three.json",
                         "--dropout-ratio", 0.3, "--samples", 2, "--downscale", 4, "--json")
    ranked = json.loads(out)
    assert code == 0 and ranked["candidates"] == 3, err
    assert sorted(r["index"] for r in ranked["ranking"]) == [0, 1, 2]
    assert all(r["camera"] == three[r["index"]] for r in ranked["ranking"])

    # A Blender capture has no "all" split: without --split, its train, val and test frames in turn.
    code, out, _ = run(capsys, "candidates", "frames", "--data", LEGO)
    assert code == 0 and len(json.loads(out)["frames"]) == 100 + 100 + 200
    code, _, err = run(capsys, "candidates", "orbit:4", "--data", LEGO, "--split", "test")
    assert code == 2 and "error: split:" in err
