"""The web page in a real browser: headless Chromium from the distribution's packages, driven
by selenium through the distribution's chromedriver, against a real uvicorn server on
127.0.0.1 that requires an API key. The server sends its Content-Security-Policy (no inline
scripts or styles; images from blob: URLs): any violation fails a test."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import httpx
import imageio.v3 as iio
import numpy as np
import pytest

from client import PHDClient
from phd_core import uq
from phd_core.data import candidate_name, export_cameras
from phd_core.renderers.gs3d import write_ply
from phd_core.scene import camera_from_frame
from phd_core.uq.candidates import candidate_cameras
from support.browser import chromium, have_browser, hold_worker
from support.fixtures import LEGO, svc_cameras, svc_random_gaussians

pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
if not have_browser():
    pytest.skip("no browser: install Debian's chromium and chromium-driver (scripts/test.sh does, as root)",
                allow_module_level=True)
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select  # noqa: E402

from support.page import choose_files, console_errors, grid_loaded, run_on_candidates, set_field, text_of, wait  # noqa: E402

KEY = "page-test-key"
AUTH = {"Authorization": f"Bearer {KEY}"}
@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = chromium(tmp_path_factory.mktemp("chromium-profile"))
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def models(tmp_path_factory, svc_model_files):
    """A server with the key on and the CSP sent; two calibrated 3DGS models with training cameras."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    server = BackgroundServer(Settings(data_dir=tmp_path_factory.mktemp("page-data"), api_key=KEY))
    try:
        with PHDClient(server.url, api_key=KEY) as phd:
            a = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3), name="model-a")
            b = phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(4, phase=0.4), name="model-b")
            for model in (a, b):
                phd.calibrate(model.id, epsilon=0.05, step=0.2, samples=3, seed=1)
        yield server, a, b
    finally:
        server.stop()


def _open(driver, server) -> None:
    driver.get(server.url + "/")   # redirects to /ui/
    assert driver.current_url.endswith("/ui/")
    policy = httpx.get(server.url + "/ui/").headers["content-security-policy"]
    assert "script-src 'self';" in policy and "style-src 'self';" in policy and "unsafe-inline" not in policy
    set_field(driver, "api-key", KEY)
    driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(driver, lambda d: len(Select(d.find_element(By.ID, "model-select")).options) == 2
         and text_of(d, "message") == "key saved in this browser", what="the model list")


def _open_empty(driver, server) -> None:
    """The page on a server that holds no model yet, with the key given."""
    driver.get(server.url + "/ui/")
    set_field(driver, "api-key", KEY)
    driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(driver, lambda d: "No model yet" in text_of(d, "model-info"), what="the empty model list")


def _in_view(driver, element_id: str) -> bool:
    """Whether the element is shown and lies within the browser window as it is scrolled."""
    return driver.execute_script(
        "const r = document.getElementById(arguments[0]).getBoundingClientRect(); "
        "return r.height > 0 && r.top >= 0 && r.bottom <= window.innerHeight", element_id)


def _classes(driver, element_id: str) -> list[str]:
    return driver.find_element(By.ID, element_id).get_attribute("class").split()


