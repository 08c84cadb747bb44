"""Property test (hypothesis) against the real server: a mutated request for any route never
gets a 5xx, and never costs the client its keep-alive connection. bench/bench_reliability.py
runs the same generator for 10,000 requests (docs/reliability.md)."""

from __future__ import annotations

import random

import httpx
from hypothesis import HealthCheck, given, settings, strategies as st

from client import PHDClient
from conftest import svc_cameras
from support.fuzz import mutated_request, send

EXAMPLES = 300


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
    client = httpx.Client(base_url=server.url, timeout=60)
    seen: set[int] = set()

    @settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(st.randoms(use_true_random=False))
    def prop(rng: random.Random) -> None:
        request = mutated_request(rng, ids, ply)
        response = send(client, request)
        seen.add(response.status_code)
        assert response.status_code < 500, (request, response.text)
        assert response.headers.get("connection") != "close", (request, response.text)

    try:
        prop()
        assert len(client._transport._pool.connections) == 1      # one connection carried every request
    finally:
        client.close()
    assert {404, 422} <= seen and seen & {200, 201, 202}          # the mutations reached every kind of answer
