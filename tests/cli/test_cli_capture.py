"""Bring your own capture through the `phd` command: a reference-trainer output folder taken
as is by calibrate and rank (with generated candidates), nerfstudio splatfacto and gsplat
folders ranked in the user's frame, `phd candidates`, training cameras from COLMAP and LLFF
files, and clean errors for malformed files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from phd_core import uq as phd
from phd_core.data import load_blender, load_cameras
from phd_core.data.inria import camera_from_entry
from phd_core.io.configs import SPLATFACTO_BACKGROUNDS as BACKGROUNDS
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.scene import Camera
from phd_core.uq.candidates import candidate_cameras
from support.captures import write_colmap, write_llff, write_output_folder
from support.cli import run
from support.toy_renderers import ring_cameras
from support.trainers import gsplat_scene, splatfacto_scene

SIZE, STEP = 16, 0.25


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("capture")
    g = torch.Generator().manual_seed(5)
    count = 250
    model = GaussianModel(means=(torch.rand(count, 3, generator=g) - 0.5) * 1.4,
                          log_scales=torch.log(0.05 + 0.1 * torch.rand(count, 3, generator=g)),
                          quats=torch.randn(count, 4, generator=g),
                          opacity_logits=torch.rand(count, generator=g) * 4 - 1,
                          sh=torch.randn(count, 1, 3, generator=g) * 0.5)
    training = ring_cameras(3, size=SIZE)
    folder = write_output_folder(root / "output", model, training)
    renderer = load_model(folder)
    curve = phd.calibrate(renderer, renderer.training_cameras, epsilon=100.0, step=STEP, samples=3)
    epsilon = float(np.quantile(curve.errors, 0.5))
    expected = phd.calibrate(renderer, renderer.training_cameras, epsilon=epsilon, step=STEP, samples=3)
    assert expected.r_drop > 0
    return {"root": root, "folder": folder, "renderer": renderer, "training": training, "epsilon": epsilon,
            "r_drop": expected.r_drop}


def calibration_args(capture, samples_flag: str = "--calibration-samples") -> list:
    return ["--epsilon", capture["epsilon"], "--step", STEP, samples_flag, 3]


def test_calibrate_takes_a_reference_output_folder_as_is(capture, capsys) -> None:
    code, out, err = run(capsys, "calibrate", "--model", capture["folder"], *calibration_args(capture, "--samples"))
    assert code == 0 and f"r_drop = {capture['r_drop']}" in out and "3 views" in out, err


def test_rank_an_output_folder_with_generated_candidates_in_one_line(capture, capsys) -> None:
    code, out, err = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", "orbit:6,rings=2",
                         "--samples", 3, *calibration_args(capture))
    assert code == 0, err
    result = json.loads(out)
    assert result["dropout_ratio"] == capture["r_drop"] and result["candidates"] == 6
    renderer = capture["renderer"]
    poses = candidate_cameras("orbit", 6, renderer=renderer, rings=2)
    ranked = phd.rank_views(renderer, poses, ratio=capture["r_drop"], samples=3)
    assert result["order"] == [r.index for r in ranked]
    assert [r["sigma_max"] for r in result["ranking"]] == pytest.approx([r.sigma_max for r in ranked])



def test_ranked_generated_candidates_carry_their_poses_and_export_as_a_batch(capture, capsys) -> None:
    """Each ranked pose is the generator's, in the project's convention and in the source's
    (a reference folder: cameras.json entries); --export writes the top k as a file the
    project's loader reads back as the same cameras, in capture order."""
    plan = capture["root"] / "plan" / "transforms.json"
    code, out, err = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", "orbit:6,rings=2",
                         "--samples", 3, "--dropout-ratio", 0.3, "--top-k", 4, "--downscale", 2, "--export", plan)
    assert code == 0, err
    result = json.loads(out)
    poses = candidate_cameras("orbit", 6, renderer=capture["renderer"], rings=2)     # at the training size
    assert result["camera_format"] == "3dgs-output" and len(result["ranking"]) == 4
    for entry in result["ranking"]:
        pose = poses[entry["index"]]
        assert entry["camera"] == pose.to_frame()                   # full size, not the downscaled render
        source = entry["source_pose"]
        assert source["format"] == "3dgs-output"
        assert torch.allclose(camera_from_entry(source).c2w, pose.c2w, atol=1e-12, rtol=0)
    assert "exported 4 poses" in err and "nerfstudio" in err
    chosen = [poses[entry["index"]] for entry in result["ranking"]]
    for got, expected in zip(load_cameras(plan), chosen, strict=True):
        assert got.c2w.tolist() == expected.c2w.tolist() and got.to_frame() == expected.to_frame()
    colmap = capture["root"] / "plan" / "colmap"
    code, out, err = run(capsys, "rank", "--model", capture["folder"], "--candidates", "orbit:6,rings=2",
                         "--samples", 3, "--dropout-ratio", 0.3, "--top-k", 4, "--export", colmap,
                         "--out", capture["root"] / "plan" / "r.json")
    assert code == 0 and "COLMAP text model" in out, err
    ranking = json.loads((capture["root"] / "plan" / "r.json").read_text())["ranking"]
    chosen = [poses[entry["index"]] for entry in ranking]
    reloaded = load_cameras(colmap, split="all")                    # sorted by name = capture order
    assert max((a.c2w - b.c2w).abs().max().item() for a, b in zip(reloaded, chosen, strict=True)) < 1e-9
    blender = capture["root"] / "plan" / "blender" / "transforms_train.json"
    code, out, err = run(capsys, "rank", "--model", capture["folder"], "--candidates", "orbit:6,rings=2",
                         "--samples", 3, "--dropout-ratio", 0.3, "--top-k", 4, "--export", blender,
                         "--export-format", "blender")
    assert code == 0 and "camera_angle_x" in out, err
    written = json.loads(blender.read_text())                       # the same ranking: same masks, same seed
    assert written["camera_angle_x"] == pytest.approx(2 * math.atan(chosen[0].width / (2 * chosen[0].fx)), abs=1e-15)
    assert [f["file_path"] for f in written["frames"]] == [
        f"./images/rank{k:03d}_candidate{entry['index']:04d}" for k, entry in enumerate(ranking, 1)]
    reloaded = load_blender(blender.parent, "train", with_images=False).cameras
    assert max((a.c2w - b.c2w).abs().max().item() for a, b in zip(reloaded, chosen, strict=True)) < 1e-12
    assert [c.fx for c in reloaded] == pytest.approx([c.fx for c in chosen], rel=1e-12)
    assert [(c.width, c.height) for c in reloaded] == [(c.width, c.height) for c in chosen]
    code, _, err = run(capsys, "rank", "--model", capture["folder"], "--candidates", "orbit:6", "--samples", 3,
                       "--dropout-ratio", 0.3, "--export", capture["root"] / "plan.yaml")
    assert code == 2 and "export:" in err and "plan.yaml" in err