def _assert_select_labels_match_rank_labels(driver) -> None:
    """Every selection card names its candidate as the rank card of that candidate does."""
    rank = {card.get_attribute("data-index"): (card.get_attribute("data-rank"),
                                               card.find_element(By.CSS_SELECTOR, ".title").text)
            for card in driver.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")}
    cards = driver.find_elements(By.CSS_SELECTOR, "#select-grid li.card")
    assert cards
    for card in cards:
        index, title = card.get_attribute("data-index"), card.find_element(By.CSS_SELECTOR, ".title").text
        assert card.get_attribute("data-rank") == rank[index][0]
        assert title.startswith(rank[index][1] + ": trust "), (title, rank[index])


def _csp_violations(driver) -> list[str]:
    return [entry["message"] for entry in driver.get_log("browser")
            if "Content Security Policy" in entry["message"] or "Refused to" in entry["message"]]


def test_page_ranks_a_model_and_shows_the_services_order(browser, models, tmp_path):
    server, model_a, _ = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    wait(browser, lambda d: "r_drop" in d.find_element(By.ID, "model-info").text, what="the model's facts")
    # The strategy field starts at the service's default and offers the registry's names.
    assert browser.find_element(By.ID, "rank-strategy").get_attribute("value") == uq.DEFAULT_STRATEGY
    offered = browser.execute_script("return [...document.querySelectorAll('#strategies option')].map(o => o.value)")
    assert offered == list(uq.STRATEGIES)
    # The page makes no poses itself: it asks the service's generator and draws what comes back.
    assert browser.execute_script("return typeof generateCandidates") == "undefined"
    run_on_candidates(browser, 7, "rank", {"rank-samples": 4, "rank-downscale": 1, "rank-seed": 3})

    # The same request through the Python client gives the order the grid shows, and the poses.
    spec = browser.execute_script("return state.spec")
    assert spec["generator"] == "orbit" and spec["options"] == {"elevation": pytest.approx(math.radians(30))}
    with PHDClient(server.url, api_key=KEY) as phd:
        expected = phd.rank(model_a.id, candidates=spec, samples=4, seed=3, downscale=1, heatmaps="files")
        drawn = browser.execute_script("return shownCandidates().map(c => [c.index, c.frame])")
        assert drawn == [[v.index, v.camera] for v in expected.views]
        generated = candidate_cameras("orbit", 7, cameras=svc_cameras(3), elevation=spec["options"]["elevation"])
        assert [v.camera for v in expected.views] == [generated[v.index].to_frame() for v in expected.views]
        cards = browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")
        assert [int(c.get_attribute("data-index")) for c in cards] == [v.index for v in expected.views]
        assert [int(c.get_attribute("data-rank")) for c in cards] == list(range(1, 8))      # #1 first, as REST says
        scores = [float(c.find_element(By.CSS_SELECTOR, "dd.score").text) for c in cards]
        assert scores == pytest.approx([v.score for v in expected.views], rel=1e-3)
        # Every heat map and render loaded, at the rendered size, and shows the artefact's pixels.
        sizes = browser.execute_script("return [...document.querySelectorAll('#rank-grid img')].map("
                                       "i => [i.className, i.naturalWidth, i.naturalHeight, i.src.slice(0, 5)])")
        assert len(sizes) == 14 and {s[0] for s in sizes} == {"render", "heatmap"}
        assert all(s[1:] == [24, 24, "blob:"] for s in sizes)
        first = cards[0].find_element(By.CSS_SELECTOR, "img.heatmap")
        shown = browser.execute_script(
            "const i = arguments[0], c = document.createElement('canvas'); c.width = i.naturalWidth; "
            "c.height = i.naturalHeight; const g = c.getContext('2d'); g.drawImage(i, 0, 0); "
            "return Array.from(g.getImageData(0, 0, c.width, c.height).data)", first)
        truth = iio.imread(phd.download(expected.views[0].heatmap_url))
        assert np.array_equal(np.array(shown, dtype=np.uint8).reshape(24, 24, 4)[..., :3], truth)

    # The plots: one coloured dot per returned pose, a cross per training camera, in both views;
    # from above, the dots sit where the returned poses' centres project (the plot's own axes).
    for plot in ("plot-top", "plot-side"):
        assert len(browser.find_elements(By.CSS_SELECTOR, f"#{plot} circle.cand[fill]")) == 7
        assert len(browser.find_elements(By.CSS_SELECTOR, f"#{plot} path.train")) == 3
    dots = browser.execute_script(
        "const f = captureFrame(), [u, w] = horizontalAxes(f.up); return shownCandidates().map(c => {"
        "const p = sub(position(c.frame), f.center); return [c.index, dot(p, u), dot(p, w)]; })")
    radii = [math.hypot(x, y) for _, x, y in dots]
    assert max(radii) - min(radii) < 1e-6 * max(radii)          # one ring: every pose at one horizontal radius
    top = browser.find_element(By.CSS_SELECTOR, f"#plot-top circle[data-index='{expected.views[0].index}']")
    assert top.get_attribute("fill") == "rgb(253,231,37)"   # the highest score gets the top colour
    browser.save_screenshot(str(tmp_path / "page_rank.png"))
    assert (tmp_path / "page_rank.png").stat().st_size > 10_000
    assert _csp_violations(browser) == []


def test_page_drops_a_ranking_that_finishes_after_the_model_changed(browser, models):
    """A rank job still queued when another model is chosen: its answer is for the first model,
    so no cards, frusta or download row appear for the second, and the rank section says why."""
    server, model_a, model_b = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    wait(browser, lambda d: d.execute_script("return state.modelId === arguments[0] && state.viewReady", model_a.id),
         what="model A's 3D view")
    set_field(browser, "gen-count", 3)
    browser.find_element(By.ID, "gen-elevation").click()
    wait(browser, lambda d: (d.execute_script("return state.spec") or {}).get("count") == 3, what="3 candidates")
    set_field(browser, "rank-samples", 3)
    held = hold_worker(server.url, AUTH, model_b.id)
    try:
        browser.find_element(By.ID, "rank-run").click()
        # The rank job waits in the queue behind the held one.
        wait(browser, lambda d: d.execute_script("return state.job"), what="the rank job")
        Select(browser.find_element(By.ID, "model-select")).select_by_value(model_b.id)
        wait(browser, lambda d: d.execute_script("return state.modelId === arguments[0] && state.viewReady",
                                                 model_b.id), what="model B's 3D view")
        assert browser.execute_script("return state.job") is not None          # model A's job still waits
    finally:
        httpx.delete(f"{server.url}/v1/jobs/{held}", headers=AUTH)
    wait(browser, lambda d: "another model" in text_of(d, "rank-message"), what="the dropped ranking")
    assert "Rank" in text_of(browser, "rank-message") and "warning" in _classes(browser, "rank-message")
    assert browser.execute_script(
        "return [state.ranking, state.job, document.querySelectorAll('#rank-grid li').length, "
        "phdView3d.debug().frusta.length, document.getElementById('poses-row').hidden]") == [None, None, 0, 0, True]
    assert browser.find_elements(By.CSS_SELECTOR, "#plot-top circle.cand") == []


def test_page_clears_the_ranked_frusta_when_the_candidates_change(browser, models):
    server, model_a, _ = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    wait(browser, lambda d: d.execute_script("return state.modelId === arguments[0] && state.viewReady", model_a.id),
         what="model A's 3D view")
    run_on_candidates(browser, 3, "rank", {"rank-samples": 3, "rank-downscale": 2})
    browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")[0].click()     # its frustum picked, detail shown
    assert len(browser.execute_script("return phdView3d.debug().frusta")) == 3
    wait(browser, lambda d: d.execute_script("return !document.querySelector('#view3d .v3d-detail').hidden"),
         what="the picked candidate's detail")
    set_field(browser, "gen-count", 2)
    browser.find_element(By.ID, "gen-elevation").click()                         # other candidates: no ranking yet
    wait(browser, lambda d: (d.execute_script("return state.spec") or {}).get("count") == 2, what="2 candidates")
    view = browser.execute_script("return phdView3d.debug()")
    assert (view["frusta"], view["selected"]) == ([], None)
    assert browser.execute_script("return [document.querySelector('#view3d .v3d-detail').hidden, "
                                  "document.querySelectorAll('#view3d .v3d-label').length]") == [True, 0]
    assert "candidate score" not in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text


def test_page_selection_shows_both_renders_and_the_choice(browser, models, tmp_path):
    server, model_a, model_b = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    Select(browser.find_element(By.ID, "model-b-select")).select_by_value(model_b.id)
    rules = Select(browser.find_element(By.ID, "select-rule"))          # the service's rules, its default chosen
    assert [o.get_attribute("value") for o in rules.options] == list(uq.SELECTION_RULES)
    assert rules.first_selected_option.get_attribute("value") == uq.DEFAULT_SELECTION_RULE
    # Generated poses exist once the service made them: selecting before a ranking says so.
    set_field(browser, "gen-count", 4)
    browser.find_element(By.ID, "gen-elevation").click()
    browser.find_element(By.ID, "select-run").click()
    wait(browser, lambda d: "Rank first" in text_of(d, "select-message"), what="the rank-first message")
    assert _in_view(browser, "select-message") and "error" in _classes(browser, "select-message")
    run_on_candidates(browser, 4, "rank", {"rank-samples": 3, "rank-downscale": 2})
    browser.find_element(By.ID, "select-run").click()             # over the 4 poses the ranking returned
    wait(browser, grid_loaded("select", 4), what="the select grid and its images")
    candidates = [v["camera"] for v in browser.execute_script("return state.ranking.views")]
    assert len(candidates) == 4
    with PHDClient(server.url, api_key=KEY) as phd:
        expected = phd.select(model_a.id, model_b.id, candidates, samples=3, seed=0, downscale=2)
    cards = browser.find_elements(By.CSS_SELECTOR, "#select-grid li.card")
    assert [c.get_attribute("data-choice") for c in cards] == [v.choice for v in expected.views]
    _assert_select_labels_match_rank_labels(browser)
    for card, view in zip(cards, expected.views):
        chosen = card.find_elements(By.CSS_SELECTOR, "figure.chosen img")
        assert len(card.find_elements(By.TAG_NAME, "img")) == 2 and len(chosen) == 1
        assert chosen[0].get_attribute("alt").startswith(f"model {view.choice.upper()} ")
    assert f"for {expected.counts['a']} views" in browser.find_element(By.ID, "select-summary").text
    browser.save_screenshot(str(tmp_path / "page_select.png"))
    assert _csp_violations(browser) == []

    # A model B not calibrated yet is calibrated from here: model A stays chosen, its ranking shown.
    write_ply(svc_random_gaussians(200, seed=3), tmp_path / "fresh.ply")
    with PHDClient(server.url, api_key=KEY) as phd:
        fresh = phd.upload_model(tmp_path / "fresh.ply", cameras=svc_cameras(3), name="fresh")
        try:
            assert not browser.find_element(By.ID, "calibrate-b").is_displayed()      # model B is calibrated
            browser.find_element(By.ID, "refresh-models").click()
            wait(browser, lambda d: len(Select(d.find_element(By.ID, "model-b-select")).options) == 3,
                 what="the new model")
            Select(browser.find_element(By.ID, "model-b-select")).select_by_value(fresh.id)
            browser.find_element(By.ID, "calibrate-b").click()
            wait(browser, lambda d: "calibrated fresh: r_drop" in text_of(d, "select-message"), what="model B's r_drop")
            assert phd.get_model(fresh.id).calibration is not None
            assert Select(browser.find_element(By.ID, "model-select")).first_selected_option.get_attribute(
                "value") == model_a.id
            ranked = browser.execute_script("return state.ranking")
            assert ranked["modelId"] == model_a.id and [int(c.get_attribute("data-index")) for c in
                                                        browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")] \
                == [v["index"] for v in ranked["views"]]
            assert not browser.find_element(By.ID, "calibrate-b").is_displayed()
            browser.find_element(By.ID, "select-run").click()           # over the same ranked poses, against B
            wait(browser, lambda d: "(fresh)" in text_of(d, "select-summary"), what="the selection against B")
        finally:
            phd.delete_model(fresh.id)


def test_page_takes_the_users_own_candidate_list(browser, models, tmp_path):
    server, model_a, _ = models
    own = svc_cameras(5, phase=0.9, radius=2.5)
    path = tmp_path / "candidates.json"   # a transforms.json: top-level keys are every frame's defaults
    frames = [c.to_frame() for c in own]
    path.write_text(json.dumps({"w": 24, "h": 24, "frames": [{k: v for k, v in f.items() if k not in ("w", "h")}
                                                             for f in frames]}))
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    browser.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=file]").click()
    assert browser.find_element(By.ID, "generate-options").get_attribute("hidden") is not None
    browser.find_element(By.ID, "cand-file").send_keys(str(path))
    wait(browser, lambda d: d.execute_script("return state.candidates.length") == 5, what="the file's 5 poses")
    sent = browser.execute_script("return state.candidates")
    assert [f["transform_matrix"] for f in sent] == [f["transform_matrix"] for f in frames]
    assert all((f["w"], f["h"]) == (24, 24) for f in sent)       # the defaults reached every frame
    assert "5 poses from candidates.json" in text_of(browser, "cand-info")
    assert len(browser.find_elements(By.CSS_SELECTOR, "#plot-top circle.cand.none")) == 5   # not ranked yet


def _record_requests(driver) -> None:
    """From now on the page's fetch calls are kept in `window.sent` as [url, parsed JSON body]."""
    driver.execute_script(
        "window.sent = []; const fetch_ = window.fetch; window.fetch = (url, options = {}) => { "
        "if (typeof options.body === 'string') window.sent.push([url, JSON.parse(options.body)]); "
        "return fetch_(url, options); };")


def _choose_targets(browser, server, model, tmp_path) -> list[dict]:
    """The page on `model` with 5 candidates of the user's own and 2 target views from a file as
    Blender writes them (camera_angle_x, no image size); returns the target frames as the
    service reads them (the model's training images' 24 x 24)."""
    candidates = tmp_path / "candidates.json"
    candidates.write_text(json.dumps([c.to_frame() for c in svc_cameras(5, phase=0.9, radius=2.5)]))
    targets = [c.to_frame() for c in svc_cameras(2, phase=2.0)]
    walkthrough = tmp_path / "walkthrough.json"
    walkthrough.write_text(json.dumps({"camera_angle_x": 0.7, "frames": [
        {"transform_matrix": f["transform_matrix"]} for f in targets]}))
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model.id)
    wait(browser, lambda d: d.execute_script("return state.modelId === arguments[0] && state.viewReady", model.id),
         what="the model's 3D view")
    browser.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=file]").click()
    choose_files(browser, "cand-file", candidates)
    wait(browser, lambda d: d.execute_script("return state.candidates.length") == 5, what="the 5 candidates")
    choose_files(browser, "targets-file", walkthrough)
    wait(browser, lambda d: text_of(d, "targets-info").startswith("2 target poses from walkthrough.json"),
         what="the target views' line")
    # No size in the file: the fields beside it, filled with the training images' size.
    assert browser.find_element(By.ID, "targets-size").is_displayed()
    assert [browser.find_element(By.ID, f).get_attribute("value") for f in ("targets-width", "targets-height")] \
        == ["24", "24"]
    assert browser.find_element(By.ID, "targets-clear").is_displayed()
    for field, value in (("rank-samples", 3), ("rank-downscale", 1), ("rank-seed", 0)):
        set_field(browser, field, value)
    return [{"camera_angle_x": 0.7, "transform_matrix": f["transform_matrix"], "w": 24, "h": 24} for f in targets]


