"""The page's 3D view (service/page/view3d.js) in a real browser: headless Chromium (WebGL on
SwiftShader) against a real uvicorn server with an API key and its CSP. The view is driven
through its own API (`window.phdView3d`) on the real page, with a rank result the REST API
returned; its pixels are read back from the canvas (preserveDrawingBuffer) and compared with
where the returned poses project through the view's camera, computed here."""

from __future__ import annotations

import base64
import json
import re

import httpx
import numpy as np
import pytest
import torch

from client import PHDClient
from support.browser import chromium, have_browser, hold_worker
from support.fixtures import svc_cameras

pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
if not have_browser():
    pytest.skip("no browser: install Debian's chromium and chromium-driver (scripts/test.sh does, as root)",
                allow_module_level=True)
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

KEY = "view3d-key"
AUTH = {"Authorization": f"Bearer {KEY}"}
BACKGROUND = (0x15, 0x18, 0x1D)
CANDIDATES, TOP_K = 6, 4


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    driver = chromium(tmp_path_factory.mktemp("chromium-profile"))
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def ranked(tmp_path_factory, svc_model_files):
    """A server with a calibrated 3DGS model (3 training cameras) and a ranking of 6 candidate
    poses, the first 4 returned with heat maps and renders as files (the REST answer)."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    server = BackgroundServer(Settings(data_dir=tmp_path_factory.mktemp("view3d-data"), api_key=KEY))
    try:
        with PHDClient(server.url, api_key=KEY) as phd:
            model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3), name="splats")
            phd.calibrate(model.id, epsilon=0.05, step=0.2, samples=3, seed=1)
        candidates = [c.to_frame() for c in svc_cameras(CANDIDATES, phase=0.25, radius=3.2)]
        answer = httpx.post(f"{server.url}/v1/models/{model.id}/rank", headers=AUTH, timeout=120, json={
            "cameras": candidates, "samples": 4, "seed": 0, "top_k": TOP_K, "heatmaps": "files"})
        assert answer.status_code == 200, answer.text
        yield server, model, answer.json(), candidates
    finally:
        server.stop()


def _call(driver, script: str, *args):
    """Run `script` (a promise expression over arguments[0..]) and return its value, or fail with its error."""
    done = driver.execute_async_script(
        f"const done = arguments[arguments.length - 1]; Promise.resolve().then(() => {script})"
        ".then(v => done({ok: v === undefined ? null : v}), e => done({error: String(e && e.stack || e)}));", *args)
    assert "error" not in done, done["error"]
    return done["ok"]


def _pixels(driver) -> np.ndarray:
    """The canvas as [H, W, 3] uint8 (CSS pixels: the view draws at device pixel ratio 1 here)."""
    data = driver.execute_script(
        "phdView3d.drawNow(); const c = document.querySelector('#view3d canvas');"
        "return [c.width, c.height, c.toDataURL('image/png')];")
    import imageio.v3 as iio
    image = iio.imread(base64.b64decode(data[2].split(",", 1)[1]))[..., :3]
    assert image.shape[:2] == (data[1], data[0])
    return image


def _project(debug: dict, point) -> tuple[float, float, float]:
    """A world point through the view's camera (three.js column-major matrices) to canvas pixels and NDC depth."""
    projection = np.array(debug["projection"]).reshape(4, 4).T
    world_to_view = np.array(debug["view"]).reshape(4, 4).T
    clip = projection @ world_to_view @ np.append(np.asarray(point, float), 1.0)
    ndc = clip[:3] / clip[3]
    return (ndc[0] + 1) / 2 * debug["width"], (1 - ndc[1]) / 2 * debug["height"], ndc[2]


def _image_centre(frame: dict, depth: float) -> np.ndarray:
    """The centre of a camera's image rectangle at `depth` in front of it, in world coordinates."""
    c2w = np.array(frame["transform_matrix"], float)
    x = (frame["w"] / 2 - frame["cx"]) / frame["fl_x"] * depth
    y = -(frame["h"] / 2 - frame["cy"]) / frame["fl_y"] * depth
    return (c2w @ np.array([x, y, -depth, 1.0]))[:3]


