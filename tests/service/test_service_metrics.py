"""GET /metrics (issue 36): Prometheus' text format from the official client library, scraped
from a real server and parsed with that library's parser; counts follow what the service did."""

from __future__ import annotations

import json

import httpx
from prometheus_client import CONTENT_TYPE_LATEST
from prometheus_client.parser import text_string_to_metric_families

from client import PHDClient
from support.fixtures import expect_error, svc_cameras

ADMIN = "admin-key-for-metrics"


def scrape(url: str, key: str | None = ADMIN) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """{(sample name, sorted labels): value} of one scrape."""
    answer = httpx.get(f"{url}/metrics", headers={"Authorization": f"Bearer {key}"} if key else {})
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"] == CONTENT_TYPE_LATEST
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(answer.text) for s in family.samples}


def test_metrics_follow_uploads_jobs_refusals_and_bytes(svc_start, svc_model_files, tmp_path):
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"alice": "alice-key-123"}))
    server = svc_start(api_key=ADMIN, keys_file=keys, workers=2, queue_size=5, memory_budget_bytes=512 << 20)
    start = scrape(server.url)
    assert start[("phd_queue_depth", ())] == 0 and start[("phd_queue_capacity", ())] == 5
    assert start[("phd_memory_budget_bytes", ())] == 512 << 20 and start[("phd_workers", ())] == 2
    assert start[("phd_stored_bytes", (("what", "models"),))] == 0

    with PHDClient(server.url, api_key=ADMIN) as phd:
        ply = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3, size=12))
        phd.upload_model(svc_model_files["ply_b"])
        nerf = phd.upload_model(svc_model_files["nerf"])
        phd.calibrate(ply.id, epsilon=0.5, step=0.5, samples=2)
        for _ in range(2):
            phd.rank(ply.id, svc_cameras(2, size=12, phase=0.5), samples=2, heatmaps="files")
    for _ in range(3):
        expect_error(httpx.get(f"{server.url}/v1/models/nope", headers={"Authorization": f"Bearer {ADMIN}"}),
                     404, "model_not_found")
    expect_error(httpx.get(f"{server.url}/v1/models"), 401, "unauthorized")       # the guard's answers count too
    uncalibrated = {"cameras": [svc_cameras(1)[0].to_frame()], "samples": 2}
    expect_error(httpx.post(f"{server.url}/v1/models/{nerf.id}/rank", json=uncalibrated,
                            headers={"Authorization": f"Bearer {ADMIN}"}), 409, "not_calibrated")

    m = scrape(server.url)
    assert m[("phd_uploads_total", (("family", "3dgs"),))] == 2 and m[("phd_uploads_total", (("family", "nerf"),))] == 1
    assert m[("phd_models", (("family", "3dgs"),))] == 2 and m[("phd_models", (("family", "nerf"),))] == 1
    assert m[("phd_jobs_finished_total", (("kind", "rank"), ("state", "succeeded")))] == 2
    assert m[("phd_jobs_finished_total", (("kind", "calibrate"), ("state", "succeeded")))] == 1
    assert m[("phd_jobs", (("kind", "rank"), ("state", "succeeded")))] == 2
    assert m[("phd_job_duration_seconds_count", (("kind", "rank"),))] == 2
    assert m[("phd_job_duration_seconds_bucket", (("kind", "rank"), ("le", "+Inf")))] == 2
    assert m[("phd_job_duration_seconds_sum", (("kind", "rank"),))] > 0
    assert m[("phd_job_wait_seconds_count", (("kind", "calibrate"),))] == 1
    assert m[("phd_error_answers_total", (("code", "model_not_found"), ("status", "404")))] == 3
    assert m[("phd_error_answers_total", (("code", "unauthorized"), ("status", "401")))] == 1
    assert m[("phd_error_answers_total", (("code", "not_calibrated"), ("status", "409")))] == 1
    data = server.settings.data_dir
    assert m[("phd_stored_bytes", (("what", "models"),))] == sum(
        p.stat().st_size for p in (data / "models").rglob("*") if p.is_file())
    assert m[("phd_stored_bytes", (("what", "jobs"),))] == sum(
        p.stat().st_size for p in (data / "jobs").rglob("*") if p.is_file()) > 0
    assert m[("phd_stored_bytes", (("what", "database"),))] >= (data / "phd.sqlite3").stat().st_size > 0
    # The three models stay in memory (idle, within the cache) and hold part of the budget.
    assert m[("phd_models_in_memory", ())] == 3 and 0 < m[("phd_memory_reserved_bytes", ())] < 512 << 20
    assert m[("phd_queue_depth", ())] == 0 and m[("phd_disk_free_bytes", ())] > 0

    # Behind the admin key: none is 401, a named key 403.
    expect_error(httpx.get(f"{server.url}/metrics"), 401, "unauthorized")
    expect_error(httpx.get(f"{server.url}/metrics", headers={"Authorization": "Bearer alice-key-123"}), 403,
                 "forbidden", "Authorization")


def test_metrics_can_be_switched_off(svc_start):
    server = svc_start(metrics=False)
    expect_error(httpx.get(f"{server.url}/metrics"), 404, "not_found")