def test_page_ranks_for_target_views_from_a_file(browser, models, tmp_path):
    """Target views from a file go to the service as the rank request's `targets`; the page shows
    the order the REST API gives for them (not the order without them), says so in the summary,
    draws them in the 3D view, and Clear drops them."""
    server, model_a, _ = models
    targets = _choose_targets(browser, server, model_a, tmp_path)
    assert len(browser.execute_script("return phdView3d.debug().targets")) == 2     # drawn before ranking
    _record_requests(browser)
    browser.find_element(By.ID, "rank-run").click()
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")) == 5, what="the rank grid")
    (url, body), = [(u, b) for u, b in browser.execute_script("return window.sent") if u.endswith("/rank")]
    assert body["targets"] == targets and body["strategy"] == uq.DEFAULT_STRATEGY
    # The REST API's answer to the same request, and without the targets (another order on this model).
    rest = {key: value for key, value in body.items() if key != "async"}
    aimed = httpx.post(server.url + url, json=rest, headers=AUTH, timeout=120)
    plain = httpx.post(server.url + url, json={k: v for k, v in rest.items() if k != "targets"}, headers=AUTH,
                       timeout=120)
    order, untargeted = ([v["index"] for v in answer.json()["views"]] for answer in (aimed, plain))
    cards = browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")
    assert [int(c.get_attribute("data-index")) for c in cards] == order != untargeted
    assert "in the order to capture them for the 2 target views;" in text_of(browser, "rank-summary")
    assert f"strategy {uq.DEFAULT_STRATEGY} ({aimed.json()['rule']})," in text_of(browser, "rank-summary")
    assert text_of(browser, "targets-message") == ""
    assert len(browser.find_elements(By.CSS_SELECTOR, "#plot-top circle.cand[fill]")) == 5
    # Target views whose own size is above the server's cap of 800 pixels a side (a phone's frames):
    # rendered at the candidates' size, so the same order, not a refusal.
    set_field(browser, "targets-width", 1200)
    set_field(browser, "targets-height", 1200)
    browser.find_element(By.ID, "rank-run").click()
    wait(browser, lambda d: "Ranked" in text_of(d, "rank-message") or "error" in _classes(d, "targets-message"),
         what="the ranking for the large target views")
    assert [int(c.get_attribute("data-index")) for c in browser.find_elements(
        By.CSS_SELECTOR, "#rank-grid li.card")] == order, text_of(browser, "targets-message")
    browser.find_element(By.ID, "targets-clear").click()
    wait(browser, lambda d: d.execute_script("return phdView3d.debug().targets.length") == 0, what="cleared targets")
    assert text_of(browser, "targets-info") == "" and not browser.find_element(By.ID, "targets-clear").is_displayed()
    assert browser.execute_script("return [state.targets.length, state.ranking]") == [0, None]   # it was for them
    assert browser.find_elements(By.CSS_SELECTOR, "#plot-top circle.cand[fill]") == []           # its dots too
    assert "target view" not in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert console_errors(browser) == []


