"""`phd calibrate`, `phd uq` and `phd rank` end to end: real PLY, JSON and PNG files on disk,
results compared with direct calls of the library."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from phd_core import uq as phd
from phd_core.data import load_cameras, load_dataset
from phd_core.eval import image_uq_metrics
from phd_core.io import ModelCache
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import GaussianModel, write_ply
from support.cli import run
from support.toy_renderers import away_camera, ring_cameras

SIZE, FOV, STEP = 16, 0.7, 0.25


def strict_json(path_or_text) -> dict:
    text = path_or_text.read_text() if isinstance(path_or_text, Path) else path_or_text

    def reject(constant: str):
        raise AssertionError(f"JSON contains {constant}")

    return json.loads(text, parse_constant=reject)


def frame(camera, file_path: str | None = None) -> dict:
    entry = {"transform_matrix": camera.c2w.tolist()}
    if file_path:
        entry["file_path"] = file_path
    return entry


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli_uq")
    g = torch.Generator().manual_seed(3)
    count = 250
    model = GaussianModel(
        means=(torch.rand(count, 3, generator=g) - 0.5) * 1.4,
        log_scales=torch.log(0.05 + 0.1 * torch.rand(count, 3, generator=g)),
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.rand(count, generator=g) * 4 - 1,
        sh=torch.randn(count, 1, 3, generator=g) * 0.5)
    write_ply(model, root / "model.ply")
    renderer = load_model(root / "model.ply")

    train, test = ring_cameras(2, size=SIZE), ring_cameras(3, size=SIZE, height=1.6)[1:] + [away_camera(SIZE)]
    (root / "cameras.json").write_text(json.dumps([c.to_frame() for c in train]))
    (root / "candidates.json").write_text(json.dumps({"camera_angle_x": FOV, "frames": [
        frame(c) for c in [away_camera(SIZE)] + ring_cameras(4, size=SIZE, height=0.5)]}))
    data = root / "data"
    for split, cameras in (("train", train), ("test", test)):
        (data / split).mkdir(parents=True)
        frames = []
        for i, camera in enumerate(cameras):
            render = renderer.render(camera)[0].numpy()
            noise = np.random.default_rng(i).normal(0, 0.05, render.shape) * (render < 0.99)
            iio.imwrite(data / split / f"r_{i}.png", np.clip((render + noise) * 255 + 0.5, 0, 255).astype(np.uint8))
            frames.append(frame(camera, f"./{split}/r_{i}"))
        (data / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV, "frames": frames}))
    return {"root": root, "model": root / "model.ply", "cameras": root / "cameras.json",
            "candidates": root / "candidates.json", "data": data}


@pytest.fixture(scope="module")
def curve(files) -> phd.CalibrationResult:
    """The whole error curve on the train split's poses (step 0.25, 3 masks, seed 0)."""
    cameras = load_dataset(files["data"], "train", with_images=False).cameras
    return phd.calibrate(load_model(files["model"]), cameras, epsilon=100.0, step=STEP, samples=3)


def linear_prefix(curve: phd.CalibrationResult, epsilon: float) -> tuple[float, list[float], list[float]]:
    """r_drop, ratios and errors that Algorithm 1 reports for `epsilon`, read off the curve."""
    k = next((i for i, e in enumerate(curve.errors) if not e < epsilon), len(curve.errors))
    r_drop = curve.ratios[k - 1] if k > 0 else 0.0
    return r_drop, curve.ratios[:k + 1], curve.errors[:k + 1]


def test_calibrate_prints_r_drop_and_writes_the_curve(files, curve, capsys) -> None:
    epsilon = float(np.quantile(curve.errors, 0.5))
    r_drop, ratios, errors = linear_prefix(curve, epsilon)
    assert 0 < r_drop < curve.r_drop
    out_json = files["root"] / "calibration.json"
    code, out, _ = run(capsys, "calibrate", "--model", files["model"], "--cameras", files["cameras"],
                       "--epsilon", epsilon, "--step", STEP, "--samples", 3, "--out", out_json)
    assert code == 0
    result = strict_json(out_json)
    assert result["r_drop"] == r_drop and result["ratios"] == ratios and result["method"] == "linear"
    assert result["errors"] == pytest.approx(errors, abs=1e-12)
    assert f"r_drop = {r_drop}" in out
    assert all(f"{r:5.3f}   {e:.6f}" in out for r, e in zip(ratios, errors))

    # The same poses from the dataset, searched by bisection over the same masks: the same r_drop.
    code, out, _ = run(capsys, "calibrate", "--model", files["model"], "--data", files["data"], "--epsilon", epsilon,
                       "--step", STEP, "--samples", 3, "--method", "bisection")
    assert code == 0 and f"r_drop = {r_drop}  (bisection" in out