def _open(driver, server, model) -> dict:
    """The real page with the key saved (as its key form does), the view mounted on the model."""
    driver.get(server.url + "/health")          # the same origin, without the page's own calls
    driver.execute_script("localStorage.setItem('phd-api-key', arguments[0])", KEY)
    driver.get(server.url + "/ui/")
    WebDriverWait(driver, 20).until(lambda d: d.execute_script("return !!window.phdView3d && state.models.length"))
    Select(driver.find_element(By.ID, "model-select")).select_by_value(model.id)   # app.js mounts the view on it
    WebDriverWait(driver, 30).until(lambda d: d.execute_script("return state.modelId === arguments[0] && "
                                                               "state.viewReady", model.id))
    return driver.execute_script("return phdView3d.debug()")


def _console_errors(driver) -> list[str]:
    """Errors in the browser's console; the favicon the browser asks for by itself is the page's
    own item (issue 33), not the view's."""
    return [e["message"] for e in driver.get_log("browser")
            if e["level"] == "SEVERE" and "/favicon.ico" not in e["message"]]


def test_the_view_draws_the_splats_and_the_returned_poses_where_they_project(browser, ranked, tmp_path):
    server, model, ranking, candidates = ranked
    state = _open(browser, server, model)
    assert (state["points"], state["total"], state["training"]) == (300, 300, 3)
    empty = _pixels(browser)
    # Splats drawn: around the model's projected centre most pixels are not the background.
    x, y, _ = _project(state, state["centre"])
    patch = empty[int(y) - 6:int(y) + 7, int(x) - 6:int(x) + 7].astype(int)
    assert (np.abs(patch - BACKGROUND).sum(-1) > 30).mean() > 0.8
    assert len(np.unique(empty.reshape(-1, 3), axis=0)) > 200          # colours, not a flat fill

    _call(browser, "phdView3d.showRanking(arguments[0], {candidates: arguments[1]})", ranking, candidates)
    state = browser.execute_script("return phdView3d.debug()")
    image = _pixels(browser)
    drawn = {f["index"]: f for f in state["frusta"]}
    assert sorted(drawn) == sorted(v["index"] for v in ranking["views"])
    scores = [v["score"] for v in ranking["views"]]
    for v in ranking["views"]:
        # Where the REST answer's pose puts its image rectangle, through the view's camera: the
        # frustum's fill, in the colour of its score on the ramp (the highest: the ramp's top).
        centre = _image_centre(v["camera"], state["frustumDepth"])
        assert np.allclose(centre, drawn[v["index"]]["centre"], atol=1e-4)
        px, py, depth = _project(state, centre)
        assert 0 < px < state["width"] and 0 < py < state["height"] and -1 < depth < 1
        colour = image[int(py), int(px)].astype(int)
        assert np.abs(colour - drawn[v["index"]]["rgb"]).max() <= 40, (v["index"], colour, drawn[v["index"]]["rgb"])
        label = browser.find_element(By.CSS_SELECTOR, f".v3d-label[data-index='{v['index']}']")
        assert label.text == f"#{v['rank']}"                               # ranks count from 1
    top = max(ranking["views"], key=lambda v: v["score"])
    assert drawn[top["index"]]["rgb"] == [253, 231, 37] and max(scores) == top["score"]
    legend = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert "candidate score" in legend and "training camera" in legend and "not returned" in legend
    browser.save_screenshot(str(tmp_path / "view3d.png"))
    assert _console_errors(browser) == []


def test_clicking_a_frustum_picks_it_and_shows_its_render_and_heat_map(browser, ranked):
    server, model, ranking, candidates = ranked
    _open(browser, server, model)
    _call(browser, "phdView3d.showRanking(arguments[0], {candidates: arguments[1]})", ranking, candidates)
    browser.execute_script("window.picked = []; phdView3d.onPick(i => window.picked.push(i));")
    state = browser.execute_script("return phdView3d.debug()")
    first = next(v for v in ranking["views"] if v["rank"] == 1)
    px, py, _ = _project(state, _image_centre(first["camera"], state["frustumDepth"]))
    canvas = browser.find_element(By.CSS_SELECTOR, "#view3d canvas")
    size = canvas.size
    ActionChains(browser).move_to_element_with_offset(canvas, px - size["width"] / 2, py - size["height"] / 2) \
        .click().perform()
    WebDriverWait(browser, 20).until(lambda d: d.execute_script(
        "return [...document.querySelectorAll('#view3d .v3d-detail img')].length === 2 && "
        "[...document.querySelectorAll('#view3d .v3d-detail img')].every(i => i.complete && i.naturalWidth > 0)"))
    assert browser.execute_script("return window.picked") == [first["index"]]
    assert browser.execute_script("return phdView3d.debug().selected") == first["index"]
    title = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-title").text
    assert title.startswith(f"#1: candidate {first['index']}")
    # The heat map shown is the ranking's own artefact, pixel for pixel.
    shown = browser.execute_script(
        "const i = document.querySelector('#view3d .v3d-detail img.heatmap'), c = document.createElement('canvas');"
        "c.width = i.naturalWidth; c.height = i.naturalHeight; const g = c.getContext('2d'); g.drawImage(i, 0, 0);"
        "return [c.width, c.height, Array.from(g.getImageData(0, 0, c.width, c.height).data)]")
    import imageio.v3 as iio
    truth = iio.imread(httpx.get(server.url + first["heatmap_url"], headers=AUTH).content)
    assert shown[:2] == [truth.shape[1], truth.shape[0]]
    assert np.array_equal(np.array(shown[2], np.uint8).reshape(shown[1], shown[0], 4)[..., :3], truth)
    # select() from the page (a rank card clicked) highlights another candidate without a pick event.
    second = next(v for v in ranking["views"] if v["rank"] == 2)
    _call(browser, "phdView3d.select(arguments[0])", second["index"])
    assert browser.execute_script("return [phdView3d.debug().selected, window.picked]") == \
        [second["index"], [first["index"]]]
    assert _console_errors(browser) == []


