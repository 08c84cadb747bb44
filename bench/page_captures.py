"""The screenshot of the page's Captures section that docs/service.md shows: a capture made from
photos and trained, photos added and trained again from the first model (warm start), the next
views asked for, all through the Python client; then the page in headless Chromium shows the
capture: its rounds' table and charts, and the 3D view with the latest model, each round's
cameras in its colour and the views to capture next.

    .venv/bin/python -m bench.page_captures --photos FIRST_DIR --add MORE_DIR --test 18.jpg 26.jpg \
        --out docs/page_captures.png

Starts the service in-process on a free 127.0.0.1 port with an API key, as bench/bench_page.py.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait

from bench.bench_page import KEY, browser, set_field
from client import PHDClient
from service.runner import BackgroundServer
from service.settings import Settings


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=Path, required=True, help="a folder of the capture's first photos")
    parser.add_argument("--add", type=Path, required=True, help="a folder of photos added as round 1")
    parser.add_argument("--test", nargs="*", default=[], help="names of first photos held out of training")
    parser.add_argument("--max-size", type=int, default=300, help="the service's capture_max_size (px)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--next", type=int, default=2, help="next views asked for after round 1")
    parser.add_argument("--zoom", type=int, default=0, help="mouse-wheel steps closer before the screenshot")
    parser.add_argument("--out", type=Path, default=Path("docs/page_captures.png"))
    args = parser.parse_args()

    settings = Settings(data_dir=Path(tempfile.mkdtemp()) / "data", api_key=KEY, capture_max_size=args.max_size)
    server = BackgroundServer(settings)
    driver = browser(1280, 2400)
    try:
        with PHDClient(server.url, api_key=KEY) as phd:
            capture = phd.create_capture(args.photos, test=args.test, name=args.photos.name)
            capture.train(iterations=args.iterations, samples=4)
            capture.add_photos(args.add)
            capture.train(iterations=args.iterations, samples=4)
            capture.next_views(args.next, candidates={"generator": "orbit", "count": 24}, samples=4)
            info = capture.info
        driver.get(server.url + "/ui/")
        set_field(driver, "api-key", KEY)
        driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
        WebDriverWait(driver, 60).until(lambda d: len(Select(d.find_element(By.ID, "capture-select")).options) == 2)
        Select(driver.find_element(By.ID, "capture-select")).select_by_value(capture.id)
        WebDriverWait(driver, 120).until(lambda d: d.execute_script(
            "return Boolean(loop.shown && state.viewReady && state.modelId === loop.shown.model_id)"))
        others = "header, #model-section, #candidate-section, #rank-section, #select-section"
        driver.execute_script(f"document.querySelectorAll('{others}').forEach(e => e.hidden = true)")
        canvas = driver.find_element(By.CSS_SELECTOR, "#view3d canvas")
        for _ in range(args.zoom):        # the mouse wheel over the view, as a user looks closer
            ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, -120).perform()
        driver.execute_script("window.phdView3d.drawNow(true)")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        driver.find_element(By.TAG_NAME, "main").screenshot(str(args.out))
        print(json.dumps({"rounds": [{"round": r.round, "photos": len(r.photos), "registered": len(r.registered),
                                      "train": r.train and r.train.model_dump(include={"test_psnr", "sigma_max_bar",
                                                                                       "r_drop", "seconds"})}
                                     for r in info.rounds], "out": str(args.out)}, indent=2))
        return 0
    finally:
        driver.quit()
        server.stop()


if __name__ == "__main__":
    sys.exit(main())