def test_a_trained_model_calibrates_and_ranks_with_its_stored_cameras(files, curve, capsys) -> None:
    from phd_core.renderers.gs3d import SIDECAR_FORMAT, sidecar_path

    trained = files["root"] / "trained.ply"
    shutil.copy(files["model"], trained)
    train = load_dataset(files["data"], "train", with_images=False).cameras
    sidecar_path(trained).write_text(json.dumps({"format": SIDECAR_FORMAT, "background": [1.0, 1.0, 1.0],
                                                 "training_cameras": [c.to_frame() for c in train]}))
    epsilon = float(np.quantile(curve.errors, 0.3))
    r_drop, _, _ = linear_prefix(curve, epsilon)
    code, out, _ = run(capsys, "calibrate", "--model", trained, "--epsilon", epsilon, "--step", STEP, "--samples", 3)
    assert code == 0 and f"r_drop = {r_drop}" in out and "2 views" in out

    code, out, _ = run(capsys, "rank", "--json", "--model", trained, "--candidates", files["candidates"],
                       "--width", SIZE, "--height", SIZE, "--epsilon", epsilon, "--step", STEP,
                       "--calibration-samples", 3, "--samples", 3)
    result = strict_json(out)
    assert code == 0 and result["dropout_ratio"] == r_drop == result["calibration"]["r_drop"]


def test_calibrate_respects_views_and_downscale(files, capsys) -> None:
    out_json = files["root"] / "calibration_small.json"
    code, _, _ = run(capsys, "calibrate", "--model", files["model"], "--data", files["data"], "--views", 1,
                     "--downscale", 2, "--epsilon", 100, "--step", 0.3, "--samples", 2, "--out", out_json)
    assert code == 0
    cameras = load_dataset(files["data"], "train", views=1, downscale=2, with_images=False).cameras
    assert cameras[0].width == SIZE // 2 and len(cameras) == 1
    expected = phd.calibrate(load_model(files["model"]), cameras, epsilon=100, step=0.3, samples=2)
    assert strict_json(out_json)["errors"] == pytest.approx(expected.errors, abs=1e-12)
    assert strict_json(out_json)["capped"] is True


def test_calibrate_failure_is_explained(files, capsys) -> None:
    code, _, err = run(capsys, "calibrate", "--model", files["model"], "--cameras", files["cameras"],
                       "--epsilon", 1e-7, "--step", STEP, "--samples", 2)
    assert code == 2
    assert "not properly trained" in err and "epsilon" in err
    assert f"{STEP:5.3f}" in err   # the evaluated curve is printed too


def test_calibrate_without_cameras_names_the_field(files, capsys) -> None:
    code, _, err = run(capsys, "calibrate", "--model", files["model"])
    assert code == 2 and "cameras" in err