def test_colour_modes_show_coverage_fragility_and_what_the_first_pick_sees(browser, ranked, tmp_path):
    server, model, ranking, candidates = ranked
    state = _open(browser, server, model)
    _call(browser, "phdView3d.setMode('novelty')")          # before a ranking: said where the toggle is
    status = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-status")
    assert "rank first" in status.text and "error" in status.get_attribute("class")
    _call(browser, "phdView3d.setMode('colour')")
    _call(browser, "phdView3d.showRanking(arguments[0], {candidates: arguments[1]})", ranking, candidates)
    x, y, _ = _project(state, state["centre"])
    area = (slice(int(y) - 30, int(y) + 31), slice(int(x) - 30, int(x) + 31))
    before = _pixels(browser)[area].astype(int)
    _call(browser, "phdView3d.setMode('coverage')")
    state = browser.execute_script("return phdView3d.debug()")
    assert state["mode"] == "coverage" and set(state["explained"]) == {"coverage", "fragility", "novelty"}
    coverage = _pixels(browser)[area].astype(int)
    assert np.abs(coverage - before).sum(-1).mean() > 20                # the splats changed colour
    legend = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert "no captured view saw it" in legend
    _call(browser, "phdView3d.setMode('fragility')")
    fragility = _pixels(browser)[area].astype(int)
    assert np.abs(fragility - coverage).sum(-1).mean() > 20
    _call(browser, "phdView3d.setMode('novelty')")
    assert "newly seen by #1" in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    # What #1 adds is drawn to the share it reaches: magenta splats, not a model all grey.
    novelty = _pixels(browser)[area].astype(int)
    magenta = (novelty[..., 0] > 150) & (novelty[..., 2] > 150) & (novelty[..., 1] < 110)
    assert magenta.sum() > 20, magenta.sum()
    # One explain job served all three modes: its pick is the ranking's first pose.
    jobs = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert sum(name.endswith(f"/v1/models/{model.id}/explain") for name in jobs) == 1
    browser.save_screenshot(str(tmp_path / "view3d_coverage.png"))
    _call(browser, "phdView3d.setMode('colour')")
    assert np.abs(_pixels(browser)[area].astype(int) - before).max() <= 2
    assert all(name.startswith((server.url, "blob:", "data:")) for name in jobs)     # nothing from another host
    # A first pick that shows nothing new (here it looks away from the model): said in words, and
    # the splats keep their own colours rather than all turning grey.
    away = json.loads(json.dumps(ranking))
    matrix = np.array(away["views"][0]["camera"]["transform_matrix"])
    matrix[:3, 0] *= -1
    matrix[:3, 2] *= -1                                       # turned about its own y axis: looking outwards
    away["views"][0]["camera"]["transform_matrix"] = matrix.tolist()
    _call(browser, "phdView3d.showRanking(arguments[0], {candidates: arguments[1]})", away, candidates)
    before = _pixels(browser)[area].astype(int)              # the splats' own colours, as framed now
    _call(browser, "phdView3d.setMode('novelty')")
    status = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-status").text
    assert "#1 shows no part of a splat that the training views had not already shown" in status
    assert "newly seen by #1" not in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert np.abs(_pixels(browser)[area].astype(int) - before).max() <= 2
    _call(browser, "phdView3d.setMode('coverage')")        # another mode says what was measured again
    assert "training views, N = " in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-status").text
    _call(browser, "phdView3d.setMode('colour')")
    assert _console_errors(browser) == []


