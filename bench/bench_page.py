"""The web page on a real model: time from the Rank click to a grid whose images have all
loaded, against the same request through the Python client, interleaved in one run; and the
screenshots that docs/service.md shows.

    .venv/bin/python -m bench.bench_page --model-a A.ply --model-b B.ply --out docs --repeats 3 \
        [--targets walkthrough.json]

With `--targets`, a pose file in the models' frame, also a ranking of the first 4 candidates for
those target views: the 3D view and the rank section together (page_targets.png).

Both PLYs need their training cameras (the sidecar JSON `phd train` writes beside them): the
page uploads each with its sidecar, as a user picks the two files. `--repeats 0` takes the
screenshots only. Starts `phd serve` in-process on a free 127.0.0.1 port with an API key,
headless Chromium through the distribution's chromedriver (as tests/page does).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait

from bench._harness import timed
from client import PHDClient
from service.runner import BackgroundServer
from service.settings import Settings

KEY = "bench-key"


def browser(width: int, height: int) -> webdriver.Chrome:
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--window-size={width},{height}", f"--user-data-dir={tempfile.mkdtemp()}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=webdriver.ChromeService(executable_path="/usr/bin/chromedriver"), options=options)


def set_field(driver, element_id: str, value) -> None:
    field = driver.find_element(By.ID, element_id)
    field.clear()
    field.send_keys(str(value))


def grid_ready(grid: str, count: int):
    return lambda d: (len(d.find_elements(By.CSS_SELECTOR, f"#{grid} li.card")) == count and d.execute_script(
        f"return [...document.querySelectorAll('#{grid} img')].every(i => i.complete && i.naturalWidth > 0)"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model-a", type=Path, required=True)
    parser.add_argument("--model-b", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--candidates", type=int, default=12)
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--targets", type=Path, default=None, help="target views: a pose file the page reads")
    args = parser.parse_args()

    server = BackgroundServer(Settings(data_dir=Path(tempfile.mkdtemp()) / "data", api_key=KEY))
    driver = browser(1280, 4400)   # tall enough that element screenshots hold whole sections
    try:
        with PHDClient(server.url, api_key=KEY) as phd:
            driver.get(server.url + "/")
            set_field(driver, "api-key", KEY)
            driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
            args.out.mkdir(parents=True, exist_ok=True)
            for count, model in enumerate((args.model_a, args.model_b), start=1):   # the PLY and its sidecar
                driver.execute_script("document.getElementById('upload-file').value = ''")
                driver.find_element(By.ID, "upload-file").send_keys(f"{model}\n{model.with_suffix('.json')}")
                set_field(driver, "upload-name", model.stem)
                driver.find_element(By.ID, "upload-run").click()
                WebDriverWait(driver, 120).until(
                    lambda d: len(Select(d.find_element(By.ID, "model-select")).options) == count
                    and "Uploaded" in d.find_element(By.ID, "upload-message").text)
                if count == 2:
                    driver.find_element(By.ID, "model-section").screenshot(str(args.out / "page_upload.png"))
            a, b = sorted(phd.list_models(), key=lambda m: m.name != args.model_a.stem)
            for model in (a, b):
                phd.calibrate(model.id, samples=4, downscale=2)
            driver.find_element(By.ID, "refresh-models").click()
            Select(driver.find_element(By.ID, "model-select")).select_by_value(a.id)
            Select(driver.find_element(By.ID, "model-b-select")).select_by_value(b.id)
            WebDriverWait(driver, 60).until(lambda d: "r_drop" in d.find_element(By.ID, "model-info").text)
            set_field(driver, "gen-count", args.candidates)
            set_field(driver, "rank-samples", args.samples)
            set_field(driver, "rank-downscale", 1)
            set_field(driver, "rank-topk", "")
            driver.find_element(By.ID, "gen-elevation").click()
            WebDriverWait(driver, 60).until(
                lambda d: (d.execute_script("return state.spec") or {}).get("count") == args.candidates)
            spec = driver.execute_script("return state.spec")      # the service makes the poses for both
            def rank_on_page() -> None:
                driver.find_element(By.ID, "rank-run").click()
                WebDriverWait(driver, 600, poll_frequency=0.05).until(grid_ready("rank-grid", args.candidates))

            page_times, client_times = [], []
            for _ in range(args.repeats):
                ranked = timed(lambda: phd.rank(a.id, candidates=spec, samples=args.samples, downscale=1,
                                                heatmaps="files"))
                client_times.append(ranked.seconds)
                page_times.append(timed(rank_on_page).seconds)
            if not page_times:
                rank_on_page()
            size = driver.execute_script("return [state.ranking.width, state.ranking.height]")
            driver.execute_script("document.querySelector('#rank-grid li.card').click()")
            driver.find_element(By.ID, "rank-section").screenshot(str(args.out / "page_rank.png"))
            # The page's first screenful and a half as a new user meets it after a rank (docs' overview).
            driver.set_window_size(1280, 1800)
            driver.execute_script("window.scrollTo(0, 0)")
            driver.save_screenshot(str(args.out / "page_overview.png"))
            driver.set_window_size(1280, 4400)
            # An error where it happened: a candidates file with a misspelt key.
            typo = Path(tempfile.mkdtemp()) / "candidates.json"
            typo.write_text(json.dumps({"camera_angle_x": 0.69, "frame": []}))
            driver.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=file]").click()
            driver.find_element(By.ID, "cand-file").send_keys(str(typo))
            WebDriverWait(driver, 60).until(lambda d: "frames" in d.find_element(By.ID, "cand-message").text)
            driver.find_element(By.ID, "candidate-section").screenshot(str(args.out / "page_error.png"))
            driver.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=generate]").click()
            driver.find_element(By.ID, "gen-elevation").click()
            rank_on_page()
            driver.find_element(By.ID, "select-run").click()
            WebDriverWait(driver, 600).until(grid_ready("select-grid", args.candidates))
            driver.find_element(By.ID, "select-section").screenshot(str(args.out / "page_select.png"))
            if args.targets:      # where the model will be looked at from: drawn, sent, named in the summary
                set_field(driver, "rank-topk", 4)
                driver.find_element(By.ID, "targets-file").send_keys(str(args.targets.resolve()))
                WebDriverWait(driver, 60).until(lambda d: d.execute_script("return state.targets.length") > 0)
                driver.find_element(By.ID, "rank-run").click()
                WebDriverWait(driver, 600).until(grid_ready("rank-grid", 4))
                others = "#model-section, #candidate-section, #select-section, #rank-grid, .plots"
                driver.execute_script(f"document.querySelectorAll('{others}').forEach(e => e.style.display = 'none')")
                driver.find_element(By.TAG_NAME, "main").screenshot(str(args.out / "page_targets.png"))
            phone = browser(390, 2400)
            try:
                phone.get(server.url + "/ui/")
                set_field(phone, "api-key", KEY)
                phone.find_element(By.CSS_SELECTOR, "#key-form button").click()
                WebDriverWait(phone, 60).until(
                    lambda d: len(Select(d.find_element(By.ID, "model-select")).options) == 2)
                overflow = phone.execute_script("return document.documentElement.scrollWidth - window.innerWidth")
            finally:
                phone.quit()
        report = {
            "candidates": args.candidates, "samples": args.samples, "size": f"{size[0]}x{size[1]}",
            "repeats": args.repeats,
            "client_rank_s": [round(t, 2) for t in client_times], "page_rank_s": [round(t, 2) for t in page_times],
            "page_over_client_median": round(statistics.median(p / c for p, c in zip(page_times, client_times)), 3)
            if page_times else None,
            "phone_horizontal_overflow_px": overflow,
        }
        print(json.dumps(report, indent=2))
        return 0
    finally:
        driver.quit()
        server.stop()


if __name__ == "__main__":
    sys.exit(main())