def test_uq_report_and_heatmaps(files, capsys) -> None:
    out_dir = files["root"] / "uq"
    code, out, _ = run(capsys, "uq", "--model", files["model"], "--data", files["data"], "--split", "test",
                       "--dropout-ratio", 0.3, "--samples", 4, "--seed", 2, "--out", out_dir)
    assert code == 0 and "sigma-max-bar" in out
    report = strict_json(out_dir / "report.json")
    renderer = load_model(files["model"])
    data = load_dataset(files["data"], "test")
    views = phd.uncertainty(renderer, data.cameras, ratio=0.3, samples=4, seed=2, keep_maps=True)
    assert report["dropout_ratio"] == 0.3 and report["r_drop"] is None and report["ddof"] == 1
    assert report["sigma_max_bar"] == pytest.approx(phd.sigma_max_bar(views), abs=1e-12)
    assert [r["sigma_max"] for r in report["views"]] == pytest.approx([v.sigma_max for v in views], abs=1e-12)
    vmax = max(v.sigma_max for v in views)
    for row, view, camera, truth in zip(report["views"], views, data.cameras, data.images):
        expected = image_uq_metrics(view.zeta, renderer.render(camera)[0], truth)
        for key in ("spearman", "pearson", "ause_rmse", "rmse"):
            assert row[key] == (None if expected[key] is None else pytest.approx(expected[key], abs=1e-9))
        heatmap = iio.imread(out_dir / row["heatmap"])
        assert heatmap.shape == (SIZE, SIZE, 3) and row["heatmap_vmax"] == pytest.approx(vmax)
    away = report["views"][-1]   # sees only background: zero uncertainty, undefined correlations
    assert away["sigma_max"] == 0.0 and away["spearman"] is None and away["pearson"] is None
    assert report["views"][0]["spearman"] is not None
    assert report["summary"]["spearman_sigma_max_vs_rmse"] is not None


def test_uq_calibrates_on_the_train_split_without_stored_cameras(files, curve, capsys) -> None:
    out_dir = files["root"] / "uq_calibrated"
    epsilon = float(np.quantile(curve.errors, 0.5))
    r_drop, _, errors = linear_prefix(curve, epsilon)
    code, _, _ = run(capsys, "uq", "--model", files["model"], "--data", files["data"], "--epsilon", epsilon,
                     "--step", STEP, "--calibration-samples", 3, "--samples", 3, "--no-heatmaps", "--out", out_dir)
    assert code == 0
    report = strict_json(out_dir / "report.json")
    assert report["r_drop"] == report["dropout_ratio"] == r_drop
    assert report["calibration"]["errors"] == pytest.approx(errors, abs=1e-12)
    assert any("no training cameras" in w for w in report["warnings"])
    assert not (out_dir / "heatmaps").exists()


def test_rank_orders_candidates(files, capsys) -> None:
    out_json = files["root"] / "rank.json"
    code, _, _ = run(capsys, "rank", "--model", files["model"], "--candidates", files["candidates"],
                     "--width", SIZE, "--height", SIZE, "--dropout-ratio", 0.4, "--samples", 5, "--out", out_json)
    assert code == 0
    result = strict_json(out_json)
    candidates = [away_camera(SIZE)] + ring_cameras(4, size=SIZE, height=0.5)
    expected = phd.rank_views(load_model(files["model"]), candidates, ratio=0.4, samples=5)
    assert result["order"] == [r.index for r in expected] and result["order"][-1] == 0   # the blind pose last
    assert result["ranking"][0]["sigma_max"] == pytest.approx(expected[0].sigma_max, abs=1e-12)
    assert result["ranking"][-1]["sigma_max"] == 0.0

    code, out, _ = run(capsys, "rank", "--json", "--model", files["model"], "--candidates", files["candidates"],
                       "--width", SIZE, "--height", SIZE, "--dropout-ratio", 0.4, "--samples", 5, "--top-k", 2)
    assert code == 0 and strict_json(out)["order"] == result["order"][:2]

    code, out, _ = run(capsys, "rank", "--json", "--model", files["model"], "--candidates", files["candidates"],
                       "--width", SIZE, "--height", SIZE, "--dropout-ratio", 0.4, "--samples", 5, "--coarse", 0.5,
                       "--refine", 2)
    coarse = phd.rank_views(load_model(files["model"]), candidates, ratio=0.4, samples=5, coarse=0.5, refine=2)
    assert code == 0 and strict_json(out)["order"] == [r.index for r in coarse]
    assert [r["refined"] for r in strict_json(out)["ranking"]] == [True, True, False, False, False]


