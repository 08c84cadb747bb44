"""What the `phd` command says while it works and what it keeps: progress bars on stderr (only
when asked or on a terminal), the calibration stored beside the model and reused, the ranking
table, the trainer's defaults in its help, a refused --out suffix and the demo's closing lines.
The real `phd` entry (`phd_cli.main`) on a tiny model with real files."""

from __future__ import annotations

import argparse
import json
import re
import shlex

import numpy as np
import pytest
import torch

from phd_cli import build_parser, main
from phd_cli.demo import next_steps
from phd_cli.train import DEFAULT_ITERATIONS
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import SIDECAR_FORMAT, sidecar_path, write_ply
from support.captures import write_images
from support.cli import run
from support.fixtures import svc_random_gaussians
from support.toy_renderers import ring_cameras

SIZE, FOV = 16, 0.7
BAR = "%|"          # what a tqdm bar line holds (percentage, then the bar)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    """A 3DGS PLY with a sidecar naming its training cameras, a Blender-layout capture whose
    train split holds those cameras and whose images are the model's renders, and candidates."""
    root = tmp_path_factory.mktemp("cli_report")
    model = svc_random_gaussians(200, seed=11)
    path = root / "model.ply"
    write_ply(model, path)
    renderer = load_model(path)
    train, test = ring_cameras(3, size=SIZE), ring_cameras(4, size=SIZE, height=1.6)
    sidecar_path(path).write_text(json.dumps({"format": SIDECAR_FORMAT, "background": [1.0, 1.0, 1.0],
                                              "training_cameras": [c.to_frame() for c in train]}))
    data = root / "data"
    for split, cameras in (("train", train), ("test", test)):
        write_images(data / split, [renderer.render(c)[0].numpy() for c in cameras],
                     [f"r_{i}.png" for i in range(len(cameras))])
        frames = [{"file_path": f"./{split}/r_{i}", "transform_matrix": c.c2w.tolist()} for i, c in enumerate(cameras)]
        (data / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV, "frames": frames}))
    candidates = root / "candidates.json"
    candidates.write_text(json.dumps([c.to_frame() for c in ring_cameras(7, size=SIZE, height=0.4)]))
    return {"root": root, "model": path, "data": data, "candidates": candidates}


CALIBRATION = ["--epsilon", 100, "--step", 0.25]        # every ratio passes: r_drop 0.75, quickly


def commands(files, tmp) -> dict[str, list]:
    """One small run of every command that shows progress, and the label of its bar."""
    model, data = files["model"], files["data"]
    return {
        "calibrate": ["calibrate", "--model", model, *CALIBRATION, "--samples", 2],
        "uq": ["uq", "--model", model, "--data", data, "--dropout-ratio", 0.3, "--samples", 3, "--no-heatmaps",
               "--out", tmp / "uq"],
        "rank": ["rank", "--model", model, "--candidates", files["candidates"], "--dropout-ratio", 0.3,
                 "--samples", 3, "--json"],
        "select": ["select", "--model-a", model, "--model-b", model, "--data", data, "--ratio-a", 0.3, "--ratio-b",
                   0.2, "--samples", 3, "--rule", "sigma_mean"],
        "render": ["render", "--model", model, "--data", data, "--out", tmp / "render"],
    }


def test_progress_goes_to_stderr_when_forced_and_never_with_quiet(files, capsys, tmp_path) -> None:
    for label, argv in commands(files, tmp_path).items():
        code, out, err = run(capsys, *argv, "--progress")
        assert code == 0, err
        bars = [line for line in err.replace("\r", "\n").splitlines() if BAR in line]
        assert bars and all(line.startswith(label) for line in bars), (label, err)
        assert any("100%" in line for line in bars), err            # the bar ran to its end
        assert BAR not in out
        if label in ("rank", "select"):
            json.loads(out)                                          # stdout is the result alone
        code, out, err = run(capsys, *argv, "--quiet")
        assert code == 0 and BAR not in err + out, err
        code, _, err = run(capsys, *argv)                            # stderr is no terminal here: no bar
        assert code == 0 and BAR not in err, err


def test_quiet_and_progress_exclude_each_other(files, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["rank", "--model", str(files["model"]), "--candidates", "orbit:3", "--quiet", "--progress"])
    assert "not allowed with" in capsys.readouterr().err