def test_phd_candidates_writes_json_that_rank_reads(capture, capsys) -> None:
    out_json = capture["root"] / "candidates.json"
    code, out, err = run(capsys, "candidates", "sphere:5", "--model", capture["folder"], "--out", out_json)
    assert code == 0 and "5 sphere poses at 16x16" in out, err
    frames = json.loads(out_json.read_text())["frames"]
    expected = candidate_cameras("sphere", 5, renderer=capture["renderer"])
    assert [f["transform_matrix"] for f in frames] == [c.c2w.tolist() for c in expected]
    assert {(f["w"], f["h"], f["fl_x"]) for f in frames} == {(SIZE, SIZE, capture["training"][0].fx)}
    from_file = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", out_json, "--samples", 3,
                    "--dropout-ratio", 0.3)
    from_spec = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", "sphere:5", "--samples", 3,
                    "--dropout-ratio", 0.3)
    assert from_file[0] == from_spec[0] == 0
    assert json.loads(from_file[1])["ranking"] == json.loads(from_spec[1])["ranking"]
    # Candidates placed from a capture's training split, printed to stdout.
    write_llff(capture["root"] / "llff", [Camera(c.c2w, c.fx, c.fx, 8, 8, 16, 16) for c in ring_cameras(9, SIZE)])
    code, out, err = run(capsys, "candidates", "jitter:4", "--data", capture["root"] / "llff")
    assert code == 0 and len(json.loads(out)["frames"]) == 4, err


@pytest.mark.parametrize("kind", ["colmap-text", "colmap-binary", "llff", "cameras.json"])
def test_calibrate_on_training_cameras_from_any_format(capture, capsys, kind) -> None:
    """The same three poses from each format give the same r_drop (captures: --data with split all)."""
    root = capture["root"] / kind
    if kind.startswith("colmap"):
        write_colmap(root, capture["training"], binary=kind.endswith("binary"))
        source = ["--data", root, "--split", "all"]
    elif kind == "llff":
        source = ["--data", write_llff(root, capture["training"]), "--split", "all"]
    else:
        source = ["--cameras", capture["folder"] / "cameras.json"]
    code, out, err = run(capsys, "calibrate", "--model", capture["folder"], *source,
                         *calibration_args(capture, "--samples"))
    assert code == 0 and f"r_drop = {capture['r_drop']}" in out and "3 views" in out, err