def test_rank_takes_a_strategy_and_captured_poses(files, capsys) -> None:
    argv = ["rank", "--json", "--model", files["model"], "--candidates", files["candidates"], "--width", SIZE,
            "--height", SIZE, "--dropout-ratio", 0.4, "--samples", 5]
    candidates = [away_camera(SIZE)] + ring_cameras(4, size=SIZE, height=0.5)
    renderer = load_model(files["model"])
    code, out, _ = run(capsys, *argv, "--strategy", "sigma_max")
    paper = strict_json(out)
    assert code == 0 and paper["strategy"] == "sigma_max"
    assert paper["order"] == [r.index for r in phd.rank_views(renderer, candidates, ratio=0.4, samples=5,
                                                               strategy="sigma_max")]
    assert [r["score"] for r in paper["ranking"]] == [r["sigma_max"] for r in paper["ranking"]]
    captured = files["root"] / "captured.json"
    captured.write_text(json.dumps([c.to_frame() for c in candidates[1:3]]))
    code, out, _ = run(capsys, *argv, "--captured", captured, "--top-k", 2)
    expected = phd.rank_views(renderer, candidates, ratio=0.4, samples=5, captured=candidates[1:3], top_k=2)
    assert code == 0 and strict_json(out)["order"] == [r.index for r in expected]
    assert not {1, 2} & set(strict_json(out)["order"])          # captured poses are not picked again
    # What the captured poses saw was kept beside the model: the next rank reads it and ranks the same.
    assert list(ModelCache(files["model"]).dir.glob("captured-coverage-*.pt"))
    assert run(capsys, *argv, "--captured", captured, "--top-k", 2)[1] == out
    # Captured frames without an image size take the candidates' (here from their own file, no
    # --width): the coverage strategies render them, so a placeholder size would rank otherwise.
    sized = files["root"] / "sized_candidates.json"
    sized.write_text(json.dumps([c.to_frame() for c in candidates]))
    captured.write_text(json.dumps([{k: v for k, v in c.to_frame().items() if k not in ("w", "h")}
                                    for c in candidates[1:3]]))
    code, out, _ = run(capsys, "rank", "--json", "--model", files["model"], "--candidates", sized,
                       "--dropout-ratio", 0.4, "--samples", 5, "--captured", captured)
    expected = phd.rank_views(renderer, candidates, ratio=0.4, samples=5, captured=candidates[1:3])
    assert code == 0 and [r["score"] for r in strict_json(out)["ranking"]] == [r.score for r in expected]
    with pytest.raises(SystemExit) as exit_info:   # argparse: usage and the known names on stderr
        run(capsys, *argv, "--strategy", "sharpest")
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "invalid choice: 'sharpest'" in err and "fvs_sigma" in err


def test_rank_measures_on_the_signal_it_is_given(files, capsys) -> None:
    argv = ["rank", "--json", "--model", files["model"], "--candidates", files["candidates"], "--width", SIZE,
            "--height", SIZE, "--dropout-ratio", 0.4, "--samples", 5]
    candidates = [away_camera(SIZE)] + ring_cameras(4, size=SIZE, height=0.5)
    code, out, _ = run(capsys, *argv, "--signal", "premultiplied")
    expected = phd.rank_views(load_model(files["model"]), candidates, ratio=0.4, samples=5, signal="premultiplied")
    result = strict_json(out)
    assert code == 0 and result["signal"] == "premultiplied" and result["order"] == [r.index for r in expected]
    assert [r["sigma_max"] for r in result["ranking"]] == pytest.approx([r.sigma_max for r in expected], abs=1e-12)
    with pytest.raises(SystemExit) as exit_info:
        run(capsys, *argv, "--signal", "straight")
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--signal" in err and "invalid choice: 'straight'" in err


@pytest.mark.parametrize("extra, field", [
    (["--samples", "1"], "samples"), (["--dropout-ratio", "1.5"], "ratio"), (["--top-k", "0"], "top_k"),
    (["--downscale", "0"], "downscale"), (["--coarse", "1.5"], "coarse"), (["--refine", "3"], "refine"),
])
def test_rank_rejects_bad_numbers(files, capsys, extra: list[str], field: str) -> None:
    argv = ["rank", "--json", "--model", files["model"], "--candidates", files["candidates"], "--width", SIZE,
            "--height", SIZE, *extra]
    if "--dropout-ratio" not in extra:
        argv += ["--dropout-ratio", "0.3"]
    code, _, err = run(capsys, *argv)
    assert code == 2 and f"{field}:" in err and "Traceback" not in err