# The heat maps' ramp (viridis), which colours the candidates by score.
SCORE_RAMP = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)


def test_target_views_are_drawn_faint_in_their_own_colour_where_they_project(browser, ranked):
    """Target views given as a reference trainer's cameras.json: a frustum each where the pose
    puts its image rectangle, filled with the target colour at its faint opacity over what lies
    behind (the same picture without them, the view turned by hand so it stays put), in a colour
    off the candidates' ramp, under the candidates, with a legend entry."""
    from phd_core.data.inria import camera_entry

    server, model, ranking, candidates = ranked
    _open(browser, server, model)
    cameras = svc_cameras(3, phase=0.6, radius=2.8)
    entries = [camera_entry(c) for c in cameras]
    _call(browser, "phdView3d.showTargets(arguments[0])", entries)
    assert "target view (3)" in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    canvas = browser.find_element(By.CSS_SELECTOR, "#view3d canvas")
    ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(25, 10).release().perform()
    state = browser.execute_script("return phdView3d.debug()")
    with_targets = _pixels(browser).astype(float)
    # The legend's check box hides the target frusta and shows them again (the legend keeps the entry).
    shown = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend input.v3d-targets-shown")
    shown.click()
    assert browser.execute_script("return phdView3d.debug().targetsShown") is False
    hidden = _pixels(browser).astype(float)
    browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend input.v3d-targets-shown").click()
    assert np.abs(_pixels(browser).astype(float) - with_targets).max() <= 2
    _call(browser, "phdView3d.showTargets([])")                # the view was turned: it stays where it is
    assert browser.execute_script("return phdView3d.debug().view") == state["view"]
    without = _pixels(browser).astype(float)
    assert np.abs(hidden - without).max() <= 2
    assert len(state["targets"]) == 3
    for camera, drawn in zip(cameras, state["targets"]):
        centre = _image_centre(camera.to_frame(), state["frustumDepth"])
        assert np.allclose(centre, drawn["centre"], atol=1e-4)              # the entry's pose, OpenCV axes read
        px, py, depth = _project(state, centre)
        assert 2 < px < state["width"] - 3 and 2 < py < state["height"] - 3 and -1 < depth < 1
        area = (slice(int(py) - 2, int(py) + 3), slice(int(px) - 2, int(px) + 3))
        blend = drawn["fill"] * np.array(drawn["rgb"]) + (1 - drawn["fill"]) * without[area]
        assert np.median(np.abs(with_targets[area] - blend).max(-1)) <= 6, (with_targets[area], blend)
        assert np.abs(with_targets[area] - without[area]).max() > 20
        assert drawn["fill"] <= 0.1              # faint: a capture's whole path must not hide the model
    # Not a colour of the score ramp (sampled finely), nor the training cameras' grey.
    ramp = np.concatenate([a + (b - a) * t[:, None] for a, b, t in
                           zip(SCORE_RAMP, SCORE_RAMP[1:], [np.linspace(0, 1, 50)] * 4)])
    target = np.array(state["targets"][0]["rgb"])
    assert np.linalg.norm(ramp - target, axis=1).min() > 60
    assert np.linalg.norm(target - [0xe8, 0xec, 0xf0]) > 60
    # Targets at the returned candidates' own poses lie under them: each candidate keeps its colour.
    _call(browser, "phdView3d.showRanking(arguments[0], {candidates: arguments[1]})", ranking, candidates)
    alone = _pixels(browser).astype(float)
    _call(browser, "phdView3d.showTargets(arguments[0])", [v["camera"] for v in ranking["views"]])
    state = browser.execute_script("return phdView3d.debug()")
    covered = _pixels(browser).astype(float)
    assert len(state["targets"]) == len(state["frusta"]) == TOP_K
    for f in state["frusta"]:
        px, py, _ = _project(state, f["centre"])
        assert 0 < px < state["width"] and 0 < py < state["height"]
        assert np.abs(covered[int(py), int(px)] - alone[int(py), int(px)]).max() <= 8
    legend = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert "candidate score" in legend and f"target view ({TOP_K})" in legend
    _assert_swatches_look_like_the_frusta(browser, state["styles"])
    _call(browser, "phdView3d.showTargets([])")
    assert "target view" not in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    assert _console_errors(browser) == []