def test_page_says_beside_the_target_views_when_the_strategy_ignores_them(browser, models, tmp_path):
    """A strategy that does not weigh coverage by target views (sigma_max, fvs): the service's
    refusal of `targets` is said under the target views' control, in words and in view, not in
    the rank section's line; a target views file that cannot be read is said there too and
    stops the rank rather than ranking without it."""
    server, model_a, _ = models
    _choose_targets(browser, server, model_a, tmp_path)
    for strategy in ("sigma_max", "fvs"):
        set_field(browser, "rank-strategy", strategy)
        browser.find_element(By.ID, "rank-run").click()
        wait(browser, lambda d: "error" in _classes(d, "targets-message"), what=f"{strategy}'s refusal")
        said = text_of(browser, "targets-message")
        assert said.startswith(f"The target views: strategy '{strategy}' ignores target views; choose one that "
                               "weighs the model's coverage by them (visibility, ")
        assert _in_view(browser, "targets-message") and text_of(browser, "rank-message") == ""   # no "ranking..." left
        assert not any(word in said for word in ("422", "field", "/v1"))
        assert browser.find_element(By.ID, "rank-progress").get_attribute("hidden") is not None
    set_field(browser, "rank-strategy", uq.DEFAULT_STRATEGY)
    broken = tmp_path / "broken.json"
    broken.write_text('{"frames": [{"transform_matrix": 1}')
    choose_files(browser, "targets-file", broken)
    wait(browser, lambda d: "broken.json is not valid JSON" in text_of(d, "targets-message"), what="the bad file")
    browser.find_element(By.ID, "rank-run").click()
    wait(browser, lambda d: "could not be read" in text_of(d, "targets-message"), what="the refused rank")
    assert browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card") == []
    assert console_errors(browser, expected=("status of 422",)) == []


def test_page_fits_a_phone_and_names_a_wrong_key(browser, models, tmp_path):
    server, _, _ = models
    browser.set_window_size(390, 844)
    try:
        browser.get(server.url + "/ui/")
        set_field(browser, "api-key", "wrong")
        browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
        wait(browser, lambda d: "refused this API key" in text_of(d, "message"), what="the 401 message")
        said = text_of(browser, "message")                             # in words: no status, code or header
        assert "401" not in said and "unauthorized" not in said and "Authorization" not in said
        _open(browser, server)
        browser.execute_script("document.getElementById('upload-details').open = true; "
                               "document.getElementById('poses-row').hidden = false")   # every control shown
        width = browser.execute_script("return [document.documentElement.scrollWidth, window.innerWidth]")
        assert width[0] <= width[1], f"the page scrolls sideways at a phone's width: {width}"
        browser.save_screenshot(str(tmp_path / "page_phone.png"))
    finally:
        browser.set_window_size(1280, 1600)


def test_page_uploads_calibrates_and_deletes_a_model(browser, svc_model_files, tmp_path):
    """The whole path a person takes on an empty server: upload with cameras, calibrate, delete."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    cameras = tmp_path / "transforms_train.json"
    cameras.write_text(json.dumps({"frames": [c.to_frame() for c in svc_cameras(3)]}))
    server = BackgroundServer(Settings(data_dir=tmp_path / "data", api_key=KEY))
    try:
        _open_empty(browser, server)
        assert browser.find_element(By.ID, "upload-details").get_attribute("open") is not None  # no model: open
        browser.find_element(By.ID, "upload-file").send_keys(str(svc_model_files["ply"]))
        browser.find_element(By.ID, "upload-cameras").send_keys(str(cameras))
        set_field(browser, "upload-name", "uploaded")
        browser.find_element(By.CSS_SELECTOR, "#upload-form button").click()
        wait(browser, lambda d: "not calibrated" in text_of(d, "model-info"), what="the uploaded model")
        assert "3 training cameras" in text_of(browser, "model-info")
        assert Select(browser.find_element(By.ID, "model-select")).first_selected_option.text == \
            "uploaded (3dgs, 300 units)"
        set_field(browser, "cal-samples", 3)
        set_field(browser, "cal-downscale", 1)
        browser.find_element(By.ID, "calibrate").click()
        wait(browser, lambda d: "calibrated: r_drop" in text_of(d, "model-info"), what="the calibration")
        with PHDClient(server.url, api_key=KEY) as phd:
            (model,) = phd.list_models()
            assert (model.name, model.num_training_cameras) == ("uploaded", 3)
            assert (model.calibration.samples, model.calibration.num_cameras) == (3, 3)
            assert f"r_drop = {model.calibration.r_drop}" in text_of(browser, "model-info")
            browser.find_element(By.ID, "delete-model").click()
            browser.switch_to.alert.accept()
            wait(browser, lambda d: "No model yet" in text_of(d, "model-info"), what="the deletion")
            assert phd.list_models() == []
        assert _csp_violations(browser) == []
    finally:
        server.stop()


def _messages(driver) -> dict[str, str]:
    """The text of every message line and warning of the sections shown, and the model's facts line, by id."""
    return driver.execute_script(
        "return Object.fromEntries([...document.querySelectorAll('main .message, #model-info')]"
        ".filter(p => !p.hidden && p.textContent).map(p => [p.id, p.textContent]))")