def test_background_flag_changes_what_calibration_sees(files, capsys) -> None:
    """--background renders the model over that colour: the curve is the library's over it,
    and not the one over the default white."""
    argv = ["calibrate", "--model", files["model"], "--cameras", files["cameras"], "--epsilon", 100, "--step",
            STEP, "--samples", 3]
    curves = {}
    for name, colour in (("white", (1.0, 1.0, 1.0)), ("grey", (0.5, 0.5, 0.5))):
        out_json = files["root"] / f"calibration_{name}.json"
        code, _, err = run(capsys, *argv, "--background", name, "--out", out_json)
        assert code == 0, err
        renderer = load_model(files["model"])
        renderer.background = torch.tensor(colour)
        expected = phd.calibrate(renderer, load_cameras(files["cameras"]), epsilon=100.0, step=STEP, samples=3)
        curves[name] = strict_json(out_json)["errors"]
        assert curves[name] == pytest.approx(expected.errors, abs=1e-9)
    assert curves["white"] != pytest.approx(curves["grey"], abs=1e-6)
    code, _, err = run(capsys, *argv, "--background", "0.5", "0.5", "0.5")
    assert code == 0, err


@pytest.mark.parametrize("values", [["purple"], ["0.5", "2", "0"], ["1", "1"], ["a", "b", "c"]])
def test_a_bad_background_names_the_flag(files, capsys, values: list[str]) -> None:
    code, _, err = run(capsys, "rank", "--model", files["model"], "--candidates", files["candidates"], "--width",
                       SIZE, "--height", SIZE, "--dropout-ratio", 0.3, "--background", *values)
    assert code == 2 and "background:" in err and "Traceback" not in err


def test_train_over_a_background_records_it_and_the_capture_format(files, capsys, tmp_path) -> None:
    out = tmp_path / "grey.ply"
    code, _, err = run(capsys, "train", "--data", files["data"], "--views", 2, "--downscale", 1, "--iterations", 3,
                       "--background", "grey", "--out", out, "--quiet")
    assert code == 0, err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["background"] == [0.5, 0.5, 0.5] and sidecar["dataset_format"] == "blender"
    facts = load_model(out).describe()
    assert facts["background"] == [0.5, 0.5, 0.5] and facts["camera_format"] == "blender"


def test_select_chooses_per_view_as_the_library_does_over_the_background_given(files, capsys, tmp_path) -> None:
    """`phd select` is select_models with the same arguments; --background reaches both models."""
    g = torch.Generator().manual_seed(8)
    other = GaussianModel(means=(torch.rand(120, 3, generator=g) - 0.5) * 1.4,
                          log_scales=torch.log(0.05 + 0.1 * torch.rand(120, 3, generator=g)),
                          quats=torch.randn(120, 4, generator=g), opacity_logits=torch.rand(120, generator=g) * 4 - 1,
                          sh=torch.randn(120, 1, 3, generator=g) * 0.5)
    write_ply(other, tmp_path / "other.ply")
    out_json = tmp_path / "select.json"
    code, out, err = run(capsys, "select", "--model-a", files["model"], "--model-b", tmp_path / "other.ply",
                         "--data", files["data"], "--split", "test", "--rule", "sigma_mean", "--samples", 4,
                         "--dropout-ratio", 0.3, "--background", "black", "--out", out_json)
    assert code == 0 and "views (sigma_mean)" in out, err
    report = strict_json(out_json)
    renderers = [load_model(files["model"]), load_model(tmp_path / "other.ply")]
    for renderer in renderers:
        renderer.background = torch.zeros(3)
    dataset = load_dataset(files["data"], "test", background=(0.0, 0.0, 0.0))
    expected = phd.select_models(*renderers, dataset.cameras, ratio_a=0.3, ratio_b=0.3, samples=4,
                                 images=dataset.images, rule="sigma_mean")
    assert [v["choice"] for v in report["views"]] == [v.choice for v in expected.views]
    assert [v["score_a"] for v in report["views"]] == pytest.approx([v.score_a for v in expected.views], abs=1e-9)
    assert report["metrics"]["psnr_a"] == pytest.approx(expected.metrics["psnr_a"], abs=1e-9)
    assert report["counts"]["a"] + report["counts"]["b"] == len(dataset.cameras)