def _assert_swatches_look_like_the_frusta(driver, styles: dict) -> None:
    """Every frustum kind in the legend (training cameras, target views, unreturned candidates) has a
    swatch drawn as a small wireframe in its frusta's own wire colour, opacity and fill, on the
    view's background: the training camera's a white wireframe, not a filled box."""
    swatches = driver.execute_script(
        "return [...document.querySelectorAll('#view3d .v3d-legend svg')].map(s => { const p = s.querySelector('path');"
        "return [s.getAttribute('class'), getComputedStyle(s).backgroundColor, p.getAttribute('stroke'),"
        "Number(p.getAttribute('stroke-opacity')), p.getAttribute('fill'), Number(p.getAttribute('fill-opacity'))]; })")
    assert sorted(s[0].split()[1] for s in swatches) == ["target", "training", "unreturned"]
    for kind_class, background, stroke, stroke_opacity, fill, fill_opacity in swatches:
        style = styles[kind_class.split()[1]]
        colour = "rgb({}, {}, {})".format(*style["rgb"]).replace(" ", "")
        assert background == "rgb({}, {}, {})".format(*BACKGROUND)
        assert stroke.replace(" ", "") == colour and stroke_opacity == style["opacity"]
        assert (fill == "none") if style["fill"] == 0 else (fill.replace(" ", "") == colour
                                                            and fill_opacity == style["fill"])
    import imageio.v3 as iio
    training = driver.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend svg.training")
    pixels = iio.imread(training.screenshot_as_png)[..., :3].astype(int)
    light = (pixels.min(-1) > 120).mean()                    # wire lines: light grey over the dark background
    dark = (np.abs(pixels - BACKGROUND).max(-1) <= 8).mean()
    assert 0.05 < light < 0.5 and dark > 0.4, (light, dark)


def test_the_view_files_are_local_and_open(ranked):
    server, _, _, _ = ranked
    page = httpx.get(server.url + "/ui/").text
    assert '<script type="module" src="view3d.js"></script>' in page and '<div id="view3d"></div>' in page
    for path in ("/ui/view3d.js", "/ui/view3d.css", "/ui/vendor/three.module.min.js", "/ui/vendor/OrbitControls.js"):
        answer = httpx.get(server.url + path)          # no key: static files
        assert answer.status_code == 200, path
        assert answer.headers["content-type"].startswith("text/css" if path.endswith(".css") else "text/javascript")
        # Nothing the view runs names another host (the one URL in three.js is the XHTML namespace).
        assert set(re.findall(r"https?://[\w.-]+", answer.text)) <= {"http://www.w3.org", "https://github.com"}, path
    three = httpx.get(server.url + "/ui/vendor/three.module.min.js").text
    assert three.startswith("// three.js r170, from the npm package three@0.170.0") and 'const t="170"' in three
    assert "from './three.module.min.js'" in httpx.get(server.url + "/ui/vendor/OrbitControls.js").text
    missing = httpx.get(server.url + "/ui/vendor/three.js", headers=AUTH)   # a fixed list of files
    assert missing.status_code == 404 and missing.json()["error"]["field"] == "name"


def test_the_view_starts_upright_on_the_captures_up(browser, ranked, tmp_path):
    """A column standing on the true up, red on top, photographed from one side looking down
    (support/upright.py): the view stands on the up the service works out, not on the cameras'
    mean up (38 degrees off here), so the column's top is drawn straight above its foot."""
    from phd_core.renderers.gs3d import write_ply
    from support.upright import UP, column, degrees_from_up, mean_up, one_side

    server, _, _, _ = ranked
    write_ply(column(), tmp_path / "column.ply")
    training = one_side()
    with PHDClient(server.url, api_key=KEY) as phd:
        model = phd.upload_model(tmp_path / "column.ply", cameras=training, name="upright column")
    served = httpx.get(f"{server.url}/v1/models/{model.id}/cameras", headers=AUTH).json()
    assert served["up_rule"] == "horizontal axes"
    assert degrees_from_up(torch.tensor(served["up"], dtype=torch.float64)) < 2.0
    assert degrees_from_up(mean_up(training)) > 25.0
    state = _open(browser, server, model)
    assert state["up"] == pytest.approx(served["up"]) and browser.execute_script("return state.up") == served["up"]
    # The true up through the view's camera: a vertical line on the canvas, pointing up.
    (x0, y0, _), (x1, y1, _) = (_project(state, sign * 0.6 * UP.numpy()) for sign in (-1, 1))
    assert abs(np.degrees(np.arctan2(x1 - x0, y0 - y1))) < 2.0
    # And in the pixels: the red splats' centroid straight above the blue ones'.
    image = _pixels(browser).astype(int)
    rows, cols = np.indices(image.shape[:2])
    red = (image[..., 0] > 150) & (image[..., 1] < 90) & (image[..., 2] < 90)
    blue = (image[..., 2] > 150) & (image[..., 0] < 90) & (image[..., 1] < 90)
    assert red.sum() > 20 and blue.sum() > 20
    dx, dy = cols[red].mean() - cols[blue].mean(), rows[blue].mean() - rows[red].mean()
    assert dy > 0 and abs(np.degrees(np.arctan2(dx, dy))) < 3.0
    assert _console_errors(browser) == []