@pytest.mark.parametrize("command, field", [
    (["rank", "--candidates", "{candidates}", "--targets", "{root}/walk/targets.json"], "targets"),
    (["rank", "--candidates", "{candidates}", "--targets", "orbit:3", "--strategy", "sigma_max"], "targets"),
    (["rank", "--candidates", "{candidates}", "--top-k", "0"], "top_k"),
    (["rank", "--candidates", "{candidates}", "--coarse", "2"], "coarse"),
    (["rank", "--candidates", "{candidates}", "--export", "{root}/plan.yaml"], "export"),
    (["rank", "--candidates", "{candidates}", "--samples", "1"], "samples"),
    (["uq", "--data", "{data}", "--samples", "1", "--out", "{root}/uq"], "samples"),
    (["uq", "--data", "{data}", "--vmax", "0", "--out", "{root}/uq"], "vmax"),
    (["select", "--model-b", "{model}", "--data", "{data}", "--ratio-b", "2"], "ratio_b"),
])
def test_every_input_is_checked_before_anything_is_calibrated(files, capsys, tmp_path, command, field) -> None:
    """A bad target file, option or number is refused (exit 2, naming it) before r_drop is
    calibrated: nothing is stored beside the model."""
    model = tmp_path / "model.ply"                                  # a copy without a stored calibration
    model.write_bytes(files["model"].read_bytes())
    sidecar_path(model).write_bytes(sidecar_path(files["model"]).read_bytes())
    names = {"candidates": files["candidates"], "data": files["data"], "root": tmp_path, "model": model}
    argv = [command[0], "--model-a" if command[0] == "select" else "--model", model,
            *[word.format(**names) for word in command[1:]], *CALIBRATION, "--calibration-samples", 2]
    code, _, err = run(capsys, *argv)
    assert code == 2 and f"{field}:" in err and "Traceback" not in err, err
    assert "calibrated" not in err and not model.with_name("model.ply.phd-cache").exists()


def test_a_misspelt_frames_key_is_named_with_the_keys_found(files, capsys, tmp_path) -> None:
    """As the page does: a "frame" typo (top level or in a frame) lists the keys the file holds."""
    frames = json.loads(files["candidates"].read_text())
    (tmp_path / "typo.json").write_text(json.dumps({"camera_angle_x": FOV, "frame": frames}))
    frames[1]["transfrom_matrix"] = frames[1].pop("transform_matrix")
    (tmp_path / "typo2.json").write_text(json.dumps({"frames": frames}))
    for name, said in (("typo.json", "no 'frames' list (its keys: 'camera_angle_x', 'frame')"),
                       ("typo2.json", "frames[1].transform_matrix: missing from the frame (its keys: ")):
        code, _, err = run(capsys, "rank", "--model", files["model"], "--candidates", tmp_path / name,
                           "--dropout-ratio", 0.3, "--samples", 3)
        assert code == 2 and said in err, err
    assert "'transfrom_matrix'" in err


def test_calibration_is_stored_beside_the_model_and_reused(files, capsys, tmp_path) -> None:
    cache = files["model"].with_name("model.ply.phd-cache")
    code, out, err = run(capsys, "calibrate", "--model", files["model"], *CALIBRATION, "--samples", 2)
    assert code == 0 and "r_drop = 0.75" in out
    stored = sorted(cache.glob("calibration-*.json"))
    assert len(stored) == 1 and f"stored in {stored[0]}" in err
    entry = json.loads(stored[0].read_text())
    assert entry["by"] == "phd calibrate" and entry["result"]["r_drop"] == 0.75 and entry["views"] == 3

    # A ratio no calibration with step 0.25 can give: rank must take it from the file, not calibrate.
    entry["result"]["r_drop"] = 0.123
    stored[0].write_text(json.dumps(entry))
    rank = ["rank", "--model", files["model"], "--candidates", files["candidates"], "--samples", 3, "--json",
            *CALIBRATION, "--calibration-samples", 2]
    code, out, err = run(capsys, *rank)
    assert code == 0 and json.loads(out)["dropout_ratio"] == 0.123
    assert "from the calibration stored by `phd calibrate`" in err and "--recalibrate" in err
    for command in (["uq", "--model", files["model"], "--data", files["data"], *CALIBRATION, "--calibration-samples",
                     2, "--samples", 3, "--no-heatmaps", "--out", tmp_path / "uq"],
                    ["select", "--model-a", files["model"], "--model-b", files["model"], "--data", files["data"],
                     *CALIBRATION, "--calibration-samples", 2, "--samples", 3]):
        code, out, err = run(capsys, *command)
        assert code == 0 and "from the calibration stored by `phd calibrate`" in err, err
    assert json.loads((tmp_path / "uq" / "report.json").read_text())["dropout_ratio"] == 0.123
    assert json.loads(out)["ratio_a"] == json.loads(out)["ratio_b"] == 0.123

    # Other settings that change r_drop miss and calibrate (and store) anew; --recalibrate replaces the entry.
    code, out, err = run(capsys, *rank, "--recalibrate")
    assert code == 0 and json.loads(out)["dropout_ratio"] == 0.75 and "calibrated, r_drop 0.75; stored in" in err
    assert json.loads(stored[0].read_text())["result"]["r_drop"] == 0.75
    assert json.loads(stored[0].read_text())["by"] == "phd rank"
    code, out, err = run(capsys, *rank, "--signal", "premultiplied")
    assert code == 0 and "calibrated, r_drop" in err and len(list(cache.glob("calibration-*.json"))) == 2


