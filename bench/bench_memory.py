"""Peak memory of `phd serve` against its own memory plan (issue 17, docs/reliability.md).

Sweep: one fresh server process per row (as users run it), every row at each budget of
`--budgets` (1 and 4 GiB), over the model families (3dgs, 2dgs, nerf), model sizes (300 /
1k / 50k / 300k random splats, the 45k donut of bench_speed and 22 tiled copies of it: 1M
splats; synthetic PLYs written by the project's own writers), overlap (small or large
splats: from a few splats per pixel to hundreds), resolution (100-800 px), samples (4-256),
the routes rank (a view's uncertainty is its sigma_max and sigma_mean) / select / calibrate
and their heat-map and image options. For each: the server's peak RSS (VmHWM, reset just
before the request) over its idle RSS (models uploaded and in memory, every code path warmed
up by a tiny request of the same route), next to the service's plan of that request
(`service.work.Bounded.plan`: the same code the worker runs, here with the model loaded in
this process). A row with repeats runs its request that many times in the one server: each
run's peak, and the largest against the plan.

Concurrent: one server with a small budget (`--concurrent-budget`, 1 GiB) under jobs on
several models at once: 6 jobs and 2 uploads on 2 workers and a cache of 4 models, and 4 jobs
on 4 workers; its peak over its idle RSS before the first upload, next to the budget.

    OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python -m bench.bench_memory [--budgets 1 4] [--only NAME ...]

Writes bench/results/memory.json (merged with the rows already there when --only is given)
and prints the table docs/reliability.md shows. Two runs at once write a file each (--out);
`--merge FILE ...` alone adds their rows to memory.json and prints the table.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import httpx
import torch

from bench._harness import RESULTS, donut_cameras, donut_model, machine, reset_peak, tiled_model, vm, write_result
from client import PayloadTooLargeError, PHDClient
from phd_core.executors import LOCAL
from phd_core.renderers.gs2d import SurfelModel, write_surfel_ply
from phd_core.renderers.gs2d.render import surfel_counts
from phd_core.renderers.gs3d import GaussianModel, write_ply
from phd_core.renderers.gs3d.render import splat_counts
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, save_nerf
from phd_core.scene import Camera
from service.budget import MemoryLedger
from service.errors import ServiceError
from service.schemas import CalibrateRequest, RankRequest, SelectRequest
from service.settings import Settings
from service.store import ModelStore
from service.work import calibrate_job, model_loader, rank_job, select_job
from tests.support.fixtures import SvcProcess, svc_cameras

GIB = 1 << 30
OUT = RESULTS / "memory.json"


# ----------------------------------------------------------------------------- models

def splats(model_type: type[GaussianModel], count: int, scale: float, sh_degree: int = 3, seed: int = 0):
    """A random cloud in [-0.6, 0.6]^3 seen by `svc_cameras`; `scale` sets the overlap."""
    g = torch.Generator().manual_seed(seed)
    return model_type(means=(torch.rand(count, 3, generator=g) - 0.5) * 1.2,
                      log_scales=torch.log(scale * (0.5 + torch.rand(count, model_type.scale_axes, generator=g))),
                      quats=torch.randn(count, 4, generator=g), opacity_logits=torch.rand(count, generator=g) * 4 - 1,
                      sh=torch.randn(count, (sh_degree + 1) ** 2, 3, generator=g) * 0.3)


def tiled(model: GaussianModel, copies: int, scale: float = 0.25, spacing: float = 0.4) -> GaussianModel:
    """`copies` shrunk copies of `model` on a 3x3x3 grid inside [-0.6, 0.6]^3 (a large model
    whose splats are those of a real-looking one, as bench_speed tiles its donut)."""
    grid = torch.tensor([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)],
                        dtype=torch.float32)[:copies] * spacing
    return GaussianModel(means=(model.means[None] * scale + grid[:, None]).reshape(-1, 3),
                         log_scales=(model.log_scales + math.log(scale)).repeat(copies, 1),
                         quats=model.quats.repeat(copies, 1), opacity_logits=model.opacity_logits.repeat(copies),
                         sh=model.sh.repeat(copies, 1, 1))


def nerf(encoding: str) -> NeRFRenderer:
    """A NeRF whose occupancy grid is all occupied: every sample is evaluated (the worst case)."""
    config = NeRFConfig(encoding=encoding, width=64, samples=64, bounds=[[-1, -1, -1], [1, 1, 1]], near=1.0, far=5.0)
    return NeRFRenderer(RadianceField(config, seed=0))


MODELS = {   # name: how to write it
    "3dgs-1k-large": lambda p: write_ply(splats(GaussianModel, 1000, 0.05), p),
    "3dgs-50k-small": lambda p: write_ply(splats(GaussianModel, 50_000, 0.005), p),
    "3dgs-50k-small-b": lambda p: write_ply(splats(GaussianModel, 50_000, 0.005, seed=1), p),
    "3dgs-50k-large": lambda p: write_ply(splats(GaussianModel, 50_000, 0.05), p),
    "3dgs-300k-small": lambda p: write_ply(splats(GaussianModel, 300_000, 0.002), p),
    "3dgs-300-attack": lambda p: write_ply(splats(GaussianModel, 300, 0.06, sh_degree=1), p),
    "3dgs-45k-donut": lambda p: write_ply(donut_model(), p),
    "3dgs-1m-donuts": lambda p: write_ply(tiled(donut_model(), 22), p),          # 1,003,728 splats
    "3dgs-3m-donuts-sh3": lambda p: write_ply(tiled_model(66, 3), p),          # 3,011,184 splats, bench_scale's
    "2dgs-1k-large": lambda p: write_surfel_ply(splats(SurfelModel, 1000, 0.05), p),
    "2dgs-50k-small": lambda p: write_surfel_ply(splats(SurfelModel, 50_000, 0.005), p),
    "2dgs-50k-large": lambda p: write_surfel_ply(splats(SurfelModel, 50_000, 0.02), p),
    "nerf-pe": lambda p: save_nerf(nerf("pe"), p),
    "nerf-hash": lambda p: save_nerf(nerf("hash"), p),
}


def model_file(root: Path, name: str) -> Path:
    path = root / (name + (".nerf" if name.startswith("nerf") else ".ply"))
    if not path.exists():
        MODELS[name](path)
    return path


# ----------------------------------------------------------------------------- one server

def submit(url: str, path: str, body: dict) -> dict:
    """POST a job asynchronously and wait for it: its final state, or the refusal."""
    response = httpx.post(url + path, json={**body, "run_async": True}, timeout=600)
    if response.status_code != 202:
        return {"state": "refused", "status": response.status_code, "error": response.json().get("error")}
    job_id = response.json()["id"]
    while True:
        job = httpx.get(f"{url}/v1/jobs/{job_id}", timeout=60).json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return {"state": job["state"], "error": job.get("error")}
        time.sleep(0.5)


@dataclass
class Row:
    """One request: its route over uploaded models, its body; the field "cameras" etc. are
    filled from `size`/`views`. `training`: training cameras uploaded with the models."""

    name: str
    route: str                       # rank | select | calibrate
    models: list[str]
    size: int
    samples: int
    views: int = 1
    training: int = 0
    body: dict = field(default_factory=dict)
    budget: int = 4 * GIB
    repeats: int = 1                 # the request run this many times in the one server
    donut_ring: bool = False         # donut_200's ring poses at size x 3/4 size (a tiled grid's), else svc_cameras

    def cameras(self, count: int, size: int, split: str = "test") -> list[Camera]:
        """`count` poses at `size` pixels wide: candidates ("test") or training cameras ("train")."""
        if self.donut_ring:
            return donut_cameras(size, size * 3 // 4, count, split)
        return svc_cameras(count, size=size, phase=0.3 if split == "test" else 0.0)

    def request(self, ids: list[str], size: int, samples: int) -> tuple[str, dict]:
        frames = [c.to_frame() for c in self.cameras(self.views, size)]
        body = {"samples": samples, "seed": 0, **self.body}
        if self.route == "rank":
            return f"/v1/models/{ids[0]}/rank", {"cameras": frames, "dropout_ratio": 0.1, **body}
        if self.route == "select":
            return "/v1/select", {"model_a": ids[0], "model_b": ids[-1], "cameras": frames, "ratio_a": 0.1,
                                  "ratio_b": 0.1, **body}
        training = [c.to_frame() for c in self.cameras(self.training, size, "train")]
        return f"/v1/models/{ids[0]}/calibrate", {"training_cameras": training, "epsilon": 0.5, **body}


def plan_of(row: Row, data_dir: Path, ids: list[str], path: str, body: dict) -> dict:
    """The service's own plan of the request, computed here by the worker's code."""
    store = ModelStore(data_dir)
    settings = Settings(data_dir=data_dir, memory_budget_bytes=row.budget)
    ledger = MemoryLedger(row.budget, 4, model_loader(store))
    records = [store.get(i) for i in ids]
    if row.route == "rank":
        work, _ = rank_job(records[0], RankRequest(**body), settings, lambda name: name, ledger, LOCAL)
    elif row.route == "select":
        work, _ = select_job(records[0], records[-1], SelectRequest(**body), settings, lambda name: name, ledger, LOCAL)
    else:
        work, _ = calibrate_job(records[0], CalibrateRequest(**body), settings, store, ledger, LOCAL)
    renderers = {i: ledger.load(i) for i in set(ids)}
    plan = work.plan(renderers, lambda fraction: None)
    renderer, camera = renderers[ids[0]], work.renders.models[0][2][0]
    counts = {"3dgs": splat_counts, "2dgs": surfel_counts}.get(renderer.kind)
    depth = None if counts is None else counts(renderer, camera)[2] / (camera.width * camera.height)
    return {"estimate_bytes": plan.bytes, "mask_batch": plan.mask_batch,
            "fragments_per_pixel_bound": None if depth is None else round(depth, 1)}


def serve(data_dir: Path, **env: str) -> SvcProcess:
    """`phd serve` on `data_dir`, waited for up to 15 minutes: on a machine whose cores a
    benchmark at normal priority holds, this one (nice 19) can take minutes to start."""
    return SvcProcess(data_dir, start_timeout=900, **env)


def row_fields(row: Row) -> dict:
    """What a result repeats of its request."""
    return {"name": row.name, "route": row.route, "models": row.models, "size": row.size, "samples": row.samples,
            "views": row.views, "options": row.body, "budget_bytes": row.budget}


def measure(row: Row, root: Path) -> dict:
    """One row in a fresh server: the upload's peak, then the request's peak over the idle RSS
    (each of `repeats` runs), and the service's own plan of it; a model file over what the
    budget can parse is refused at upload, and that refusal is the row."""
    data_dir = Path(tempfile.mkdtemp(dir=root))
    server = serve(data_dir, PHD_MEMORY_BUDGET_BYTES=str(row.budget))
    try:
        with PHDClient(server.url, timeout=600) as phd:
            cameras = row.cameras(row.training, row.size, "train") if row.training else None
            start_rss = reset_peak(server.proc.pid)                   # the uploads' own peak too
            try:
                ids = [phd.upload_model(model_file(root, name), cameras=cameras).id for name in row.models]
            except PayloadTooLargeError as exc:                      # the model itself is over the budget
                return {**row_fields(row), "state": "refused", "error": {"code": exc.code, "field": exc.field,
                                                                           "message": exc.message},
                        "upload_peak_bytes": vm(server.proc.pid, "VmHWM") - start_rss, "peak_over_idle_bytes": 0,
                        "within_budget": True, "plan_error": exc.message}
            upload_peak = vm(server.proc.pid, "VmHWM") - start_rss
        warm = submit(server.url, *row.request(ids, 16, 2))          # every code path compiled and warmed
        assert warm["state"] == "succeeded" or (warm.get("error") or {}).get("code") == "over_memory_budget", warm
        path, body = row.request(ids, row.size, row.samples)
        idle = reset_peak(server.proc.pid)
        runs = row.repeats if warm["state"] == "succeeded" else 0     # refused even at 16 px: the refusal is the row
        outcome, peaks, start = warm, [], time.perf_counter()
        for _ in range(runs):            # each run's peak over the idle RSS before the first
            reset_peak(server.proc.pid)
            outcome = submit(server.url, path, body)
            peaks.append(vm(server.proc.pid, "VmHWM") - idle)
        seconds = (time.perf_counter() - start) / max(runs, 1)
        peak = max(peaks, default=0)
    finally:
        server.kill()
    result = {**row_fields(row), **outcome,
              "seconds": round(seconds, 1), "upload_peak_bytes": upload_peak, "idle_rss_bytes": idle,
              "peak_over_idle_bytes": peak, "within_budget": peak <= row.budget}
    if len(peaks) > 1:
        result["peaks_bytes"] = peaks
    try:
        result.update(plan_of(row, data_dir, ids, path, body))
        result["ratio"] = round(peak / result["estimate_bytes"], 3)
        result["within_estimate"] = peak <= result["estimate_bytes"]
    except ServiceError as exc:  # refused once projected: the row's result is that refusal
        result["plan_error"] = exc.message
    return result


SWEEP = [
    Row("issue 25: 1 candidate 400x400 N=256, 300 splats", "rank", ["3dgs-300-attack"], 400, 256),
    Row("issue 25, 10 times in one server: 400x400 N=256, 300 splats", "rank", ["3dgs-300-attack"], 400, 256,
        repeats=10),
    Row("attack: 1 candidate 800x800 N=256, 300 splats", "rank", ["3dgs-300-attack"], 800, 256),
    Row("3dgs 300 100 N=4", "rank", ["3dgs-300-attack"], 100, 4),
    Row("3dgs 1k large 800 N=32", "rank", ["3dgs-1k-large"], 800, 32),
    Row("3dgs 50k small 800 N=64", "rank", ["3dgs-50k-small"], 800, 64),
    Row("3dgs 50k large 200 N=32", "rank", ["3dgs-50k-large"], 200, 32),
    Row("3dgs 50k large 400 N=16", "rank", ["3dgs-50k-large"], 400, 16),
    Row("3dgs 50k large 800 (refused)", "rank", ["3dgs-50k-large"], 800, 16),
    Row("3dgs 300k small 400 N=32", "rank", ["3dgs-300k-small"], 400, 32),
    Row("3dgs 300k small 800 N=256", "rank", ["3dgs-300k-small"], 800, 256),
    Row("3dgs 50k small 32 candidates x400 N=16", "rank", ["3dgs-50k-small"], 400, 16, views=32),
    Row("3dgs 50k small heatmaps=files 8x400", "rank", ["3dgs-50k-small"], 400, 16, views=8,
        body={"heatmaps": "files"}),
    Row("3dgs 50k small heatmaps=base64 4x400", "rank", ["3dgs-50k-small"], 400, 16, views=4,
        body={"heatmaps": "base64"}),
    Row("3dgs 50k small calibrate 8x400", "calibrate", ["3dgs-50k-small"], 400, 8, training=8,
        body={"samples": 8, "step": 0.25}),
    Row("3dgs 50k large calibrate 4x200", "calibrate", ["3dgs-50k-large"], 200, 8, training=4,
        body={"samples": 8, "step": 0.25}),
    Row("3dgs select 50k vs 50k images=both 2x400", "select", ["3dgs-50k-small", "3dgs-50k-small-b"], 400, 16,
        views=2, body={"images": "files", "both_images": True, "rule": "sigma_mean"}),
    Row("3dgs select distance_sigma 2x400", "select", ["3dgs-50k-small", "3dgs-50k-large"], 400, 8, views=2,
        training=8, body={"rule": "distance_sigma"}),
    Row("3dgs select coverage_checked (default) 2x400", "select", ["3dgs-50k-small", "3dgs-50k-large"], 400, 8,
        views=2, training=8),
    Row("3dgs select coverage_checked (default) 50k small vs 50k small 2x200", "select",
        ["3dgs-50k-small", "3dgs-50k-small-b"], 200, 8, views=2, training=4),
    Row("3dgs 50k small visibility_sigma 4 candidates x400, 8 captured", "rank", ["3dgs-50k-small"], 400, 16,
        views=4, training=8, body={"strategy": "visibility_sigma"}),
    Row("donut 45k 400 N=64 heatmaps=base64 2x", "rank", ["3dgs-45k-donut"], 400, 64, views=2,
        body={"heatmaps": "base64"}),
    Row("donut 45k 800 N=128", "rank", ["3dgs-45k-donut"], 800, 128),
    Row("donut 45k calibrate 4x400", "calibrate", ["3dgs-45k-donut"], 400, 8, training=4,
        body={"samples": 8, "step": 0.25}),
    Row("donut 45k select vs 50k small images=base64 2x400", "select", ["3dgs-45k-donut", "3dgs-50k-small"], 400, 16,
        views=2, body={"images": "base64", "rule": "sigma_mean"}),
    Row("1M splats (22 donuts) 400 N=16", "rank", ["3dgs-1m-donuts"], 400, 16),
    Row("1M splats (22 donuts) 800 N=64 heatmaps=files", "rank", ["3dgs-1m-donuts"], 800, 64,
        body={"heatmaps": "files"}),
    Row("1M splats (22 donuts) 400 N=16 strategy=sigma_max", "rank", ["3dgs-1m-donuts"], 400, 16,
        body={"strategy": "sigma_max"}),
    Row("1M splats (22 donuts) calibrate 2x200", "calibrate", ["3dgs-1m-donuts"], 200, 4, training=2,
        body={"samples": 4, "step": 0.25}),
    Row("3M splats SH-3 (66 donuts) 200x150 N=16", "rank", ["3dgs-3m-donuts-sh3"], 200, 16, donut_ring=True),
    Row("3M splats SH-3 (66 donuts) 200x150 N=16 strategy=sigma_max", "rank", ["3dgs-3m-donuts-sh3"], 200, 16,
        body={"strategy": "sigma_max"}, donut_ring=True),
    Row("3M splats SH-3 (66 donuts) calibrate 4x200x150", "calibrate", ["3dgs-3m-donuts-sh3"], 200, 8, training=4,
        body={"samples": 8, "step": 0.25}, donut_ring=True),
    Row("2dgs 1k large 400 N=32", "rank", ["2dgs-1k-large"], 400, 32),
    Row("2dgs 50k small 400 N=32", "rank", ["2dgs-50k-small"], 400, 32),
    Row("2dgs 50k large 300 N=16", "rank", ["2dgs-50k-large"], 300, 16),
    Row("2dgs 50k small 8 candidates x200 N=8", "rank", ["2dgs-50k-small"], 200, 8, views=8),
    Row("2dgs 50k small calibrate 4x200", "calibrate", ["2dgs-50k-small"], 200, 8, training=4,
        body={"samples": 8, "step": 0.25}),
    Row("nerf pe 100 N=16", "rank", ["nerf-pe"], 100, 16),
    Row("nerf pe 200 N=256", "rank", ["nerf-pe"], 200, 256),
    Row("nerf hash 100 N=16", "rank", ["nerf-hash"], 100, 16),
    Row("nerf pe 4 candidates x100 N=8", "rank", ["nerf-pe"], 100, 8, views=4),
    Row("nerf pe heatmaps=files 2x100", "rank", ["nerf-pe"], 100, 8, views=2, body={"heatmaps": "files"}),
    Row("nerf pe calibrate 2x100", "calibrate", ["nerf-pe"], 100, 8, training=2, body={"samples": 8, "step": 0.25}),
]


# ----------------------------------------------------------------------------- concurrent

@dataclass
class Crowd:
    """Requests and uploads sent to one server at once."""

    name: str
    workers: int
    requests: list[Row]
    uploads: list[str] = field(default_factory=list)


CROWDS = [
    Crowd("concurrent: 6 jobs on 4 models + 2 uploads, 2 workers, cache 4", 2,
          [Row("", "rank", ["3dgs-300k-small"], 800, 64), Row("", "rank", ["3dgs-50k-large"], 200, 32),
           Row("", "rank", ["2dgs-50k-small"], 300, 16), Row("", "rank", ["nerf-pe"], 100, 16),
           Row("", "select", ["3dgs-300k-small", "3dgs-50k-large"], 200, 16,
               body={"images": "base64", "rule": "sigma_mean"}),
           Row("", "calibrate", ["3dgs-50k-large"], 150, 8, training=2, body={"samples": 8, "step": 0.25})],
          ["3dgs-50k-small", "2dgs-50k-large"]),
    Crowd("concurrent: 4 jobs on 4 workers (issue 25 400x400 N=256, donut heat maps, 2dgs, nerf)", 4,
          [Row("", "rank", ["3dgs-300-attack"], 400, 256),
           Row("", "rank", ["3dgs-45k-donut"], 400, 64, views=2, body={"heatmaps": "base64"}),
           Row("", "rank", ["2dgs-50k-small"], 300, 16), Row("", "rank", ["nerf-pe"], 200, 64)]),
]


def concurrent(root: Path, budget: int, crowd: Crowd) -> dict:
    """A crowd's jobs and uploads at once under one small budget and a cache of 4 models."""
    data_dir = Path(tempfile.mkdtemp(dir=root))
    server = serve(data_dir, PHD_MEMORY_BUDGET_BYTES=str(budget), PHD_WORKERS=str(crowd.workers),
                        PHD_CACHE_SIZE="4", PHD_QUEUE_SIZE="32")
    names = sorted({name for row in crowd.requests for name in row.models})
    try:
        with PHDClient(server.url, timeout=600) as phd:      # warm every route up on a tiny model
            tiny = phd.upload_model(model_file(root, "3dgs-300-attack"), cameras=svc_cameras(2, size=16)).id
            for route in ("rank", "select", "calibrate"):
                row = Row("warm", route, ["3dgs-300-attack"], 16, 2, training=2,
                          body={"step": 0.5} if route == "calibrate" else {})
                assert submit(server.url, *row.request([tiny], 16, 2))["state"] == "succeeded"
            phd.delete_model(tiny)
            idle = reset_peak(server.proc.pid)
            start = time.perf_counter()
            ids = {name: phd.upload_model(model_file(root, name), cameras=svc_cameras(4, size=16)).id
                   for name in names}
        outcomes: list[dict] = []

        def run(row: Row) -> None:
            outcomes.append(submit(server.url, *row.request([ids[n] for n in row.models], row.size, row.samples)))

        def upload(name: str) -> None:
            with PHDClient(server.url, timeout=600) as phd:
                try:
                    phd.upload_model(model_file(root, name))
                    outcomes.append({"state": "uploaded"})
                except Exception as exc:       # a 429 when the budget stays taken: a result, not a failure
                    outcomes.append({"state": "upload refused", "error": str(exc)})

        threads = [threading.Thread(target=run, args=(row,)) for row in crowd.requests]
        threads += [threading.Thread(target=upload, args=(name,)) for name in crowd.uploads]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        seconds = time.perf_counter() - start
        peak = vm(server.proc.pid, "VmHWM") - idle
    finally:
        server.kill()
    states: dict[str, int] = {}
    for outcome in outcomes:
        states[outcome["state"]] = states.get(outcome["state"], 0) + 1
    return {"name": f"{crowd.name} [{budget / GIB:g} GiB]", "budget_bytes": budget, "states": states,
            "outcomes": outcomes, "seconds": round(seconds, 1), "idle_rss_bytes": idle,
            "peak_over_idle_bytes": peak, "within_budget": peak <= budget}


