"""Every command takes a trainer's output folder the same way (one loader, `phd_cli.models`):
splatfacto and gsplat runs bring their capture and their run's own train/test split, so
`phd render --model RUN` renders the held-out frames with no --data or --split; a capture in
another frame (the COLMAP model a splatfacto run's transforms.json was made from) is refused.
The folders are written as the trainers write them (tests/support/trainers.py); the capture's
images are renders of the user-frame model, so a right frame scores far above a wrong one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from phd_cli import main
from phd_core.io.configs import SPLATFACTO_BACKGROUNDS as BACKGROUNDS
from phd_core.renderers.gs3d import GaussianRenderer
from support.captures import write_colmap, write_images, write_output_folder
from support.cli import run
from support.trainers import (
    APPLIED_TRANSFORM,
    frame_names,
    gsplat_scene,
    move_camera,
    scene_cameras,
    scene_splats,
    splatfacto_scene,
)

LAYOUTS = ("cameras.json + point_cloud/iteration_*", "config.yml + dataparser_transforms.json", "ckpts/ckpt_*_rank*.pt")


def render_images(folder: Path, names: list[str], cameras, renderer) -> None:
    """The capture's images: the user-frame model's renders at its cameras."""
    write_images(folder, [renderer.render(c)[0].numpy() for c in cameras], names)


@pytest.fixture(scope="module")
def splatfacto(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("splatfacto")
    scene = splatfacto_scene(root)
    names = frame_names(len(scene["cameras"]))
    render_images(root / "data" / "desk" / "images", [Path(n).name for n in names], scene["cameras"],
                 GaussianRenderer(scene["user_model"], BACKGROUNDS["random"]))
    # nerfstudio's fraction split (0.9) over the frames sorted by name holds out the 9th of 10.
    order = sorted(range(len(names)), key=lambda i: names[i])
    return {**scene, "root": root, "names": names, "held_out": [order[8]]}


@pytest.fixture(scope="module")
def gsplat(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("gsplat")
    scene = gsplat_scene(root)
    cameras = scene["training"]
    count = 10
    names = [f"IMG_{(7 * i) % count:04d}.png" for i in range(count)]
    render_images(root / "data" / "garden" / "images", names, scene_cameras(count),
                 GaussianRenderer(scene["user_model"], (0.0, 0.0, 0.0)))
    assert len(cameras) == 8                           # test_every 8 over 10 images by name: 0 and 8 held out
    return {**scene, "root": root}


def metrics(folder: Path) -> dict:
    return json.loads((folder / "metrics.json").read_text())


def test_render_a_splatfacto_run_on_its_own_capture_and_split(splatfacto, capsys, tmp_path) -> None:
    code, out, err = run(capsys, "render", "--model", splatfacto["folder"], "--out", tmp_path / "test")
    assert code == 0, err
    result = metrics(tmp_path / "test")
    assert [v["index"] for v in result["views"]] == splatfacto["held_out"]
    assert result["split"] == "test" and Path(result["data"]) == splatfacto["root"] / "data" / "desk"
    assert result["psnr"] > 40
    # --split train: the frames the run trained on; naming the same capture with --data changes nothing.
    code, _, err = run(capsys, "render", "--model", splatfacto["folder"], "--split", "train", "--data",
                       splatfacto["root"] / "data" / "desk", "--out", tmp_path / "train")
    assert code == 0, err
    trained = [v["index"] for v in metrics(tmp_path / "train")["views"]]
    assert sorted(trained) == sorted(set(range(10)) - set(splatfacto["held_out"]))
    assert metrics(tmp_path / "train")["psnr"] > 40


def test_a_capture_in_another_frame_is_refused_not_rendered(splatfacto, capsys, tmp_path) -> None:
    """The COLMAP model ns-process-data started from: the same images, poses before its applied_transform."""
    colmap = tmp_path / "colmap"
    original = np.linalg.inv(APPLIED_TRANSFORM)
    write_colmap(colmap, [move_camera(c, original) for c in splatfacto["cameras"]], binary=False,
                 names=[Path(n).name for n in splatfacto["names"]])
    for argv in (["render", "--split", "all", "--out", tmp_path / "r"],
                 ["uq", "--split", "all", "--dropout-ratio", 0.3, "--samples", 3, "--out", tmp_path / "u"],
                 ["calibrate", "--samples", 2]):
        code, _, err = run(capsys, argv[0], "--model", splatfacto["folder"], "--data", colmap, *argv[1:])
        assert code == 2 and "error: data:" in err and "not in the frame" in err and "transforms.json" in err, err
    assert not (tmp_path / "r").exists()


def test_a_gsplat_run_renders_and_measures_its_held_out_frames(gsplat, capsys, tmp_path) -> None:
    code, _, err = run(capsys, "render", "--model", gsplat["folder"], "--out", tmp_path / "render")
    assert code == 0, err
    result = metrics(tmp_path / "render")
    assert [v["index"] for v in result["views"]] == [0, 8] and result["psnr"] > 40
    code, _, err = run(capsys, "render", "--model", gsplat["folder"], "--data", gsplat["root"] / "data" / "garden",
                       "--out", tmp_path / "named")                  # the run's capture named: the same frames
    assert code == 0 and [v["index"] for v in metrics(tmp_path / "named")["views"]] == [0, 8], err
    code, _, err = run(capsys, "uq", "--model", gsplat["folder"], "--dropout-ratio", 0.3, "--samples", 3,
                       "--no-heatmaps", "--out", tmp_path / "uq")
    assert code == 0, err
    report = json.loads((tmp_path / "uq" / "report.json").read_text())
    assert [v["index"] for v in report["views"]] == [0, 8] and all(v["rmse"] < 0.02 for v in report["views"])
    code, out, err = run(capsys, "select", "--model-a", gsplat["folder"], "--model-b", gsplat["folder"],
                         "--ratio-a", 0.3, "--ratio-b", 0.2, "--samples", 3)
    assert code == 0, err
    assert len(json.loads(out)["views"]) == 2


def photographed(capture: Path, seed: int) -> Path:
    """A COLMAP capture of 10 ring cameras whose photos are renders of `scene_splats(300, seed)`."""
    cameras = scene_cameras(10)
    renderer = GaussianRenderer(scene_splats(300, seed=seed), (0.0, 0.0, 0.0))
    write_colmap(capture, cameras, binary=True, images=[renderer.render(c)[0].numpy() for c in cameras])
    return capture


def reference_run(tmp_path: Path) -> tuple[Path, Path]:
    """A reference-trainer folder whose cfg_args names its COLMAP capture, trained on all but every 8th view."""
    capture = photographed(tmp_path / "garden", seed=4)
    folder = write_output_folder(tmp_path / "output", scene_splats(300, seed=4),
                                 [c for i, c in enumerate(scene_cameras(10)) if i % 8], eval_split=False)
    cfg = folder / "cfg_args"
    cfg.write_text(cfg.read_text().replace("source_path='/data/x'", f"source_path='{capture}'"))
    return folder, capture


def test_a_reference_output_folder_renders_its_source_capture(capsys, tmp_path) -> None:
    """cfg_args' source_path names the COLMAP capture; its own split (every 8th image by name) is the run's."""
    folder, _ = reference_run(tmp_path)
    code, _, err = run(capsys, "render", "--model", folder, "--out", tmp_path / "render")
    assert code == 0, err
    result = metrics(tmp_path / "render")
    # The capture's own test split: its images 0 and 8 by name, numbered within the split.
    assert [v["index"] for v in result["views"]] == [0, 1] and result["split"] == "test" and result["psnr"] > 40


def test_a_reference_output_folder_refuses_other_photos_at_its_poses(capsys, tmp_path) -> None:
    """A trainer's folder records no fit: it is measured on the run's own capture, and a capture at the
    run's poses with photos of another scene falls far below it; a copy of the run's capture does not."""
    folder, capture = reference_run(tmp_path)
    other = photographed(tmp_path / "other", seed=5)
    code, _, err = run(capsys, "render", "--model", folder, "--data", other, "--out", tmp_path / "other_render")
    assert code == 2 and f"error: data: {other} is not the capture {folder} was trained on ({capture}): 4 of its " \
                         "views render at" in err and "dB below the" in err, err
    copy = shutil.copytree(capture, tmp_path / "copy")
    code, _, err = run(capsys, "render", "--model", folder, "--data", copy, "--out", tmp_path / "copy_render")
    assert code == 0 and "note" not in err, err


def test_a_split_the_run_does_not_have_names_the_field(splatfacto, capsys, tmp_path) -> None:
    code, _, err = run(capsys, "render", "--model", splatfacto["folder"], "--split", "val", "--out", tmp_path)
    assert code == 2 and "error: split:" in err and "train, test" in err


@pytest.mark.parametrize("command", ["render", "calibrate", "uq", "rank", "select", "view", "candidates"])
def test_every_command_lists_the_folder_layouts_in_its_help(command, capsys) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(layout in text for layout in LAYOUTS), text
