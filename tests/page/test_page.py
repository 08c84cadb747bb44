"""The web page in a real browser: headless Chromium from the distribution's packages, driven
by selenium through the distribution's chromedriver, against a real uvicorn server on
127.0.0.1 that requires an API key. The server sends its Content-Security-Policy (no inline
scripts or styles; images from blob: URLs): any violation fails a test."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import httpx
import imageio.v3 as iio
import numpy as np
import pytest

from client import PHDClient
from phd_core import uq
from phd_core.uq.candidates import candidate_cameras
from support.fixtures import svc_cameras

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
    pytest.skip("no browser: install Debian's chromium and chromium-driver (scripts/test.sh does, as root)",
                allow_module_level=True)
from selenium.common.exceptions import TimeoutException  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

KEY = "page-test-key"
@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1280,1600",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # An explicit driver path: Selenium Manager then downloads nothing.
    driver = webdriver.Chrome(service=webdriver.ChromeService(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
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


def _wait(driver, condition, timeout: float = 40.0, what: str = "the page"):
    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.1).until(condition)
    except TimeoutException:
        pytest.fail(f"timed out waiting for {what}; the page says: {d_text(driver, 'message')!r}")


def d_text(driver, element_id: str) -> str:
    return driver.find_element(By.ID, element_id).text


def _set(driver, element_id: str, value) -> None:
    field = driver.find_element(By.ID, element_id)
    field.clear()
    field.send_keys(str(value))


def _open(driver, server) -> None:
    driver.get(server.url + "/")   # redirects to /ui/
    assert driver.current_url.endswith("/ui/")
    policy = httpx.get(server.url + "/ui/").headers["content-security-policy"]
    assert "script-src 'self';" in policy and "style-src 'self';" in policy and "unsafe-inline" not in policy
    _set(driver, "api-key", KEY)
    driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
    _wait(driver, lambda d: len(Select(d.find_element(By.ID, "model-select")).options) == 2
          and d_text(d, "message") == "key saved in this browser", what="the model list")


def _csp_violations(driver) -> list[str]:
    return [entry["message"] for entry in driver.get_log("browser")
            if "Content Security Policy" in entry["message"] or "Refused to" in entry["message"]]


def _run_on_candidates(browser, count: int, job: str, fields: dict[str, int]) -> None:
    """Ask for `count` generated candidates, fill `fields`, press the job's button ("rank" or
    "select") and wait until its grid shows `count` cards with every image loaded."""
    _set(browser, "gen-count", count)
    browser.find_element(By.ID, "gen-elevation").click()          # the change event takes the new count
    for field, value in fields.items():
        _set(browser, field, value)
    _wait(browser, lambda d: (d.execute_script("return state.spec") or {}).get("count") == count,
          what=f"a spec of {count} candidates")
    browser.find_element(By.ID, f"{job}-run").click()
    _wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, f"#{job}-grid li.card")) == count
          and d.execute_script(f"return [...document.querySelectorAll('#{job}-grid img')].every(i => i.complete "
                               "&& i.naturalWidth > 0)"), what=f"the {job} grid and its images")

def test_page_ranks_a_model_and_shows_the_services_order(browser, models, tmp_path):
    server, model_a, _ = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    _wait(browser, lambda d: "r_drop" in d.find_element(By.ID, "model-info").text, what="the model's facts")
    # The strategy field starts at the service's default and offers the registry's names.
    assert browser.find_element(By.ID, "rank-strategy").get_attribute("value") == uq.DEFAULT_STRATEGY
    offered = browser.execute_script("return [...document.querySelectorAll('#strategies option')].map(o => o.value)")
    assert offered == list(uq.STRATEGIES)
    # The page makes no poses itself: it asks the service's generator and draws what comes back.
    assert browser.execute_script("return typeof generateCandidates") == "undefined"
    _run_on_candidates(browser, 7, "rank", {"rank-samples": 4, "rank-downscale": 1, "rank-seed": 3})

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
        assert [int(c.get_attribute("data-rank")) for c in cards] == list(range(7))
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


def test_page_selection_shows_both_renders_and_the_choice(browser, models, tmp_path):
    server, model_a, model_b = models
    _open(browser, server)
    Select(browser.find_element(By.ID, "model-select")).select_by_value(model_a.id)
    Select(browser.find_element(By.ID, "model-b-select")).select_by_value(model_b.id)
    rules = Select(browser.find_element(By.ID, "select-rule"))          # the service's rules, its default chosen
    assert [o.get_attribute("value") for o in rules.options] == list(uq.SELECTION_RULES)
    assert rules.first_selected_option.get_attribute("value") == uq.DEFAULT_SELECTION_RULE
    # Generated poses exist once the service made them: selecting before a ranking says so.
    _set(browser, "gen-count", 4)
    browser.find_element(By.ID, "gen-elevation").click()
    browser.find_element(By.ID, "select-run").click()
    _wait(browser, lambda d: "rank first" in d_text(d, "message"), what="the rank-first message")
    _run_on_candidates(browser, 4, "rank", {"rank-samples": 3, "rank-downscale": 2})
    browser.find_element(By.ID, "select-run").click()             # over the 4 poses the ranking returned
    _wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#select-grid li.card")) == 4
          and d.execute_script("return [...document.querySelectorAll('#select-grid img')].every(i => i.complete "
                               "&& i.naturalWidth > 0)"), what="the select grid and its images")
    candidates = [v["camera"] for v in browser.execute_script("return state.ranking.views")]
    assert len(candidates) == 4
    with PHDClient(server.url, api_key=KEY) as phd:
        expected = phd.select(model_a.id, model_b.id, candidates, samples=3, seed=0, downscale=2)
    cards = browser.find_elements(By.CSS_SELECTOR, "#select-grid li.card")
    assert [c.get_attribute("data-choice") for c in cards] == [v.choice for v in expected.views]
    for card, view in zip(cards, expected.views):
        chosen = card.find_elements(By.CSS_SELECTOR, "figure.chosen img")
        assert len(card.find_elements(By.TAG_NAME, "img")) == 2 and len(chosen) == 1
        assert chosen[0].get_attribute("alt").startswith(f"model {view.choice.upper()} ")
    assert f"for {expected.counts['a']} views" in browser.find_element(By.ID, "select-summary").text
    browser.save_screenshot(str(tmp_path / "page_select.png"))
    assert _csp_violations(browser) == []


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
    _wait(browser, lambda d: d.execute_script("return state.candidates.length") == 5, what="the file's 5 poses")
    sent = browser.execute_script("return state.candidates")
    assert [f["transform_matrix"] for f in sent] == [f["transform_matrix"] for f in frames]
    assert all((f["w"], f["h"]) == (24, 24) for f in sent)       # the defaults reached every frame
    assert "5 poses from candidates.json" in d_text(browser, "cand-info")
    assert len(browser.find_elements(By.CSS_SELECTOR, "#plot-top circle.cand.none")) == 5   # not ranked yet


def test_page_fits_a_phone_and_names_a_wrong_key(browser, models, tmp_path):
    server, _, _ = models
    browser.set_window_size(390, 844)
    try:
        browser.get(server.url + "/ui/")
        _set(browser, "api-key", "wrong")
        browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
        _wait(browser, lambda d: "unauthorized" in d_text(d, "message"), what="the 401 message")
        assert "Authorization" in d_text(browser, "message")          # the field the server named
        _open(browser, server)
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
        browser.get(server.url + "/ui/")
        _set(browser, "api-key", KEY)
        browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
        _wait(browser, lambda d: "No model yet" in d_text(d, "model-info"), what="the empty model list")
        browser.find_element(By.CSS_SELECTOR, "#model-section summary").click()
        browser.find_element(By.ID, "upload-file").send_keys(str(svc_model_files["ply"]))
        browser.find_element(By.ID, "upload-cameras").send_keys(str(cameras))
        _set(browser, "upload-name", "uploaded")
        browser.find_element(By.CSS_SELECTOR, "#upload-form button").click()
        _wait(browser, lambda d: "not calibrated" in d_text(d, "model-info"), what="the uploaded model")
        assert "3 training cameras" in d_text(browser, "model-info")
        assert Select(browser.find_element(By.ID, "model-select")).first_selected_option.text == \
            "uploaded (3dgs, 300 units)"
        _set(browser, "cal-samples", 3)
        _set(browser, "cal-downscale", 1)
        browser.find_element(By.ID, "calibrate").click()
        _wait(browser, lambda d: "calibrated: r_drop" in d_text(d, "model-info"), what="the calibration")
        with PHDClient(server.url, api_key=KEY) as phd:
            (model,) = phd.list_models()
            assert (model.name, model.num_training_cameras) == ("uploaded", 3)
            assert (model.calibration.samples, model.calibration.num_cameras) == (3, 3)
            assert f"r_drop = {model.calibration.r_drop}" in d_text(browser, "model-info")
            browser.find_element(By.ID, "delete-model").click()
            browser.switch_to.alert.accept()
            _wait(browser, lambda d: "No model yet" in d_text(d, "model-info"), what="the deletion")
            assert phd.list_models() == []
        assert _csp_violations(browser) == []
    finally:
        server.stop()
