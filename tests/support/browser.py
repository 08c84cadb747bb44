"""Headless Chromium from the distribution's packages, driven by selenium through the
distribution's chromedriver (an explicit path: Selenium Manager downloads nothing). WebGL
runs on SwiftShader, the CPU rasteriser Chromium ships."""

from __future__ import annotations

import shutil
from pathlib import Path

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--enable-unsafe-swiftshader", "--use-angle=swiftshader")


def have_browser() -> bool:
    return Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()


def chromium(profile: Path, width: int = 1280, height: int = 1600, flags: tuple[str, ...] = ()):
    """A headless Chromium whose console log the test can read (goog:loggingPrefs); `flags`: more
    command-line switches (e.g. `--disable-webgl`, a browser without WebGL)."""
    from selenium import webdriver

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--window-size={width},{height}", f"--user-data-dir={profile}", *flags):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=webdriver.ChromeService(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    return driver


def hold_worker(url: str, headers: dict[str, str], model_id: str) -> str:
    """Occupy the server's one worker with a long rank job and return its id (DELETE /v1/jobs/{id}
    lets go): the page's next job then waits in the queue for as long as the test needs."""
    import httpx

    answer = httpx.post(f"{url}/v1/models/{model_id}/rank", headers=headers, timeout=30, json={
        "candidates": {"generator": "hemisphere", "count": 400}, "samples": 32, "downscale": 1, "async": True})
    assert answer.status_code == 202, answer.text
    return answer.json()["id"]
