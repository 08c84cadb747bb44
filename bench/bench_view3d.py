"""The page's 3D view on a real model: the screenshots docs/service.md shows, and what the view
costs at a million splats (the scene's bytes and time, the browser's load and its depth sort).

    .venv/bin/python -m bench.bench_view3d --model a2.ply --out docs [--splats 1000000]

The PLY needs its training cameras (the sidecar JSON `phd train` writes). Starts the service
in-process on a free 127.0.0.1 port with an API key and drives headless Chromium (WebGL on
SwiftShader, the CPU rasteriser) through the distribution's chromedriver, as tests/page does.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import httpx
import torch
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from client import PHDClient
from phd_core.renderers.gs3d import GaussianModel, write_ply
from service.runner import BackgroundServer
from service.settings import Settings

KEY = "bench-key"
AUTH = {"Authorization": f"Bearer {KEY}"}
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.browser import chromium  # noqa: E402


def call(driver, script: str, *args):
    done = driver.execute_async_script(
        f"const done = arguments[arguments.length - 1]; Promise.resolve().then(() => {script})"
        ".then(v => done({ok: v === undefined ? null : v}), e => done({error: String(e && e.stack || e)}));", *args)
    if "error" in done:
        raise RuntimeError(done["error"])
    return done["ok"]


def open_view(driver, server: BackgroundServer, model_id: str) -> float:
    """The page with the view mounted on the model; the seconds mount took."""
    driver.get(server.url + "/health")
    driver.execute_script("localStorage.setItem('phd-api-key', arguments[0])", KEY)
    driver.get(server.url + "/ui/")
    WebDriverWait(driver, 30).until(lambda d: d.execute_script("return !!window.phdView3d"))
    start = time.perf_counter()
    call(driver, "phdView3d.mount(document.getElementById('view3d'), {modelId: arguments[0], headers: arguments[1]})",
         model_id, AUTH)
    return time.perf_counter() - start


def screenshots(server: BackgroundServer, model: Path, out: Path, candidates: int, top_k: int) -> None:
    with PHDClient(server.url, api_key=KEY) as phd:
        info = phd.upload_model(model, name=model.stem)
        phd.calibrate(info.id, samples=4, downscale=2)
    spec = {"generator": "orbit", "count": candidates, "options": {"elevation": math.radians(30)}}
    ranking = httpx.post(f"{server.url}/v1/models/{info.id}/rank", headers=AUTH, timeout=600, json={
        "candidates": spec, "samples": 8, "downscale": 2, "top_k": top_k, "heatmaps": "files"}).json()
    driver = chromium(Path(tempfile.mkdtemp()), 1100, 1400)
    try:
        open_view(driver, server, info.id)
        call(driver, "phdView3d.showRanking(arguments[0])", ranking)
        first = next(v["index"] for v in ranking["views"] if v["rank"] == 1)
        call(driver, "phdView3d.select(arguments[0])", first)
        driver.execute_script("document.getElementById('view3d').scrollIntoView()")
        driver.find_element(By.ID, "view3d").screenshot(str(out / "view3d_rank.png"))
        for mode in ("coverage", "novelty"):
            call(driver, f"phdView3d.setMode('{mode}')")
            driver.find_element(By.ID, "view3d").screenshot(str(out / f"view3d_{mode}.png"))
        print(json.dumps({"model": str(model), "splats": info.num_units, "candidates": candidates, "top_k": top_k,
                          "first": first, "status": driver.find_element(By.CSS_SELECTOR, ".v3d-status").text}))
    finally:
        driver.quit()


def large_model(splats: int, path: Path) -> None:
    """A random SH-degree-0 splat cloud: a sphere shell and its inside, scales from 1 to 10 mm."""
    g = torch.Generator().manual_seed(0)
    direction = torch.nn.functional.normalize(torch.randn(splats, 3, generator=g), dim=1)
    radius = torch.rand(splats, 1, generator=g).pow(0.2)
    scales = torch.log(0.001 + 0.009 * torch.rand(splats, 3, generator=g))
    write_ply(GaussianModel(means=direction * radius, log_scales=scales, quats=torch.randn(splats, 4, generator=g),
                            opacity_logits=torch.randn(splats, generator=g) * 2,
                            sh=torch.randn(splats, 1, 3, generator=g) * 0.5), path)


def scale(server: BackgroundServer, splats: int, repeats: int) -> None:
    """The scene of a model of `splats` splats at the default cap: bytes, server time, browser load, depth sort."""
    from phd_core.scene import look_at

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "large.ply"
        large_model(splats, path)
        cameras = [look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0), (0, 0, 1), width=100, height=100,
                           fov_x=0.8) for a in (0.0, 2.0, 4.0)]
        with PHDClient(server.url, api_key=KEY, timeout=600) as phd:
            info = phd.upload_model(path, cameras=cameras, name="large")
    rows = []
    driver = chromium(Path(tempfile.mkdtemp()), 1100, 1400)
    try:
        for _ in range(repeats):
            start = time.perf_counter()
            data = httpx.get(f"{server.url}/v1/models/{info.id}/scene", headers=AUTH, timeout=600).content
            served = time.perf_counter() - start
            mounted = open_view(driver, server, info.id)
            # A turn of the view: the depth sort (JS) and the frame drawn and read back (SwiftShader).
            frames = driver.execute_script(
                "const c = document.querySelector('#view3d canvas'), t = [], s = [];"
                "for (let k = 0; k < 5; k++) { const t0 = performance.now(); phdView3d.drawNow(true); "
                "c.toDataURL(); t.push(performance.now() - t0); s.push(phdView3d.debug().sortMs); } return [t, s];")
            count = driver.execute_script("return phdView3d.debug().points")
            rows.append({"bytes": len(data), "points": count, "scene_s": round(served, 2),
                         "mount_s": round(mounted, 2), "frame_ms": [round(x) for x in frames[0]],
                         "sort_ms": [round(x) for x in frames[1]]})
    finally:
        driver.quit()
    print(json.dumps({"splats": splats, "runs": rows}))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--candidates", type=int, default=16)
    parser.add_argument("--top-k", type=int, default=6)
    parser.add_argument("--splats", type=int, default=0, help="also time the view on a random model this large")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as data, \
            BackgroundServer(Settings(data_dir=Path(data), api_key=KEY, memory_budget_bytes=8 << 30)) as server:
        screenshots(server, args.model, args.out, args.candidates, args.top_k)
        if args.splats:
            scale(server, args.splats, args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
