"""A model `phd train` wrote, through the service's two other doors as a user takes each: the
Python client (`through_client`) and the web page (`through_page`). Each uploads the PLY with
its sidecar, calibrates, ranks generated orbit candidates (the first `top_k`) and every frame
of a poses file (`phd candidates frames` writes one) at `phd rank`'s defaults (but `samples`,
when given), and returns what it was shown. bench/bench_real.py compares that with `phd rank` on every real
capture, tests/page/test_page_real_capture.py on one."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import imageio.v3 as iio
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select

from client import PHDClient
from phd_core.uq import DEFAULT_CALIBRATION_SAMPLES, DEFAULT_SAMPLES
from service.schemas import RankResult

from .page import choose_files, console_errors, grid_loaded, run_on_candidates, set_field, text_of, wait


class Stopwatch:
    """Wall seconds per step, each step from the end of the one before."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step] = round(now - self._last, 2)
        self._last = now


def ranked(result: RankResult) -> dict[str, Any]:
    """A ranking as the doors compare them: candidate indices first to last, their scores, the ratio."""
    return {"order": [v.index for v in result.views], "scores": [v.score for v in result.views],
            "dropout_ratio": result.dropout_ratio}


def through_client(url: str, key: str, model: Path, frames: Path, *, orbit: int = 64, top_k: int = 5,
                   samples: int = DEFAULT_SAMPLES) -> dict[str, Any]:
    """Upload (the sidecar beside the PLY goes with it), calibrate, rank `orbit` generated
    candidates and the poses file's frames (heat maps as files: the first one is downloaded);
    the model is deleted at the end, so that the next door uploads its own."""
    watch = Stopwatch()
    with PHDClient(url, api_key=key) as phd:
        info = phd.upload_model(model, name=f"{model.stem} (client)")
        watch.lap("upload")
        calibration = phd.calibrate(info.id)
        watch.lap("calibrate")
        around = phd.rank(info.id, candidates=f"orbit:{orbit}", top_k=top_k, samples=samples)
        watch.lap("rank_orbit")
        own = phd.rank(info.id, frames, samples=samples, heatmaps="files")
        assert isinstance(around, RankResult) and isinstance(own, RankResult)   # waited for: no Job
        first = own.views[0]
        heatmap = iio.imread(phd.download(first.heatmap_url or ""))
        watch.lap("rank_frames")
        phd.delete_model(info.id)       # else the page's upload of the same files is answered by this model
    return {"training_cameras": info.num_training_cameras, "r_drop": calibration.r_drop,
            "seconds": watch.seconds, "orbit": ranked(around), "frames": ranked(own),
            "heatmap_size": [heatmap.shape[1], heatmap.shape[0]], "frame_size": [first.camera["w"], first.camera["h"]]}


# What the page shows of its last ranking: the cards' order, the heat maps' sizes against their
# frames', what the 3D view and the plot from above drew.
SHOWN = """
const cards = [...document.querySelectorAll('#rank-grid li.card')], view = phdView3d.debug();
const heatmaps = [...document.querySelectorAll('#rank-grid img.heatmap')];
return {order: cards.map(c => Number(c.dataset.index)), scores: state.ranking.views.map(v => v.score),
        dropout_ratio: state.ranking.dropout_ratio, heatmap_sizes: heatmaps.map(i => [i.naturalWidth, i.naturalHeight]),
        frame_sizes: state.ranking.views.map(v => [v.camera.w, v.camera.h]),
        view: {training: view.training, splats: view.total, frusta: view.frusta.length},
        plot: {training: document.querySelectorAll('#plot-top path.train').length,
               candidates: document.querySelectorAll('#plot-top circle.cand[fill]').length}};
"""


def through_page(driver, url: str, key: str, model: Path, frames: Path, *, orbit: int = 64, top_k: int = 5,
                 samples: int = DEFAULT_SAMPLES, timeout: float = 900.0) -> dict[str, Any]:
    """The same on the page: the PLY and its sidecar picked in the upload's file input, the
    uploaded model chosen, Calibrate, a ring of `orbit` candidates ranked (the page's own
    elevation: the same request through the client gives the order the page should show), then
    the poses file picked as candidates and ranked. `timeout`: seconds any one step may take."""
    name = f"{model.stem} (page)"
    console_errors(driver)                                  # the log from here on
    watch = Stopwatch()
    driver.get(url + "/ui/")
    set_field(driver, "api-key", key)
    driver.find_element(By.CSS_SELECTOR, "#key-form button").click()
    wait(driver, lambda d: text_of(d, "message") == "key saved in this browser", what="the model list")
    driver.execute_script("document.getElementById('upload-details').open = true")
    choose_files(driver, "upload-file", model, model.with_suffix(".json"))
    set_field(driver, "upload-name", name)
    driver.find_element(By.ID, "upload-run").click()
    wait(driver, lambda d: f"Uploaded {name}: " in text_of(d, "upload-message"), timeout, what="the upload")
    model_id = driver.execute_script("return state.models.find(m => m.name === arguments[0]).id", name)
    Select(driver.find_element(By.ID, "model-select")).select_by_value(model_id)    # a model chosen before stays A
    wait(driver, lambda d: d.execute_script("return state.modelId === arguments[0] && state.viewReady", model_id),
         timeout, what="the model's 3D view")
    watch.lap("upload")

    set_field(driver, "cal-samples", DEFAULT_CALIBRATION_SAMPLES)
    set_field(driver, "cal-downscale", 1)
    driver.find_element(By.ID, "calibrate").click()
    wait(driver, lambda d: "calibrated: r_drop" in text_of(d, "model-info"), timeout, what="the calibration")
    r_drop = driver.execute_script("return currentModel().calibration.r_drop")
    watch.lap("calibrate")

    run_on_candidates(driver, orbit, "rank", {"rank-samples": samples, "rank-downscale": 1, "rank-seed": 0,
                                              "rank-topk": top_k}, cards=top_k, timeout=timeout)
    around, spec = driver.execute_script(SHOWN), driver.execute_script("return state.spec")
    watch.lap("rank_orbit")

    count = len(json.loads(frames.read_text())["frames"])
    driver.find_element(By.CSS_SELECTOR, "input[name=cand-mode][value=file]").click()
    choose_files(driver, "cand-file", frames)
    wait(driver, lambda d: d.execute_script("return state.candidates.length") == count, what="the poses file")
    set_field(driver, "rank-topk", "")                      # every frame
    driver.find_element(By.ID, "rank-run").click()
    wait(driver, grid_loaded("rank", count), timeout, what="the ranking of the poses file")
    own = driver.execute_script(SHOWN)
    watch.lap("rank_frames")

    with PHDClient(url, api_key=key) as phd:
        replayed = phd.rank(model_id, candidates=spec, samples=samples, downscale=1, top_k=top_k)
        assert isinstance(replayed, RankResult)
    return {"model_id": model_id, "r_drop": r_drop, "seconds": watch.seconds, "orbit": around, "orbit_spec": spec,
            "orbit_through_client": ranked(replayed), "frames": own, "console_errors": console_errors(driver)}
