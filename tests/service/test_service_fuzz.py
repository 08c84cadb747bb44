"""Property tests (hypothesis) against the real server: a mutated request for any route, a
damaged raw multipart upload and a damaged trainer's folder never get a 5xx, and never cost
the client its keep-alive connection. bench/bench_reliability.py runs the same generators for
10,000 requests and 3,000 folders (docs/reliability.md)."""

from __future__ import annotations

import random
from typing import Callable

import httpx
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client import PHDClient
from support.fixtures import svc_cameras
from support.fuzz import FuzzRequest, mutated_folder, mutated_request, mutated_upload, send, trainer_folders

EXAMPLES = 300
UPLOAD_EXAMPLES = 200
FOLDER_EXAMPLES = 40


def test_mutated_requests_never_give_5xx_nor_drop_the_connection(svc_start, svc_model_files):
    server = svc_start(max_samples=8, max_image_size=32, max_candidates=4, max_training_cameras=4,
                       max_json_bytes=100_000, memory_budget_bytes=256 << 20)
    with PHDClient(server.url) as phd:
        a = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2, size=16))
        b = phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(2, size=16))
        job = phd.rank(a.id, svc_cameras(1, size=16), samples=2, dropout_ratio=0.1, heatmaps="files",
                       run_async=True, wait=False)
        phd.wait_job(job.id, timeout=60)
    ids = {"model": a.id, "model_b": b.id, "job": job.id}
    ply = svc_model_files["ply"].read_bytes()
    seen = _statuses(server.url, lambda rng: mutated_request(rng, ids, ply), EXAMPLES)
    assert {404, 422} <= seen and seen & {200, 201, 202}          # the mutations reached every kind of answer


def test_damaged_multipart_uploads_never_give_5xx_nor_drop_the_connection(svc_start, svc_model_files):
    server = svc_start()
    ply = svc_model_files["ply"].read_bytes()
    seen = _statuses(server.url, lambda rng: mutated_upload(rng, ply), UPLOAD_EXAMPLES)
    assert {201, 400, 415, 422} <= seen       # stored, refused as multipart, as content, and as a field
    assert not list((server.settings.data_dir / "tmp").iterdir())


def test_damaged_folder_uploads_never_give_5xx_nor_drop_the_connection(svc_start, tmp_path):
    server = svc_start(memory_budget_bytes=256 << 20)
    folders = trainer_folders(tmp_path / "runs")
    seen = _statuses(server.url, lambda rng: mutated_folder(rng, folders), FOLDER_EXAMPLES)
    assert {201, 422} <= seen                 # some damage leaves a readable folder, most is refused
    assert not list((server.settings.data_dir / "tmp").iterdir())


def _statuses(url: str, make: Callable[[random.Random], FuzzRequest], examples: int) -> set[int]:
    """Send `examples` requests from `make` over one connection, asserting none is a 5xx or closes it."""
    client = httpx.Client(base_url=url, timeout=60)
    seen: set[int] = set()

    @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(st.randoms(use_true_random=False))
    def prop(rng: random.Random) -> None:
        request = make(rng)
        response = send(client, request)
        seen.add(response.status_code)
        assert response.status_code < 500, (request.method, request.path, response.text)
        assert response.headers.get("connection") != "close", (request.method, request.path, response.text)

    try:
        prop()
        assert len(client._transport._pool.connections) == 1      # one connection carried every request
    finally:
        client.close()
    return seen
