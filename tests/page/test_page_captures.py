"""The page's Captures section in headless Chromium against a real uvicorn server with an API key
(issue 49): a capture made and trained through the Python client from photos the project renders
(tests/support/captures_loop.py), then photos added and a second round trained from the page; the
table, the charts and the 3D view show what the API answers."""

from __future__ import annotations

import pytest

from client import PHDClient
from support.browser import chromium, have_browser
from support.captures_loop import LoopPhotos, loop_photos

pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
if not have_browser():
    pytest.skip("no browser: install Debian's chromium and chromium-driver (scripts/test.sh does, as root)",
                allow_module_level=True)
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select  # noqa: E402

from support.page import choose_files, set_field, text_of, wait  # noqa: E402

KEY = "captures-page-key"
ITERATIONS, DOWNSCALE, SAMPLES = 60, 2, 4      # a round trains in seconds on these photos


def _rows(driver) -> list[list[str]]:
    return driver.execute_script("return [...document.querySelectorAll('#rounds-table tbody tr')]"
                                 ".map(r => [...r.cells].map(c => c.textContent))")


def _view(driver) -> dict:
    return driver.execute_script("return window.phdView3d.debug()")


def _shows_latest_model(driver) -> bool:
    """The 3D view has drawn the shown capture's latest model."""
    return driver.execute_script("return Boolean(loop.shown && state.viewReady "
                                 "&& state.modelId === loop.shown.model_id)")


def test_the_captures_rounds_as_the_api_gives_them(tmp_path, svc_start) -> None:
    """Round 0 from the client: one row with its model's numbers, its 12 cameras as frusta over the
    model the section chose. Round 1 from the page: the photos added (a photo of something else
    named as not registered) while the page polls the job, a warm start trained with the section's
    Train; every number in the table and the charts is the API's, one frustum per captured camera
    per round in its own colour, and no request breaks the CSP."""
    shots: LoopPhotos = loop_photos(tmp_path / "photos")
    server = svc_start(capture_max_size=shots.max_size, api_key=KEY)
    with PHDClient(server.url, api_key=KEY) as phd:
        capture = phd.create_capture(shots.initial, test=shots.test, name="scene", **shots.sfm)
        first = capture.train(iterations=ITERATIONS, downscale=DOWNSCALE, samples=SAMPLES).summary

        driver = chromium(tmp_path / "profile")
        try:
            driver.get(server.url + "/ui/")
            set_field(driver, "api-key", KEY)
            driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
            wait(driver, lambda d: len(Select(d.find_element(By.ID, "capture-select")).options) == 2,
                 what="the capture list")
            Select(driver.find_element(By.ID, "capture-select")).select_by_value(capture.id)
            wait(driver, lambda d: len(_rows(d)) == 1 and _shows_latest_model(d), what="round 0 and its model")
            assert driver.find_element(By.ID, "model-select").get_attribute("value") == first.model_id
            row = _rows(driver)[0]
            assert row[:4] == ["0", str(shots.initial_count), str(shots.initial_count), "-"]
            assert float(row[5]) == pytest.approx(first.test_psnr, rel=1e-3) and row[9] == "scratch"
            assert [r["frusta"] for r in _view(driver)["rounds"]] == [len(capture.info.rounds[0].captured)]
            assert _view(driver)["training"] == first.train_views      # the model's own, drawn as round 0's

            # Round 1 through the page: the new photos and a photo of something else, registered as a job.
            choose_files(driver, "photos-file", *sorted(shots.more.iterdir()), shots.other)
            driver.find_element(By.ID, "photos-add").click()
            wait(driver, lambda d: len(_rows(d)) == 2 and d.execute_script("return loop.shown.state") == "ready",
                 timeout=60, what="round 1 registered")
            set_field(driver, "train-iterations", ITERATIONS)
            set_field(driver, "train-downscale", DOWNSCALE)
            driver.find_element(By.ID, "capture-train").click()
            wait(driver, lambda d: _rows(d)[1][4] != "-" and _shows_latest_model(d), timeout=60,
                 what="round 1 trained and its model in the view")
            shown = {"rows": _rows(driver), "view": _view(driver),
                     "model": driver.find_element(By.ID, "model-select").get_attribute("value"),
                     "legend": len(driver.find_elements(By.CSS_SELECTOR, ".v3d-round")),
                     "charts": driver.execute_script(
                         "return ['chart-psnr', 'chart-sigma'].map(id => [...document.querySelectorAll("
                         "'#' + id + ' text.value')].map(t => t.textContent))"),
                     "info": text_of(driver, "capture-info"),
                     "errors": [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"
                                or "Content Security Policy" in e["message"]]}
        finally:
            driver.quit()
        info = phd.get_capture(capture.id).info

    assert len(info.rounds) == len(shown["rows"]) == 2
    added = info.rounds[1]
    assert added.not_registered == [shots.other.name] and len(added.registered) == shots.more_count
    second = added.train
    assert second is not None and second.warm_from == first.model_id and info.model_id == second.model_id
    assert shown["model"] == second.model_id                      # the section put the new model in the view
    for row, r in zip(shown["rows"], info.rounds):
        assert row[:4] == [str(r.round), str(len(r.photos)), str(len(r.registered)),
                           ", ".join(r.not_registered) or "-"]
        assert float(row[5]) == pytest.approx(r.train.test_psnr, rel=1e-3)
        assert float(row[6]) == pytest.approx(r.train.sigma_max_bar, rel=1e-2)
        assert float(row[7]) == pytest.approx(r.train.r_drop, rel=1e-2)
    assert shown["rows"][1][9].startswith("warm: ")
    assert [[float(v) for v in chart] for chart in shown["charts"]] == [
        pytest.approx([r.train.test_psnr for r in info.rounds], rel=1e-3),
        pytest.approx([r.train.sigma_max_bar for r in info.rounds], rel=1e-2)]
    # One frustum per captured camera per round, each round in its own colour, and a legend key each.
    rounds = shown["view"]["rounds"]
    assert [(r["round"], r["frusta"]) for r in rounds] == [(r.round, len(r.captured)) for r in info.rounds]
    assert rounds[0]["rgb"] != rounds[1]["rgb"] and shown["legend"] == 2
    assert shown["view"]["points"] > 0 and shown["view"]["next"] == 0      # round 1 asked for no next views
    assert f"{info.num_photos} photos registered in 2 rounds" in shown["info"]
    assert shown["errors"] == []
