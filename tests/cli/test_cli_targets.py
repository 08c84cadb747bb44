"""`phd rank --targets FILE|GENERATOR`: the views the model will be looked at from reach the
coverage strategies, from a file or a generator spec, and give the library's ranking."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from uq.test_visibility_strategy import camera, open_box

from phd_cli import main
from phd_core import uq as phd
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import write_ply
from phd_core.uq.candidates import candidate_cameras

CAPTURED = [camera((5.0, 0.0, 0.2))]                                   # at the walls' height
CANDIDATES = [camera((-5.0, 0.2, 0.2)), camera((0.0, 0.3, 5.0))]        # behind the box | above it
TARGETS = [camera((0.4, 0.0, 6.0)), camera((-0.3, 0.4, 5.5))]           # above: the inside


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def box(tmp_path_factory) -> dict[str, Path]:
    """The open box (walls around a cluster only a view from above sees), one captured camera at the
    walls' height, candidates behind the box and above it, targets above."""
    root = tmp_path_factory.mktemp("cli_targets")
    write_ply(open_box().model, root / "box.ply")
    files = {"model": root / "box.ply", "captured": root / "captured.json", "candidates": root / "candidates.json",
             "targets": root / "targets.json"}
    for key, cameras in (("captured", CAPTURED), ("candidates", CANDIDATES), ("targets", TARGETS)):
        files[key].write_text(json.dumps([c.to_frame() for c in cameras]))
    return files


def test_rank_weighs_the_candidates_by_the_target_views_from_a_file_or_a_generator(box, capsys) -> None:
    argv = ["rank", "--model", box["model"], "--candidates", box["candidates"], "--captured", box["captured"],
            "--dropout-ratio", 0.3, "--samples", 4, "--json"]
    renderer = load_model(box["model"])
    code, out, _ = run(capsys, *argv, "--targets", box["targets"])
    told = json.loads(out)
    expected = phd.rank_views(renderer, CANDIDATES, ratio=0.3, samples=4, captured=CAPTURED, targets=TARGETS)
    assert code == 0 and told["targets"] == 2 and told["order"] == [r.index for r in expected] == [1, 0]
    assert [r["score"] for r in told["ranking"]] == pytest.approx([r.score for r in expected], rel=1e-12)
    code, out, _ = run(capsys, *argv)
    plain = json.loads(out)
    assert code == 0 and plain["targets"] is None and plain["order"] == [0, 1]   # unseen far wall first

    # A generator spec is placed around the model's cameras as --candidates' are (a ring at the walls' height).
    code, out, _ = run(capsys, *argv, "--targets", "orbit:6,elevation=0.1")
    ring_targets = candidate_cameras("orbit", 6, renderer=renderer, elevation=0.1)
    expected = phd.rank_views(renderer, CANDIDATES, ratio=0.3, samples=4, captured=CAPTURED, targets=ring_targets)
    assert code == 0 and json.loads(out)["order"] == [r.index for r in expected]


def test_rank_refuses_targets_for_a_strategy_that_ignores_them(box, capsys) -> None:
    code, _, err = run(capsys, "rank", "--model", box["model"], "--candidates", box["candidates"],
                       "--dropout-ratio", 0.3, "--samples", 4, "--strategy", "fvs", "--targets", box["targets"])
    assert code == 2 and "targets: strategy 'fvs' ignores target views" in err
    code, _, err = run(capsys, "rank", "--model", box["model"], "--candidates", box["candidates"],
                       "--dropout-ratio", 0.3, "--samples", 4, "--targets", "missing/targets.json")
    assert code == 2 and "targets: no such file" in err


def test_rank_renders_targets_at_the_candidates_size_as_the_service_does(box, capsys, tmp_path) -> None:
    """Targets written at twice the candidates' size (a capture's full-size frames) rank exactly as
    targets at the candidates' size: the service's rule (`targets_at_size`), not their photos' size."""
    large = tmp_path / "large_targets.json"
    large.write_text(json.dumps([c.resized(2 * c.width, 2 * c.height).to_frame() for c in TARGETS]))
    argv = ["rank", "--model", box["model"], "--candidates", box["candidates"], "--captured", box["captured"],
            "--dropout-ratio", 0.3, "--samples", 4, "--json", "--targets"]
    code, out, _ = run(capsys, *argv, large)
    expected = phd.rank_views(load_model(box["model"]), CANDIDATES, ratio=0.3, samples=4, captured=CAPTURED,
                              targets=TARGETS)
    assert code == 0 and [r["score"] for r in json.loads(out)["ranking"]] == pytest.approx(
        [r.score for r in expected], rel=1e-6)
    # Portrait targets keep their aspect: the longer side becomes the candidates' longest.
    portrait = [TARGETS[0].resized(40, 80)]
    assert [(c.width, c.height) for c in phd.targets_at_size(portrait, CANDIDATES)] == [
        (CANDIDATES[0].width // 2, CANDIDATES[0].width)]


def test_rank_names_the_rule_that_ordered_it_in_its_json_and_its_table(box, capsys) -> None:
    argv = ["rank", "--model", box["model"], "--candidates", box["candidates"], "--captured", box["captured"],
            "--dropout-ratio", 0.3, "--samples", 4]
    renderer = load_model(box["model"])
    expected = phd.rank_views(renderer, CANDIDATES, ratio=0.3, samples=4, captured=CAPTURED, targets=TARGETS).rule
    code, out, _ = run(capsys, *argv, "--targets", box["targets"], "--json")
    assert code == 0 and json.loads(out)["rule"] == expected
    assert expected == "spread from the captured views, toward what the target views show that no captured view saw"
    code, out, _ = run(capsys, *argv)
    assert code == 0 and "(visibility_sigma_fvs: spread from the captured views, toward what no captured view saw)" \
        in out.splitlines()[0]