# ----------------------------------------------------------------------------- replan

def at_budgets(budgets: list[float]) -> list[Row]:
    """Every SWEEP row at each budget (GiB), named with it as the results name it."""
    return [replace(row, name=f"{row.name} [{budget:g} GiB]", budget=int(budget * GIB))
            for budget in budgets for row in SWEEP]



def replan(rows: dict[str, dict], root: Path) -> list[dict]:
    """Every accepted row of the results planned again by today's code, without running it:
    its recorded peak against the plan it would get now (a plan change shows which rows to
    measure again). One server at 4 GiB holds the uploads; each model is uploaded once per
    set of training cameras."""
    data_dir = root / "replan"
    data_dir.mkdir()
    server = serve(data_dir, PHD_MEMORY_BUDGET_BYTES=str(4 * GIB))
    uploaded: dict[tuple, str] = {}
    out = []
    try:
        with PHDClient(server.url, timeout=1800) as phd:
            for row in at_budgets([1, 4]):
                recorded = rows.get(row.name, {})
                if recorded.get("state") != "succeeded" or "estimate_bytes" not in recorded:
                    continue
                ids = []
                for name in row.models:
                    key = (name, row.training, row.size, row.donut_ring)
                    if key not in uploaded:
                        cameras = row.cameras(row.training, row.size, "train") if row.training else None
                        uploaded[key] = phd.upload_model(model_file(root, name), cameras=cameras).id
                    ids.append(uploaded[key])
                plan = plan_of(row, data_dir, ids, *row.request(ids, row.size, row.samples))["estimate_bytes"]
                out.append({"name": row.name, "peak_bytes": recorded["peak_over_idle_bytes"],
                            "plan_then_bytes": recorded["estimate_bytes"], "plan_now_bytes": plan,
                            "ratio_now": round(recorded["peak_over_idle_bytes"] / plan, 3)})
                print(json.dumps(out[-1]), flush=True)
    finally:
        server.kill()
    return out


