"""A real capture with lens distortion through the client and the page as through the command
line: drone_flight1 (one OPENCV camera; its photos undistorted by pycolmap) trained by `phd
train` for 60 steps at 55x29 px, its test frames written by `phd candidates frames` and ranked by
`phd rank`; then the PLY and its sidecar through the Python client and through the page in
headless Chromium, against a real uvicorn server with an API key. bench/bench_real.py takes
every real capture through the same doors (tests/support/doors.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from support.browser import chromium, have_browser
from support.cli import run

pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
if not have_browser():
    pytest.skip("no browser: install Debian's chromium and chromium-driver (scripts/test.sh does, as root)",
                allow_module_level=True)
from support.doors import through_client, through_page  # noqa: E402

CAPTURE = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "drone_flight1"
KEY = "real-capture-key"
ORBIT, TOP_K, SAMPLES = 8, 3, 8        # small: the test's budget is seconds, the bench's minutes


def test_a_distorted_capture_ranks_alike_through_the_cli_the_client_and_the_page(tmp_path, capsys) -> None:
    """The same model, cameras, masks and code behind every door: the same r_drop, and the
    test frames in the same order with the same scores to the bit. The page shows the model's
    12 training cameras and its splats in the 3D view and the plot, a frustum and a dot per
    ranked frame, and every heat map at its frame's size; the page's ring is ranked as the
    client ranks the same request."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    model, frames = tmp_path / "drone.ply", tmp_path / "test_frames.json"
    code, _, err = run(capsys, "train", "--data", CAPTURE, "--views", 12, "--downscale", 4, "--iterations", 60,
                       "--out", model, "--quiet")
    assert code == 0, err
    assert run(capsys, "candidates", "frames", "--data", CAPTURE, "--split", "test", "--out", frames)[0] == 0
    cli = {}
    for name, candidates in (("frames", [frames]), ("orbit", [f"orbit:{ORBIT}", "--top-k", TOP_K])):
        code, out, err = run(capsys, "rank", "--model", model, "--candidates", *candidates, "--samples", SAMPLES,
                             "--json", "--quiet")
        assert code == 0, err
        cli[name] = json.loads(out)
    sidecar = json.loads(model.with_suffix(".json").read_text())
    sizes = [[f["w"], f["h"]] for f in json.loads(frames.read_text())["frames"]]
    assert len(sizes) == 9 and sizes[0] == [220, 115]          # the undistorted photos' size, 240 px wide before

    server = BackgroundServer(Settings(data_dir=tmp_path / "data", api_key=KEY))
    driver = chromium(tmp_path / "profile")
    try:
        client = through_client(server.url, KEY, model, frames, orbit=ORBIT, top_k=TOP_K, samples=SAMPLES)
        page = through_page(driver, server.url, KEY, model, frames, orbit=ORBIT, top_k=TOP_K, samples=SAMPLES,
                            timeout=60)
    finally:
        driver.quit()
        server.stop()

    r_drop = cli["frames"]["dropout_ratio"]
    assert 0 < r_drop < 0.9 and client["r_drop"] == page["r_drop"] == r_drop
    order, scores = cli["frames"]["order"], [view["score"] for view in cli["frames"]["ranking"]]
    assert sorted(order) == list(range(9)) and len(set(scores)) == 9
    for door in (client["frames"], page["frames"]):
        assert (door["order"], door["scores"]) == (order, scores)
    assert client["orbit"]["order"] == cli["orbit"]["order"] and len(cli["orbit"]["order"]) == TOP_K
    assert client["training_cameras"] == 12 and client["heatmap_size"] == client["frame_size"] == sizes[order[0]]

    shown = page["frames"]
    assert shown["view"] == {"training": 12, "splats": sidecar["num_splats"], "frusta": 9}
    assert shown["plot"] == {"training": 12, "candidates": 9}
    assert shown["heatmap_sizes"] == shown["frame_sizes"] == [sizes[i] for i in order]
    assert page["orbit"]["order"] == page["orbit_through_client"]["order"]
    assert page["orbit"]["view"]["frusta"] == page["orbit"]["plot"]["candidates"] == TOP_K
    assert page["console_errors"] == []