def test_malformed_files_give_a_clean_cli_error(capture, capsys, tmp_path) -> None:
    broken = write_output_folder(tmp_path / "broken", capture["renderer"].model, capture["training"])
    entries = json.loads((broken / "cameras.json").read_text())
    entries[1]["rotation"] = [[1, 0, 0], [0, 1, 0]]
    (broken / "cameras.json").write_text(json.dumps(entries))
    code, _, err = run(capsys, "calibrate", "--model", broken)
    assert code == 2 and "cameras.json[1].rotation" in err and "Traceback" not in err
    write_llff(tmp_path / "llff", capture["training"])
    np.save(tmp_path / "llff" / "poses_bounds.npy", np.zeros((3, 12)))
    code, _, err = run(capsys, "calibrate", "--model", capture["folder"], "--cameras",
                       tmp_path / "llff" / "poses_bounds.npy")
    assert code == 2 and "poses_bounds.npy" in err and "[N, 17]" in err
    code, _, err = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", "zigzag:3",
                       "--dropout-ratio", 0.3)
    assert code == 2 and "generator" in err and "orbit" in err
    code, _, err = run(capsys, "candidates", "orbit:3,tilt=2", "--model", capture["folder"])
    assert code == 2 and "options.tilt" in err
    code, _, err = run(capsys, "candidates", "orbit:3,cameras=2", "--model", capture["folder"])   # not an option
    assert code == 2 and "options.cameras" in err and "Traceback" not in err
    sparse = write_colmap(tmp_path / "colmap", capture["training"], binary=False, model="SIMPLE_RADIAL",
                          extra=(float("nan"),))        # checked before pycolmap's undistortion sees it
    code, _, err = run(capsys, "calibrate", "--model", capture["folder"], "--cameras", sparse)
    assert code == 2 and "cameras.txt: camera 1" in err and "finite" in err and "Traceback" not in err


def test_rank_candidates_from_a_folder_without_cameras_use_the_splats(capture, capsys, tmp_path) -> None:
    from phd_core.renderers.gs3d import write_ply

    write_ply(capture["renderer"].model, tmp_path / "bare.ply")
    code, out, err = run(capsys, "rank", "--json", "--model", tmp_path / "bare.ply", "--candidates", "hemisphere:4",
                         "--width", 12, "--height", 12, "--samples", 3, "--dropout-ratio", 0.3)
    assert code == 0, err
    result = json.loads(out)
    assert result["candidates"] == 4 and sorted(result["order"]) == [0, 1, 2, 3]
    assert math.isfinite(result["ranking"][0]["sigma_max"]) and result["ranking"][0]["sigma_max"] > 0


def test_uq_and_rank_read_colmap_and_llff_captures(capture, capsys) -> None:
    """Candidates and evaluation views straight from COLMAP / LLFF captures (images rendered by the model)."""
    renderer = capture["renderer"]
    views = ring_cameras(9, size=SIZE, height=1.5)
    images = [renderer.render(c)[0].numpy() for c in views]
    colmap = capture["root"] / "uq-colmap"
    write_colmap(colmap, views, binary=True, images=images)
    llff = capture["root"] / "uq-llff"
    write_llff(llff, [Camera(c.c2w, c.fx, c.fx, SIZE / 2, SIZE / 2, SIZE, SIZE) for c in views], images=images)
    for data in (colmap, llff):
        out = capture["root"] / f"report-{data.name}"
        code, _, err = run(capsys, "uq", "--model", capture["folder"], "--data", data, "--split", "test",
                           "--samples", 3, "--dropout-ratio", 0.3, "--no-heatmaps", "--out", out)
        assert code == 0, err
        report = json.loads((out / "report.json").read_text())
        assert [v["index"] for v in report["views"]] == [0, 1]                  # frames 0 and 8 by name
        assert all(v["rmse"] < 0.01 for v in report["views"])                   # the images are the model's renders
        code, out, err = run(capsys, "rank", "--json", "--model", capture["folder"], "--candidates", data,
                             "--samples", 3, "--dropout-ratio", 0.3)
        assert code == 0 and json.loads(out)["candidates"] == 9, err


@pytest.mark.parametrize("trainer", ["splatfacto export", "splatfacto checkpoint", "gsplat"])
def test_rank_a_splatfacto_or_gsplat_folder_in_the_users_frame(capsys, tmp_path, trainer) -> None:
    """The folder as the trainer left it ranks as the scene built in the user's frame does,
    and generated candidates come out in that frame."""
    if trainer == "gsplat":
        scene, background = gsplat_scene(tmp_path), (0.0, 0.0, 0.0)
    else:
        scene, background = splatfacto_scene(tmp_path, export_ply=trainer.endswith("export")), BACKGROUNDS["random"]
    reference = GaussianRenderer(scene["user_model"], background, scene["training"])
    code, out, err = run(capsys, "candidates", "orbit:5,rings=1", "--model", scene["folder"],
                         "--out", tmp_path / "c.json")
    assert code == 0 and "note:" in err and "warning:" not in err, err
    expected = candidate_cameras("orbit", 5, cameras=scene["training"], rings=1)
    frames = json.loads((tmp_path / "c.json").read_text())["frames"]
    assert np.allclose([f["transform_matrix"] for f in frames], [c.c2w.tolist() for c in expected], atol=1e-9)
    code, out, err = run(capsys, "rank", "--model", scene["folder"], "--candidates", "orbit:5,rings=1",
                         "--samples", 3, "--dropout-ratio", 0.2, "--out", tmp_path / "r.json")
    assert code == 0, err
    result = json.loads((tmp_path / "r.json").read_text())
    ranked = phd.rank_views(reference, expected, ratio=0.2, samples=3)
    got = {r["index"]: r["sigma_max"] for r in result["ranking"]}
    assert max(r.sigma_max for r in ranked) > 0.01
    assert [got[r.index] for r in ranked] == pytest.approx([r.sigma_max for r in ranked], rel=1e-3, abs=1e-5)
