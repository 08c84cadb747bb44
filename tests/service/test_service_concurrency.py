"""Concurrency: 8 clients ranking at once all succeed (with the library's numbers); a
full work queue answers 429 with Retry-After at once instead of hanging."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from client import PHDClient, QueueFullError
from phd_core import uq
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from support.fixtures import svc_cameras


def test_eight_clients_rank_at_once(svc_start, svc_model_files):
    server = svc_start(workers=2, queue_size=8)
    cameras = svc_cameras(2, size=12)
    expected = uq.rank_views(GaussianRenderer(read_ply(svc_model_files["ply"])), cameras, ratio=0.2,
                             samples=4, seed=7)
    with PHDClient(server.url) as phd:
        model_id = phd.upload_model(svc_model_files["ply"]).id
    barrier = threading.Barrier(8)

    def one_client(_: int):
        with PHDClient(server.url) as phd:
            barrier.wait()
            return phd.rank(model_id, cameras, samples=4, seed=7, dropout_ratio=0.2)

    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(one_client, range(8)))
    for result in results:
        assert [v.index for v in result.views] == [r.index for r in expected]
        assert [v.sigma_max for v in result.views] == pytest.approx([r.sigma_max for r in expected], rel=1e-6)


def test_full_queue_answers_429_with_retry_after(svc_start, svc_model_files):
    server = svc_start(workers=1, queue_size=1, retry_after=7, max_candidates=2000)
    slow = svc_cameras(600, size=32)
    with PHDClient(server.url) as phd:
        model_id = phd.upload_model(svc_model_files["ply"]).id
        running = phd.rank(model_id, slow, samples=16, dropout_ratio=0.2, run_async=True, wait=False)
        deadline = time.monotonic() + 30
        while phd.get_job(running.id).state != "running":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        queued = phd.rank(model_id, slow, samples=16, dropout_ratio=0.2, run_async=True, wait=False)
        assert queued.state == "queued"

        small = {"cameras": [svc_cameras(1, size=8)[0].to_frame()], "samples": 2, "dropout_ratio": 0.2}
        started = time.monotonic()
        answer = httpx.post(f"{server.url}/v1/models/{model_id}/rank", json=small, timeout=30)
        assert time.monotonic() - started < 5  # refused at once, not after the queue drains
        assert answer.status_code == 429 and answer.headers["retry-after"] == "7"
        assert answer.json()["error"]["code"] == "queue_full"
        with pytest.raises(QueueFullError) as exc:
            phd.rank(model_id, svc_cameras(1, size=8), samples=2, dropout_ratio=0.2)
        assert (exc.value.status, exc.value.retry_after) == (429, 7.0)

        phd.cancel_job(queued.id)
        phd.cancel_job(running.id)
        while phd.get_job(running.id).state == "running":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert httpx.post(f"{server.url}/v1/models/{model_id}/rank", json=small, timeout=30).status_code == 200
