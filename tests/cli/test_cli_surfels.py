"""2DGS through the CLI: `phd train --model 2dgs`, then `phd calibrate`, `phd rank` and
`phd render` on the trained model and on a hand-made PLY in the 2DGS reference layout;
results equal the library called directly."""

from __future__ import annotations

import json

import pytest

from phd_cli import main
from phd_core import uq
from phd_core.renderers import load_model
from phd_core.renderers.gs2d import read_surfel_ply
from phd_core.uq.strategies import STRATEGIES
from support.cli import run
from support.fixtures import LEGO, svc_cameras
from support.surfels import random_surfels, reference_layout_ply


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> object:
    root = tmp_path_factory.mktemp("cli_2dgs")
    path = root / "surfels.ply"
    assert main(["train", "--model", "2dgs", "--data", str(LEGO), "--views", "3", "--downscale", "8",
                 "--iterations", "12", "--depth-distortion", "1", "--normal-consistency", "0.05",
                 "--out", str(path), "--quiet"]) == 0
    return path


def test_train_2dgs_writes_a_2dgs_model_that_renders(trained, tmp_path, capsys) -> None:
    renderer = load_model(trained)
    assert renderer.kind == "2dgs" and renderer.num_units == read_surfel_ply(trained).num_splats
    settings = json.loads(trained.with_suffix(".json").read_text())
    assert settings["model"] == "2dgs" and len(settings["training_cameras"]) == 3
    code, out, _ = run(capsys, "render", "--model", trained, "--data", LEGO, "--split", "test", "--views", 2,
                       "--out", tmp_path / "renders")
    metrics = json.loads((tmp_path / "renders" / "metrics.json").read_text())
    assert code == 0 and metrics["downscale"] == 8.0 and 5 < metrics["psnr"] < 60 and "PSNR" in out


def test_a_trained_2dgs_model_calibrates_and_ranks(trained, tmp_path, capsys) -> None:
    renderer = load_model(trained)
    code, out, _ = run(capsys, "calibrate", "--model", trained, "--epsilon", 0.5, "--step", 0.25, "--samples", 2,
                       "--downscale", 2, "--out", tmp_path / "cal.json")
    training = [c.scaled(2) for c in renderer.training_cameras]
    direct = uq.calibrate(renderer, training, epsilon=0.5, step=0.25, samples=2)
    assert code == 0 and direct.r_drop > 0 and f"r_drop = {direct.r_drop}" in out
    assert json.loads((tmp_path / "cal.json").read_text())["r_drop"] == direct.r_drop

    candidates = svc_cameras(4, radius=4.0, size=12)
    (tmp_path / "candidates.json").write_text(json.dumps([c.to_frame() for c in candidates]))
    code, out, _ = run(capsys, "rank", "--json", "--model", trained, "--candidates", tmp_path / "candidates.json",
                       "--epsilon", 0.5, "--step", 0.25, "--calibration-samples", 2, "--samples", 3)
    result = json.loads(out)
    assert code == 0 and result["dropout_ratio"] > 0
    expected = uq.rank_views(renderer, candidates, ratio=result["dropout_ratio"], samples=3)
    assert result["order"] == [r.index for r in expected]


def test_a_hand_made_2dgs_ply_calibrates_and_ranks_with_every_strategy(tmp_path, capsys) -> None:
    path = tmp_path / "hand.ply"
    path.write_bytes(reference_layout_ply(random_surfels(200, seed=7)))
    train, candidates = svc_cameras(3, size=16), svc_cameras(4, phase=0.4, size=16)
    (tmp_path / "train.json").write_text(json.dumps([c.to_frame() for c in train]))
    (tmp_path / "candidates.json").write_text(json.dumps([c.to_frame() for c in candidates]))
    renderer = load_model(path)
    code, out, _ = run(capsys, "calibrate", "--model", path, "--cameras", tmp_path / "train.json",
                       "--epsilon", 0.05, "--step", 0.2, "--samples", 3)
    direct = uq.calibrate(renderer, train, epsilon=0.05, step=0.2, samples=3)
    assert code == 0 and direct.r_drop > 0 and f"r_drop = {direct.r_drop}" in out
    for strategy in STRATEGIES:
        code, out, _ = run(capsys, "rank", "--json", "--model", path, "--candidates", tmp_path / "candidates.json",
                           "--captured", tmp_path / "train.json", "--dropout-ratio", direct.r_drop,
                           "--samples", 3, "--strategy", strategy)
        expected = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=3, strategy=strategy,
                                 captured=train)
        assert code == 0 and json.loads(out)["order"] == [r.index for r in expected], strategy


def test_bad_2dgs_options_name_the_field(tmp_path, capsys) -> None:
    code, _, err = run(capsys, "train", "--model", "2dgs", "--data", LEGO, "--views", "2", "--downscale", "8",
                       "--iterations", "2", "--normal-consistency", "-1", "--out", tmp_path / "x.ply", "--quiet")
    assert code == 2 and "normal_consistency" in err and "Traceback" not in err