def test_a_model_mounted_while_another_is_explained_gets_its_own_explanation(browser, ranked, svc_model_files):
    """Coverage on: model A's explain job still queued when model B is chosen. B is explained
    (its own job), not left with A's request, which was for other splats."""
    server, model, _, _ = ranked
    with PHDClient(server.url, api_key=KEY) as phd:
        other = phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(4), name="other splats")
        phd.calibrate(other.id, epsilon=0.05, step=0.2, samples=3, seed=1)
    _open(browser, server, model)
    held = hold_worker(server.url, AUTH, model.id)
    try:
        browser.execute_script("phdView3d.setMode('coverage')")                 # A's explain waits for the worker
        Select(browser.find_element(By.ID, "model-select")).select_by_value(other.id)
        WebDriverWait(browser, 30).until(lambda d: d.execute_script(
            "return state.modelId === arguments[0] && state.viewReady", other.id))
    finally:
        httpx.delete(f"{server.url}/v1/jobs/{held}", headers=AUTH)
    WebDriverWait(browser, 60).until(lambda d: d.execute_script("return phdView3d.debug().explained.length"))
    state = browser.execute_script("return phdView3d.debug()")
    assert (state["mode"], state["points"], set(state["explained"])) == ("coverage", 200, {"coverage", "fragility"})
    jobs = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert sum(name.endswith(f"/v1/models/{other.id}/explain") for name in jobs) == 1
    assert "no captured view saw it" in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    _call(browser, "phdView3d.setMode('colour')")


def test_calibrating_on_the_page_lets_the_view_explain_the_model(browser, ranked, svc_model_files):
    """Fragility asked before calibrating says to calibrate; the page's Calibrate button (disabled
    while its job runs) then brings the fragility colours, and the message goes."""
    server, model, _, _ = ranked
    with PHDClient(server.url, api_key=KEY) as phd:
        # Another model than the fixture's (4 cameras, not 3): the same upload would answer the calibrated one.
        bare = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(4), name="calibrated on the page")
    _open(browser, server, bare)
    _call(browser, "phdView3d.setMode('fragility')")
    status = browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-status")
    assert status.text == "calibrate the model first: fragility is measured at its dropout ratio"
    assert "error" in status.get_attribute("class") and status.is_displayed()
    assert browser.execute_script("return phdView3d.debug().explained") == []
    errors = _console_errors(browser)          # the browser logs the refused request itself, and nothing else
    assert len(errors) == 1 and "/explain" in errors[0] and "409" in errors[0]
    browser.find_element(By.ID, "cal-samples").clear()
    browser.find_element(By.ID, "cal-samples").send_keys("3")
    held = hold_worker(server.url, AUTH, model.id)
    try:
        browser.find_element(By.ID, "calibrate").click()                      # queued behind the held job
        WebDriverWait(browser, 10).until(
            lambda d: d.execute_script("return !document.getElementById('cal-progress').hidden"))
        assert not browser.find_element(By.ID, "calibrate").is_enabled()
    finally:
        httpx.delete(f"{server.url}/v1/jobs/{held}", headers=AUTH)
    WebDriverWait(browser, 60).until(lambda d: "calibrated: r_drop" in d.find_element(By.ID, "model-info").text)
    WebDriverWait(browser, 60).until(lambda d: d.execute_script("return phdView3d.debug().explained.length"))
    assert browser.find_element(By.ID, "calibrate").is_enabled()
    assert browser.execute_script("return [state.modelId, phdView3d.debug().mode]") == [bare.id, "fragility"]
    assert "calibrate" not in status.text and "error" not in status.get_attribute("class")
    assert "fragile (zeta high)" in browser.find_element(By.CSS_SELECTOR, "#view3d .v3d-legend").text
    _call(browser, "phdView3d.setMode('colour')")