def test_page_says_each_cause_once_and_forgets_it_with_the_next_upload(browser, svc_model_files, tmp_path):
    """A PLY without its sidecar: that it has no cameras and what to add is said once (the warning
    under Model), with no advice that cannot apply (press Calibrate; read from its folder), and
    Calibrate is off. The next upload, with cameras, leaves no message of the first model's."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    server = BackgroundServer(Settings(data_dir=tmp_path / "data", api_key=KEY))
    try:
        _open_empty(browser, server)
        choose_files(browser, "upload-file", svc_model_files["ply_b"])
        browser.find_element(By.ID, "upload-run").click()
        wait(browser, lambda d: "Uploaded" in text_of(d, "upload-message"), what="the bare PLY")
        said = _messages(browser)
        assert [where for where, text in said.items() if "sidecar" in text] == ["model-warning"], said
        assert "no training cameras, so it cannot be calibrated" in said["model-info"]
        assert not any(words in text for text in said.values() for words in ("press Calibrate", "folder:"))
        assert browser.find_element(By.ID, "calibrate").get_attribute("disabled") is not None
        # Model B with cameras: model A (chosen) keeps its facts, its warning is not left above B's message.
        cameras = tmp_path / "transforms_train.json"
        cameras.write_text(json.dumps({"frames": [c.to_frame() for c in svc_cameras(3)]}))
        choose_files(browser, "upload-file", svc_model_files["ply"])
        choose_files(browser, "upload-cameras", cameras)
        browser.find_element(By.ID, "upload-run").click()
        wait(browser, lambda d: "It is model B" in text_of(d, "upload-message"), what="model B")
        said = _messages(browser)
        assert set(said) == {"model-info", "upload-message"} and "sidecar" not in said["upload-message"], said
        assert "warning" not in _classes(browser, "upload-message")
        # Choosing a model says what is news about it: nothing for the one with cameras, the advice
        # (once) for the bare one chosen again, Calibrate on and off with them.
        bare, with_cameras = (o.get_attribute("value") for o in Select(
            browser.find_element(By.ID, "model-select")).options)
        Select(browser.find_element(By.ID, "model-select")).select_by_value(with_cameras)
        wait(browser, lambda d: "3 training cameras" in text_of(d, "model-info"), what="the model with cameras")
        assert "model-warning" not in _messages(browser)
        assert browser.find_element(By.ID, "calibrate").get_attribute("disabled") is None
        Select(browser.find_element(By.ID, "model-select")).select_by_value(bare)
        wait(browser, lambda d: "model-warning" in _messages(d), what="the bare model's warning")
        assert [where for where, text in _messages(browser).items() if "sidecar" in text] == ["model-warning"]
    finally:
        server.stop()


def test_page_refuses_another_captures_cameras_and_uploads_them_when_told(browser, svc_model_files, tmp_path):
    """Training cameras that see none of the model (raised 100 units: another capture's frame): the
    service's refusal in the page's words, and the box that overrides it; ticked, the same files upload."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    frames = [c.to_frame() for c in svc_cameras(3)]
    for frame in frames:
        frame["transform_matrix"][2][3] += 100.0
    cameras = tmp_path / "transforms_train.json"
    cameras.write_text(json.dumps({"frames": frames}))
    server = BackgroundServer(Settings(data_dir=tmp_path / "data", api_key=KEY))
    try:
        _open_empty(browser, server)
        assert not browser.find_element(By.ID, "upload-other-capture").is_displayed()
        browser.find_element(By.ID, "upload-file").send_keys(str(svc_model_files["ply"]))
        browser.find_element(By.ID, "upload-cameras").send_keys(str(cameras))
        browser.find_element(By.CSS_SELECTOR, "#upload-form button").click()
        wait(browser, lambda d: "do not see this model" in text_of(d, "upload-message"), what="the refusal")
        said = text_of(browser, "upload-message")
        assert "3 of the 3 training cameras see almost none of the model" in said and "tick the box" in said
        assert "error" in _classes(browser, "upload-message")
        browser.find_element(By.ID, "upload-other-capture").click()          # shown now
        browser.find_element(By.CSS_SELECTOR, "#upload-form button").click()
        wait(browser, lambda d: "Uploaded splats.ply: 3dgs, 3 training cameras" in text_of(d, "upload-message"),
             what="the upload told to go on")
        assert not browser.find_element(By.ID, "upload-other-capture").is_displayed()   # for those files only
        with PHDClient(server.url, api_key=KEY) as phd:
            assert [m.num_training_cameras for m in phd.list_models()] == [3]
        assert console_errors(browser, expected=("status of 422",)) == [] and _csp_violations(browser) == []
    finally:
        server.stop()


# ----------------------------------------------------------------------------- what `phd train` wrote

@pytest.fixture(scope="module")
def trained_server(tmp_path_factory):
    """An empty server with the key on, and a cap on dropout samples below the page's default N = 8."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    server = BackgroundServer(Settings(data_dir=tmp_path_factory.mktemp("page-trained"), api_key=KEY,
                                       max_samples=6))
    yield server
    server.stop()


def _download(driver, folder: Path, before: set[str]) -> Path:
    """The file the page's last download saved in `folder` (the browser writes a .crdownload first)."""
    def done(_):
        new = [p for p in folder.iterdir() if p.name not in before and not p.name.endswith(".crdownload")]
        return new[0] if new else False
    return wait(driver, done, what="the download")


def test_page_takes_what_phd_train_wrote_and_hands_back_the_poses(browser, trained_server, svc_trained, tmp_path):
    """A new user's path: upload the PLY and its sidecar as `phd train` wrote them, calibrate,
    rank, download the poses (the service's answer, written as `phd rank --export` writes it),
    then select against a second model uploaded without cameras."""
    server = trained_server
    sidecar = svc_trained.with_name("model.json")
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    browser.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
    browser.execute_script("localStorage.clear()")
    browser.get(server.url + "/ui/")
    # The server needs a key (its /health says so): the page asks for it before calling anything else.
    wait(browser, lambda d: "asks for an API key" in text_of(d, "message"), what="the request for a key")
    set_field(browser, "api-key", KEY)
    browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(browser, lambda d: "No model yet" in text_of(d, "model-info"), what="the empty model list")
    assert browser.find_element(By.ID, "upload-details").get_attribute("open") is not None   # opened for a newcomer

    choose_files(browser, "upload-file", svc_trained, sidecar)          # picked together, as trained
    assert text_of(browser, "upload-picked").startswith("Uploads 2 files: ")
    browser.find_element(By.ID, "upload-run").click()
    run = f"{svc_trained.parent.name}/model"                           # named by its sidecar, not "model.ply"
    wait(browser, lambda d: f"Uploaded {run}: 3dgs, 4 training cameras (blender)" in text_of(d, "upload-message"),
         what="the uploaded model")
    assert "4 training cameras (blender)" in text_of(browser, "model-info")
    # The 3D view (view3d.js) is mounted on the uploaded model by the page: its splats and 4 cameras.
    wait(browser, lambda d: d.execute_script("return state.viewReady"), what="the 3D view")
    drawn = browser.execute_script("return phdView3d.debug()")
    assert drawn["training"] == 4 and drawn["total"] == json.loads(sidecar.read_text())["num_splats"]
    # The model's images are 25 px (lego_200 at downscale 8): the page starts at downscale 1, the largest
    # render up to 100 px (for 200 px images it would be 2).
    assert [browser.find_element(By.ID, f).get_attribute("value") for f in ("cal-downscale", "rank-downscale")] == \
        ["1", "1"]
    with PHDClient(server.url, api_key=KEY) as phd:
        (model_a,) = phd.list_models()
        assert phd.training_cameras(model_a.id) == json.loads(sidecar.read_text())["training_cameras"]
        assert model_a.details["background"] == json.loads(sidecar.read_text())["background"]
    # The same two files again: the model stored already, said so; no second entry.
    choose_files(browser, "upload-file", svc_trained, sidecar)
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "no new entry" in text_of(d, "upload-message"), what="the repeat's note")
    assert text_of(browser, "upload-message").startswith(f"{run}: the same file")
    assert [m.id for m in PHDClient(server.url, api_key=KEY).list_models()] == [model_a.id]

    # The bare PLY: said at once that it has no cameras and what to add; model A stays chosen.
    choose_files(browser, "upload-file", svc_trained)
    set_field(browser, "upload-name", "no cameras")
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "no training cameras" in text_of(d, "upload-message"), what="the no-cameras warning")
    assert "warning" in _classes(browser, "upload-message") and "sidecar" in text_of(browser, "upload-message")
    assert Select(browser.find_element(By.ID, "model-select")).first_selected_option.get_attribute("value") == \
        model_a.id
    model_b = next(m for m in PHDClient(server.url, api_key=KEY).list_models() if m.name == "no cameras")
    assert Select(browser.find_element(By.ID, "model-b-select")).first_selected_option.get_attribute("value") == \
        model_b.id

    # The PLY and a sidecar with 3 of its 4 cameras (another model) as a zip (what a user mails around),
    # dropped: read by the same rules, with cameras.
    zipped = tmp_path / "run.zip"
    fewer = json.loads(sidecar.read_text())
    fewer["training_cameras"] = fewer["training_cameras"][:3]
    with zipfile.ZipFile(zipped, "w") as archive:
        archive.write(svc_trained, "run/model.ply")
        archive.writestr("run/model.json", json.dumps(fewer))
    choose_files(browser, "upload-file", zipped)       # then dropped on the box instead (the drop's path)
    browser.execute_script(
        "const input = document.getElementById('upload-file'), dt = new DataTransfer(); "
        "for (const f of input.files) dt.items.add(f); input.value = ''; "
        "document.getElementById('drop-zone').dispatchEvent(new DragEvent('drop', {dataTransfer: dt, bubbles: true, "
        "cancelable: true}))")
    wait(browser, lambda d: text_of(d, "upload-picked") == "Uploads 1 file: run.zip", what="the dropped zip")
    set_field(browser, "upload-name", "from the zip")
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "Uploaded from the zip: 3dgs, 3 training cameras (blender). It is model B"
         in text_of(d, "upload-message"), what="the zip's model")
    with PHDClient(server.url, api_key=KEY) as phd:
        model_c = next(m for m in phd.list_models() if m.name == "from the zip")
        assert model_c.sha256 == model_a.sha256
        phd.calibrate(model_c.id, samples=2, downscale=2)

    set_field(browser, "cal-samples", 2)
    set_field(browser, "cal-downscale", 2)
    browser.find_element(By.ID, "calibrate").click()
    wait(browser, lambda d: "calibrated: r_drop" in text_of(d, "model-info"), timeout=120, what="the calibration")

    # Rank with the page's default N = 8: this server caps samples at 6, said beside Rank in words.
    browser.find_element(By.ID, "rank-run").click()
    wait(browser, lambda d: "error" in _classes(d, "rank-message"), what="the cap's error")
    said = text_of(browser, "rank-message")
    assert said == "Samples: 8 samples exceed the cap of 6" and _in_view(browser, "rank-message")
    assert browser.find_element(By.ID, "rank-progress").get_attribute("hidden") is not None   # the bar ended

    run_on_candidates(browser, 5, "rank", {"rank-samples": 3, "rank-downscale": 2, "rank-seed": 1})
    spec = browser.execute_script("return state.spec")
    with PHDClient(server.url, api_key=KEY) as phd:
        expected = phd.rank(model_a.id, candidates=spec, samples=3, seed=1, downscale=2)
    cards = browser.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")
    assert [c.find_element(By.CSS_SELECTOR, ".title").text for c in cards] == \
        [f"candidate {v.index} · rank #{v.rank}" for v in expected.views]
    # The ranking reached the 3D view: one frustum per returned pose, with its rank; a rank card's
    # click selects its frustum, and a frustum's pick marks its card.
    frusta = browser.execute_script("return phdView3d.debug().frusta")
    assert sorted((f["index"], f["rank"]) for f in frusta) == sorted((v.index, v.rank) for v in expected.views)
    cards[1].click()
    assert browser.execute_script("return phdView3d.debug().selected") == expected.views[1].index

    # Download poses: the model's own convention (its capture was a Blender scene), the first 3.
    assert Select(browser.find_element(By.ID, "poses-format")).first_selected_option.get_attribute("value") == \
        "blender"
    set_field(browser, "poses-topk", 3)
    first = [v for v in expected.views[:3]]
    for convention, name in (("blender", "transforms_train.json"), ("colmap", "colmap.zip")):
        Select(browser.find_element(By.ID, "poses-format")).select_by_value(convention)
        before = {p.name for p in downloads.iterdir()}
        browser.find_element(By.ID, "poses-download").click()
        saved = _download(browser, downloads, before)
        assert saved.name == name and f"Saved the first 3 poses as {name}" in text_of(browser, "rank-message")
        # What `phd rank --export` writes for the REST answer's poses, with the same image names.
        written = tmp_path / convention / ("transforms_train.json" if convention == "blender" else "colmap")
        export_cameras(written, [camera_from_frame(v.camera) for v in first],
                       [candidate_name(v.rank, v.index) for v in first], convention)
        if convention == "blender":
            assert saved.read_bytes() == written.read_bytes()
            assert [f["transform_matrix"] for f in json.loads(saved.read_text())["frames"]] == \
                [v.camera["transform_matrix"] for v in first]
        else:
            files = zipfile.ZipFile(saved)
            assert {n: files.read(n) for n in files.namelist()} == {
                f"colmap/{p.name}": p.read_bytes() for p in written.iterdir()}

    # Selection against the model without cameras (so never calibrated): said beside Select, in words
    # that fit (it cannot be calibrated: no "press Calibrate", no Calibrate model B button).
    Select(browser.find_element(By.ID, "model-b-select")).select_by_value(model_b.id)
    browser.find_element(By.ID, "select-run").click()
    wait(browser, lambda d: "error" in _classes(d, "select-message"), what="the calibration's error")
    said = text_of(browser, "select-message")
    assert said.startswith("Model B has no training cameras, so it cannot be calibrated")
    assert not browser.find_element(By.ID, "calibrate-b").is_displayed()
    assert _in_view(browser, "select-message")
    assert not any(word in said for word in ("/v1", "409", "field", "ratio_b", model_b.id))
    assert browser.find_element(By.ID, "select-progress").get_attribute("hidden") is not None
    Select(browser.find_element(By.ID, "model-b-select")).select_by_value(model_c.id)
    browser.find_element(By.ID, "select-run").click()
    wait(browser, grid_loaded("select", 5), what="the select grid")
    _assert_select_labels_match_rank_labels(browser)
    browser.save_screenshot(str(tmp_path / "page_trained.png"))
    # No console errors but the two refusals the test asked for.
    assert console_errors(browser, expected=("status of 422", "status of 409")) == []