# ----------------------------------------------------------------------------- report

def table(rows: list[dict]) -> str:
    mib = lambda b: f"{b / 2**20:,.0f}"  # noqa: E731
    lines = ["| request | budget MiB | result | fragments/px (bound) | batch | plan MiB | peak MiB | peak/plan | "
             "peak/budget |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "states" in r:
            result = ", ".join(f"{n}x {s}" for s, n in sorted(r["states"].items()))
        else:
            result = r["state"] if r.get("error") is None else f"{r['state']} {r['error']['code']}"
        estimate = r.get("estimate_bytes")
        if estimate is not None:
            planned, ratio = mib(estimate), f"{r['ratio']:.2f}" + ("" if r["within_estimate"] else " OVER")
        else:      # refused once projected (no plan), or concurrent work (the budget is its bound)
            planned, ratio = ("(budget)", "") if "states" in r else ("(refused)", "")
        peak = mib(r["peak_over_idle_bytes"])
        if "peaks_bytes" in r:
            peak = f"{mib(min(r['peaks_bytes']))}-{peak} ({len(r['peaks_bytes'])} runs)"
        over = r["peak_over_idle_bytes"] / r["budget_bytes"]
        lines.append(f"| {r['name']} | {mib(r['budget_bytes'])} | {result} | "
                     f"{r.get('fragments_per_pixel_bound') or ''} | "
                     f"{r.get('mask_batch', '')} | {planned} | {peak} | {ratio} | "
                     f"{over:.2f}{'' if r['within_budget'] else ' OVER'} |")
    return "\n".join(lines)


COMMAND = "OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python -m bench.bench_memory"


def save(rows: dict[str, dict], out: Path = OUT) -> list[dict]:
    """Write the rows to `out` (after every row: a sweep stopped half way keeps what it measured)."""
    ordered = sorted((r for r in rows.values() if "states" not in r), key=lambda r: r["budget_bytes"])
    ordered += [r for r in rows.values() if "states" in r]
    write_result(out, {"machine": machine(), "command": COMMAND, "rows": ordered})
    return ordered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="rows whose name contains one of these ('concurrent': the crowds)")
    parser.add_argument("--budgets", nargs="*", type=float, default=[1, 4], help="GiB, each row at each")
    parser.add_argument("--concurrent-budget", type=int, default=GIB)
    parser.add_argument("--out", type=Path, default=OUT, help="results file (two runs at once need one each)")
    parser.add_argument("--merge", type=Path, nargs="*", default=[], help="results files whose rows join --out's")
    parser.add_argument("--replan", action="store_true",
                        help="plan every accepted row of --out again with today's code (nothing is run)")
    args = parser.parse_args()
    if args.replan:
        with tempfile.TemporaryDirectory() as tmp:
            planned = replan({r["name"]: r for r in json.loads(args.out.read_text())["rows"]}, Path(tmp))
        mib = lambda b: f"{b / 2**20:,.0f}"  # noqa: E731
        print("| request | peak MiB | plan then MiB | plan now MiB | peak/plan now |\n|---|---|---|---|---|")
        for r in sorted(planned, key=lambda r: -r["ratio_now"]):
            print(f"| {r['name']} | {mib(r['peak_bytes'])} | {mib(r['plan_then_bytes'])} | "
                  f"{mib(r['plan_now_bytes'])} | {r['ratio_now']:.2f} |")
        return
    previous = json.loads(args.out.read_text()) if args.out.exists() and (args.only or args.merge) else {"rows": []}
    rows = {r["name"]: r for r in previous["rows"]}
    rows.update({r["name"]: r for path in args.merge for r in json.loads(path.read_text())["rows"]})
    def chosen(name: str) -> bool:     # --merge alone measures nothing
        return any(word in name for word in args.only) if args.only else not args.merge

    sweep = at_budgets(args.budgets)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for row in sweep:
            if not chosen(row.name):
                continue
            rows[row.name] = measure(row, root)
            save(rows, args.out)
            print(json.dumps({k: v for k, v in rows[row.name].items() if k != "options"}), flush=True)
        for crowd in CROWDS:
            if chosen(crowd.name):
                result = concurrent(root, args.concurrent_budget, crowd)
                rows[result["name"]] = result
                save(rows, args.out)
                print(json.dumps(result), flush=True)
    print(table(save(rows, args.out)))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
