"""Memory through a real uvicorn server and the real client: models in memory hold their bytes
in the same budget as jobs and are evicted for a job that needs the room; a model the budget
cannot hold and a view whose fragments it cannot hold are 413s naming the field to lower; the
same request run again and again in one server peaks the same each time, within its plan."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
import torch

from client import PHDClient
from phd_core.renderers.gs3d import GaussianModel, write_ply
from service.budget import MemoryLedger, model_bytes
from service.schemas import RankRequest
from service.settings import Settings
from service.store import ModelStore
from service.work import model_loader, rank_job
from support.fixtures import SvcProcess, expect_error, proc_bytes, svc_cameras


def rank(server, model_id: str, **body) -> httpx.Response:
    """A rank by the paper's rule: these tests are about the dropout renders' memory (the
    visibility strategies' own terms: tests/service/test_budget.py)."""
    frames = [c.to_frame() for c in svc_cameras(1)]
    return httpx.post(f"{server.url}/v1/models/{model_id}/rank", timeout=120,
                      json={"cameras": frames, "samples": 2, "dropout_ratio": 0.1, "strategy": "sigma_max", **body})


def test_a_job_evicts_idle_models_for_its_room_instead_of_exceeding_the_budget(svc_start, svc_model_files):
    files = svc_model_files["ply"], svc_model_files["ply_b"]
    # Room for both models in memory and not much more: a job must make room by evicting.
    budget = sum(model_bytes(f.stat().st_size) for f in files) + 200_000
    server = svc_start(memory_budget_bytes=budget)
    ledger = server.app.state.service.ledger
    with PHDClient(server.url) as phd:
        a, b = (phd.upload_model(f).id for f in files)
    assert ledger.loaded() == [a, b]                     # both kept in memory after their upload
    response = rank(server, b)
    assert response.status_code == 200, response.text
    assert ledger.loaded() == [b] and ledger.used <= budget     # the idle model a made the room
    response = rank(server, a)                           # a is loaded again, b goes
    assert response.status_code == 200, response.text
    assert ledger.loaded() == [a] and ledger.used <= budget


def test_a_model_the_budget_cannot_load_is_413_naming_it(svc_start, svc_model_files, tmp_path):
    first = svc_start(data_dir=tmp_path / "data")
    with PHDClient(first.url) as phd:
        model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
    first.stop()
    server = svc_start(data_dir=tmp_path / "data", memory_budget_bytes=1 << 20)   # restarted with less memory
    expect_error(rank(server, model.id), 413, "over_memory_budget", "model_id")
    select = {"model_a": model.id, "model_b": model.id, "cameras": [svc_cameras(1)[0].to_frame()],
              "ratio_a": 0.1, "ratio_b": 0.1, "rule": "sigma_mean"}
    expect_error(httpx.post(f"{server.url}/v1/select", json=select), 413, "over_memory_budget", "model_a")
    assert server.app.state.service.ledger.used == 0


def test_a_view_whose_fragments_exceed_the_budget_is_413_once_the_model_is_projected(svc_start, tmp_path):
    # 2,000 large splats: every pixel is covered by hundreds, which only a projection tells.
    g = torch.Generator().manual_seed(0)
    count = 2000
    write_ply(GaussianModel(means=(torch.rand(count, 3, generator=g) - 0.5) * 1.2,
                            log_scales=torch.full((count, 3), -1.2), quats=torch.randn(count, 4, generator=g),
                            opacity_logits=torch.zeros(count), sh=torch.randn(count, 4, 3, generator=g) * 0.5),
              tmp_path / "dense.ply")
    server = svc_start(memory_budget_bytes=64 << 20)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(tmp_path / "dense.ply")
    frame = svc_cameras(1, size=200)[0].to_frame()
    error = expect_error(rank(server, model.id, cameras=[frame]), 413, "over_memory_budget", "downscale")
    assert "MiB" in error["message"]
    response = rank(server, model.id, cameras=[frame], downscale=8)           # 25x25 fits
    assert response.status_code == 200, response.text
    assert server.app.state.service.ledger.used <= 64 << 20


def test_a_finished_job_keeps_its_result_and_images_on_disk_not_in_memory(svc_start, svc_model_files):
    server = svc_start()
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
        job = phd.rank(model.id, svc_cameras(2), samples=2, dropout_ratio=0.1, heatmaps="files", run_async=True,
                       wait=False)
        phd.wait_job(job.id, timeout=60)
        live = server.app.state.service.jobs.get(job.id)
        assert live.on_disk and live.result is None and live.artifacts == {}
        served = phd.get_job(job.id)                   # answered from the job store
        assert served.state == "succeeded" and len(served.result.views) == 2
        assert sorted(served.artifacts) == sorted([f"heatmap_{i:04d}.png" for i in range(2)]
                                                  + [f"render_{i:04d}.png" for i in range(2)])
        assert phd.download(served.result.views[0].heatmap_url).startswith(b"\x89PNG")


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc peak-RSS reset")
def test_the_same_request_peaks_the_same_each_time_within_its_plan(svc_model_files, tmp_path):
    # A separate `phd serve`, so its peak RSS (VmHWM, restarted before each run) is the service's
    # alone. Under a 256 MiB budget the rank takes batches of 64 masks of 200x200 (~150 MiB
    # of float64 terms at once): with freed batches kept in the heap it went past its plan and
    # grew with the server's age; each run now frees what it took and peaks within its plan.
    budget = 256 << 20
    server = SvcProcess(tmp_path / "data", PHD_MEMORY_BUDGET_BYTES=str(budget), OMP_NUM_THREADS="1")
    try:
        with PHDClient(server.url) as phd:
            model = phd.upload_model(svc_model_files["ply"])
        assert rank(server, model.id).status_code == 200                    # every code path warmed up
        body = {"cameras": [svc_cameras(1, size=200)[0].to_frame()], "samples": 64, "strategy": "sigma_max"}
        idle = proc_bytes(server.proc.pid, "VmRSS")
        peaks = []
        for _ in range(5):
            Path(f"/proc/{server.proc.pid}/clear_refs").write_text("5")      # VmHWM starts again from VmRSS
            response = rank(server, model.id, **body)
            assert response.status_code == 200, response.text
            peaks.append(proc_bytes(server.proc.pid, "VmHWM") - idle)
    finally:
        server.kill()
    store = ModelStore(tmp_path / "data")
    record = store.get(model.id)
    settings = Settings(data_dir=tmp_path / "data", memory_budget_bytes=budget)
    ledger = MemoryLedger(budget, 1, model_loader(store))
    work, _ = rank_job(record, RankRequest(**body, dropout_ratio=0.1), settings, lambda name: name, ledger)
    plan = work.plan({model.id: ledger.load(model.id)}, lambda fraction: None)
    assert plan.mask_batch == 64
    assert max(peaks) <= plan.bytes <= budget
    assert min(peaks) >= plan.bytes // 2                     # the runs did the work planned
    assert max(peaks) - min(peaks) <= 8 << 20, peaks         # no run inherits what an earlier one left