def test_page_checks_a_candidates_file_and_asks_for_its_image_size(browser, trained_server, svc_trained, tmp_path):
    server = trained_server
    with PHDClient(server.url, api_key=KEY) as phd:
        model = phd.upload_model(svc_trained)       # the model stored already, when an earlier test uploaded it
    browser.get(server.url + "/ui/")
    set_field(browser, "api-key", KEY)
    browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(browser, lambda d: d.execute_script("return state.training.length") == 4, what="the model's cameras")
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model.id)
    wait(browser, lambda d: d.execute_script("return state.modelId") == model.id, what="model A")
    browser.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=file]").click()
    broken = tmp_path / "broken.json"
    broken.write_text('{"frames": [{transform_matrix: 1}]}')
    typo = tmp_path / "typo.json"
    typo.write_text(json.dumps({"camera_angle_x": 0.7, "frame": [{"transform_matrix": np.eye(4).tolist()}]}))
    for path, words in ((broken, "broken.json is not valid JSON"), (typo, 'typo.json has no "frames" list '
                                                                           '(its keys: "camera_angle_x", "frame")')):
        choose_files(browser, "cand-file", path)
        wait(browser, lambda d: words in text_of(d, "cand-message"), what=f"the error of {path.name}")
        assert "error" in _classes(browser, "cand-message") and _in_view(browser, "cand-message")
        assert "poses" not in text_of(browser, "cand-info")          # not "0 poses"
        assert browser.execute_script("return state.candidates.length") == 0
    # The README's candidates: Blender's transforms_val.json, without an image size: width and
    # height fields appear, filled with the model's training images' size.
    choose_files(browser, "cand-file", LEGO / "transforms_val.json")
    wait(browser, lambda d: "100 poses from transforms_val.json" in text_of(d, "cand-info"), what="the val poses")
    assert text_of(browser, "cand-message") == ""
    assert browser.find_element(By.ID, "cand-size").is_displayed()
    sizes = [browser.find_element(By.ID, f).get_attribute("value") for f in ("cand-width", "cand-height")]
    training = PHDClient(server.url, api_key=KEY).training_cameras(model.id)
    assert sizes == [str(training[0]["w"]), str(training[0]["h"])] == ["25", "25"]
    sent = browser.execute_script("return candidateBody().cameras")
    assert len(sent) == 100 and all((f["w"], f["h"]) == (25, 25) for f in sent)
    set_field(browser, "cand-width", "")
    browser.find_element(By.ID, "rank-run").click()
    wait(browser, lambda d: "fill in width and height" in text_of(d, "rank-message"), what="the missing size")
    assert console_errors(browser) == []