def test_rank_prints_a_table_of_the_top_k_with_the_json_poses(files, capsys) -> None:
    argv = ["rank", "--model", files["model"], "--candidates", files["candidates"], "--dropout-ratio", 0.3,
            "--samples", 3, "--top-k", 3]
    code, table, err = run(capsys, *argv)
    assert code == 0, err
    with pytest.raises(json.JSONDecodeError):
        json.loads(table)
    rows = [line.split() for line in table.splitlines() if re.match(r"\s*#\d", line)]
    code, out, _ = run(capsys, *argv, "--json")
    ranking = json.loads(out)["ranking"]
    assert len(rows) == len(ranking) == 3 and [r["rank"] for r in ranking] == [1, 2, 3]
    for row, ranked in zip(rows, ranking):
        assert [int(row[0][1:]), int(row[1])] == [ranked["rank"], ranked["index"]]     # #1 is rank 1, as the JSON says
        assert float(row[2]) == pytest.approx(ranked["score"], rel=1e-3)
        assert float(row[3]) == pytest.approx(ranked["sigma_max"], rel=1e-3)
        c2w = np.array(ranked["camera"]["transform_matrix"])
        assert [float(v) for v in row[4:7]] == pytest.approx(c2w[:3, 3].tolist(), abs=1e-4)
        assert [float(v) for v in row[7:10]] == pytest.approx((-c2w[:3, 2]).tolist(), abs=1e-3)

    # Without --top-k: the first rows and how to get the rest.
    code, table, _ = run(capsys, *argv[:-2])
    assert code == 0 and len([line for line in table.splitlines() if re.match(r"\s*#\d", line)]) == 7
    assert "JSON" not in table and "written to" not in table


def test_an_out_suffix_of_another_family_is_refused(files, capsys, tmp_path) -> None:
    for family, out in (("nerf", "model.ply"), ("3dgs", "model.nerf"), ("2dgs", "model")):
        code, _, err = run(capsys, "train", "--model", family, "--data", files["data"], "--iterations", 1,
                           "--out", tmp_path / out)
        assert code == 2 and err.startswith("phd train: error: out: ") and out in err, err
    assert not list(tmp_path.iterdir())                              # refused before anything was trained


def test_train_help_states_the_default_iterations_every_trainer_uses(capsys) -> None:
    from phd_core.train.nerf import DEFAULT_ITERATIONS as NERF_DEFAULT
    from phd_core.train.splats import TrainConfig

    assert TrainConfig().iterations == NERF_DEFAULT == DEFAULT_ITERATIONS
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"default {DEFAULT_ITERATIONS}" in text and "minutes" in text


def test_help_shows_registry_text_with_percent_signs_as_it_is(capsys, monkeypatch) -> None:
    """A strategy registered with '%' in its summary (bench/nbv_experiments.py has 'the top 10 %')
    is shown as written: argparse %-formats help, and such a text broke `phd rank --help`."""
    import dataclasses

    from phd_core.uq.strategies import STRATEGIES

    monkeypatch.setitem(STRATEGIES, "random", dataclasses.replace(STRATEGIES["random"], summary="the top 10 % of it"))
    with pytest.raises(SystemExit):
        main(["rank", "--help"])
    assert "random: the top 10 % of it" in " ".join(capsys.readouterr().out.split())