def test_api_docs_render_offline(browser, trained_server):
    """/docs and /redoc load Swagger UI and ReDoc from the service itself, and nothing from another
    host: ReDoc's bundle, which asks a CDN for its footer logo, is served with an empty image there."""
    server = trained_server
    for path, ready in (("/docs", "document.querySelectorAll('.swagger-ui .opblock').length"),
                        ("/redoc", "document.querySelectorAll('.api-content h2').length")):
        browser.get(server.url + path)
        wait(browser, lambda d: d.execute_script("return " + ready) > 5, what=f"{path} to render")
        loaded = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
        scripts = browser.execute_script("return [...document.scripts].map(s => s.src).filter(s => s)")
        assert scripts and all(url.startswith(server.url + "/docs-assets/") for url in scripts), scripts
        assert all(url.startswith(server.url) for url in loaded), loaded
        assert console_errors(browser) == []
    browser.get(server.url + "/docs")
    wait(browser, lambda d: "POST/v1/models/{model_id}/poses" in d.find_element(By.CSS_SELECTOR, ".swagger-ui")
         .text.replace("\n", "").replace(" ", ""), what="the poses route in Swagger UI")
    icon = httpx.get(server.url + "/favicon.ico")
    assert icon.status_code == 200 and icon.headers["content-type"] == "image/svg+xml"


def test_page_uploads_a_trainer_output_folder_picked_as_a_folder(browser, trained_server, tmp_path, capsys):
    """A reference-trainer output folder picked whole (the folder input): its files go up by their
    paths, its images and phd's cached results stay behind (the line says which and why), and the
    service reads it as the client does. The calibration `phd calibrate` stored in its .phd-cache/
    for this model and these cameras is used, not run again; one made on other cameras is not."""
    from phd_cli import main
    from support.captures import write_output_folder

    server = trained_server
    folder = write_output_folder(tmp_path / "lego_out", svc_random_gaussians(200), svc_cameras(3))
    (folder / "input.png").write_bytes(b"\x89PNG not needed")
    calibrate = ["calibrate", "--model", str(folder), "--epsilon", "0.05", "--step", "0.2", "--samples", "3",
                 "--quiet", "--out"]
    assert main([*calibrate, str(tmp_path / "calibration.json")]) == 0
    r_drop = json.loads((tmp_path / "calibration.json").read_text())["r_drop"]
    cached = sorted(p.name for p in (folder / ".phd-cache").iterdir())
    assert len(cached) == 2 and cached[0].startswith("calibration-")      # the entry, and the digest memo
    browser.get(server.url + "/ui/")
    set_field(browser, "api-key", KEY)
    browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(browser, lambda d: text_of(d, "message") == "key saved in this browser", what="the key")
    browser.execute_script("document.getElementById('upload-details').open = true")
    browser.find_element(By.ID, "upload-folder").send_keys(str(folder))
    wait(browser, lambda d: "Leaves out" in text_of(d, "upload-picked"), what="the picked folder")
    picked = text_of(browser, "upload-picked")
    assert picked.startswith("Uploads 5 files: ") and picked.endswith(
        "Leaves out 1 image (the model needs no photos) and 1 other .phd-cache file (results the service "
        "works out itself)."), picked
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "3dgs, 3 training cameras (3dgs-output)" in text_of(d, "upload-message"),
         what="the folder's model")
    assert f"calibrated: r_drop = {r_drop} (the calibration phd stored" in text_of(browser, "upload-message")
    with PHDClient(server.url, api_key=KEY) as phd:
        # The same run through the client: the page's model (the same bytes, cameras and background), named alike.
        expected = phd.upload_model(folder)
        assert "no new entry" in (expected.note or "")
        assert text_of(browser, "upload-message").startswith(f"Uploaded {expected.name}: ")
        assert [m.id for m in phd.list_models() if m.name == expected.name] == [expected.id]
        assert expected.calibration is not None and expected.calibration.r_drop == r_drop
        assert any("not run again" in note for note in expected.details["notes"])
        phd.delete_model(expected.id)

    # Calibrated on other cameras (at half their size) only: that calibration is not this model's.
    for entry in (folder / ".phd-cache").glob("calibration-*.json"):
        entry.unlink()
    assert main([*calibrate, str(tmp_path / "half.json"), "--downscale", "2"]) == 0
    capsys.readouterr()
    browser.execute_script("document.getElementById('upload-folder').value = ''")    # the folder as it is now
    browser.find_element(By.ID, "upload-folder").send_keys(str(folder))
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: text_of(d, "upload-message").startswith(f"Uploaded {expected.name}: 3dgs, 3 training "
                                                                   "cameras (3dgs-output). It is"),
         what="the second folder upload, not calibrated")
    with PHDClient(server.url, api_key=KEY) as phd:
        again = next(m for m in phd.list_models() if m.name == expected.name and m.id != expected.id)
        assert again.calibration is None
        assert any("made on other training cameras" in note for note in again.details["notes"])
        phd.delete_model(again.id)
    # A PLY picked with a transforms file that is not its sidecar: the file goes up as its cameras,
    # and as its frames say no image size, the page asks for it beside the upload.
    cameras = tmp_path / "transforms_train.json"
    cameras.write_text(json.dumps({"camera_angle_x": 0.7, "frames": [
        {"transform_matrix": c.c2w.tolist()} for c in svc_cameras(3)]}))
    browser.execute_script("document.getElementById('upload-folder').value = ''")
    choose_files(browser, "upload-file", folder / "point_cloud" / "iteration_30000" / "point_cloud.ply", cameras)
    set_field(browser, "upload-name", "with its transforms")
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "fill in width and height" in text_of(d, "upload-message"), what="the missing size")
    assert browser.find_element(By.ID, "upload-size").is_displayed() and _in_view(browser, "upload-message")
    set_field(browser, "upload-width", 24)
    set_field(browser, "upload-height", 24)
    browser.find_element(By.ID, "upload-run").click()
    wait(browser, lambda d: "Uploaded with its transforms: 3dgs, 3 training cameras" in text_of(d, "upload-message"),
         what="the model with its transforms")
    with PHDClient(server.url, api_key=KEY) as phd:
        stored = next(m for m in phd.list_models() if m.name == "with its transforms")
        assert [(f["w"], f["h"]) for f in phd.training_cameras(stored.id)] == [(24, 24)] * 3
        assert stored.camera_format == "nerfstudio"
    assert console_errors(browser) == []


def test_without_webgl_the_view_says_why_and_the_rest_of_the_page_works(models, tmp_path):
    """A browser without WebGL (remote desktops, locked-down machines): the 3D view says in its
    own status line that it needs WebGL, the page's message line stays free of errors, the
    model's facts are shown, and a rank from the page shows its cards (the view's calls do nothing)."""
    server, model_a, _ = models
    driver = chromium(tmp_path / "profile", flags=("--disable-webgl", "--disable-3d-apis"))
    try:
        _open(driver, server)
        Select(driver.find_element(By.ID, "model-select")).select_by_value(model_a.id)
        status = lambda d: d.find_element(By.CSS_SELECTOR, "#view3d .v3d-status").text   # noqa: E731
        wait(driver, lambda d: "WebGL" in status(d), what="the view's word on WebGL")
        assert "cannot draw the 3D view" in status(driver)
        assert not driver.find_elements(By.CSS_SELECTOR, "#view3d .v3d-stage, #view3d .v3d-modes")   # only the why
        wait(driver, lambda d: "r_drop" in text_of(d, "model-info"), what="the model's facts")
        assert "error" not in _classes(driver, "message") and "WebGL" not in text_of(driver, "message")
        run_on_candidates(driver, 3, "rank", {"rank-samples": 3, "rank-downscale": 1, "rank-seed": 0})
        driver.find_elements(By.CSS_SELECTOR, "#rank-grid li.card")[1].click()      # picks it: the view ignores it
        assert _classes(driver, "rank-message") == ["message"] and "error" not in _classes(driver, "message")
        driver.save_screenshot(str(tmp_path / "page_no_webgl.png"))
        assert console_errors(driver, expected=("WebGL",)) == []
    finally:
        driver.quit()