def test_train_says_its_views_and_size_and_shows_no_time_left_while_splats_grow(files, capsys, tmp_path) -> None:
    """The last line names the views and the size trained on; the hint before training is this
    capture's (2 views at 16x16, 12 steps), and the bar (forced, --progress) gives no time left
    until densification ends, then tqdm's."""
    code, out, err = run(capsys, "train", "--data", files["data"], "--views", 2, "--downscale", 1, "--iterations", 12,
                         "--progress", "--out", tmp_path / "m.ply")
    assert code == 0, err
    assert " on 2 views at 16x16 in " in out.splitlines()[-1]
    assert "phd train: training 2 views at 16x16 for 12 steps: about " in err
    frames = [part for part in re.split(r"[\r\n]", err) if BAR in part]
    assert "stop growing" in frames[0] and "<" not in frames[0]                  # step 0: no estimate
    assert frames[-1].count("12/12") == 1 and "<00:00" in frames[-1]            # densification over: tqdm's


def test_the_time_hint_is_the_captures_own(capsys) -> None:
    """Steps x pixels of a view x the CPU time per pixel-step measured on lego_200 (246 s for
    2000 steps at 100x100): a phone capture's 71 views at 720x1280 are 92x lego's pixels."""
    from phd_cli.train import time_hint
    from phd_core.scene import Camera

    phone = [Camera(torch.eye(4, dtype=torch.float64), 900.0, 900.0, 360.0, 640.0, 720, 1280)] * 71
    minutes = 2000 * 720 * 1280 * (246 / (2000 * 100 * 100)) / 60
    assert time_hint(phone, 2000).startswith(f"training 71 views at 720x1280 for 2000 steps: about {minutes:.1f} "
                                             "minutes of CPU time")
    lego = [Camera(torch.eye(4, dtype=torch.float64), 111.0, 111.0, 50.0, 50.0, 100, 100)] * 16
    assert f"about {246 / 60:.1f} minutes" in time_hint(lego, 2000)               # the measured run itself


def test_the_demo_draws_no_bars_into_a_file_and_ranks_from_1(capsys, tmp_path) -> None:
    """`phd demo` on a tiny Blender scene (64 train views for its two disjoint 16-view sets, 8x8
    pixels), its stderr and stdout files, not terminals: no tqdm bar, no redrawn percentages;
    its table and report.json count ranks from 1, as the CLI, REST and the page do."""
    scene = tmp_path / "scene"
    g = np.random.default_rng(0)
    for split, count, height in (("train", 64, 0.8), ("test", 3, 1.4)):
        cameras = ring_cameras(count, size=8, height=height)
        write_images(scene / split, [np.clip(0.5 + 0.2 * g.standard_normal((8, 8, 3)), 0, 1) for _ in cameras],
                     [f"r_{i}.png" for i in range(count)])
        frames = [{"file_path": f"./{split}/r_{i}", "transform_matrix": c.c2w.tolist()} for i, c in enumerate(cameras)]
        (scene / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV, "frames": frames}))
    code, out, err = run(capsys, "demo", "--data", scene, "--iterations", 3, "--candidates", 2, "--samples", 2,
                         "--out", tmp_path / "demo")
    assert code == 0, err
    assert BAR not in err and "\r" not in out, err[:300]
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert [row["rank"] for row in report["ranking"]] == [1, 2]


def test_the_demo_ends_with_the_next_three_commands(tmp_path) -> None:
    serve, page, client = next_steps(tmp_path / "model_a.ply", port=8123)
    args = build_parser().parse_args(shlex.split(serve, comments=True)[1:])
    assert isinstance(args, argparse.Namespace) and args.command == "serve" and args.port == 8123
    assert page.split()[0] == "http://127.0.0.1:8123/ui/" and "model_a.json" in page
    words = shlex.split(client, comments=True)
    assert words[:2] == ["python", "-c"]
    compile(words[2], "client", "exec")
    assert "PHDClient('http://127.0.0.1:8123')" in words[2] and str(tmp_path / "model_a.ply") in words[2]
