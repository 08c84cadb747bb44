"""Issue 17's reliability suite against a real uvicorn server: the five failures found by the
attack (server file reads via `cameras`, memory beyond the caps, ASCII PLY memory, non-finite
numbers as 500s, jobs lost on restart) as regression tests, plus temp-file names in messages,
slow clients, CORS, security headers and per-key ownership; and issue 25's malformed bodies
(JSON nested past the decoder, multipart boundaries the parser refuses), trickled bodies and
oversized headers."""

from __future__ import annotations

import json
import socket
import threading
import time

import httpx
import pytest

from client import PHDClient
from support.fixtures import SvcProcess, expect_error, svc_cameras


def _frame(**changes) -> dict:
    frame = svc_cameras(1)[0].to_frame()
    frame.update(changes)
    return frame


@pytest.fixture
def svc_up(svc_start, svc_model_files):
    """A server with one PLY uploaded with training cameras: (server, model id)."""
    server = svc_start()
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
    return server, model.id


# ----------------------------------------------------------------------------- 1. no server file reads

@pytest.mark.parametrize("path", ["/etc/hostname", "/nonexistent", "/dev/zero"])
def test_cameras_part_is_never_opened_as_a_server_path(svc_start, svc_model_files, path):
    server = svc_start()
    files = {"file": ("m.ply", svc_model_files["ply"].read_bytes()), "cameras": (None, json.dumps(path))}
    error = expect_error(httpx.post(f"{server.url}/v1/models", files=files, timeout=30), 422, "invalid_input",
                         "cameras")
    assert "Expecting value" not in error["message"] and "No such file" not in error["message"]
    assert "str" in error["message"]                     # refused for its type, before any file is touched
    body = {"cameras": path, "dropout_ratio": 0.1}
    expect_error(httpx.post(f"{server.url}/v1/models/x/rank", json=body), 422, "invalid_input")
    assert not list((server.settings.data_dir / "models").iterdir())


# ----------------------------------------------------------------------------- 2. memory bounded

def test_work_over_the_memory_budget_is_refused_before_it_is_queued(svc_start, svc_model_files):
    server = svc_start(memory_budget_bytes=64 << 20)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
    big = _frame(w=800, h=800, fl_x=900.0, fl_y=900.0, cx=400, cy=400)
    rank = f"{server.url}/v1/models/{model.id}/rank"
    error = expect_error(httpx.post(rank, json={"cameras": [big], "samples": 256, "dropout_ratio": 0.1}),
                   413, "over_memory_budget", "downscale")
    assert "MiB" in error["message"]
    # The same view at 1/8 fits and streams its 256 samples in batches.
    small = httpx.post(rank, json={"cameras": [big], "samples": 256, "dropout_ratio": 0.1, "downscale": 8},
                       timeout=120)
    assert small.status_code == 200, small.text
    assert small.json()["width"] == 100
    many = {"training_cameras": [big] * 40, "epsilon": 0.5, "step": 0.5, "samples": 2}
    expect_error(httpx.post(f"{server.url}/v1/models/{model.id}/calibrate", json=many), 413, "over_memory_budget",
           "training_cameras")
    select = {"model_a": model.id, "model_b": model.id, "cameras": [big], "ratio_a": 0.1, "ratio_b": 0.1,
              "rule": "sigma_mean"}
    expect_error(httpx.post(f"{server.url}/v1/select", json=select), 413, "over_memory_budget", "downscale")


def test_uploads_past_what_the_budget_can_parse_are_cut_off_as_they_stream(svc_start, svc_model_files):
    server = svc_start(memory_budget_bytes=1 << 20)        # parses files up to 256 KiB
    body = svc_model_files["ply"].read_bytes() + b"\0" * 400_000

    def chunks():                                          # no Content-Length: only the stream tells
        for i in range(0, len(body), 65536):
            yield body[i:i + 65536]

    boundary = b"--xyz\r\nContent-Disposition: form-data; name=\"file\"; filename=\"m.ply\"\r\n\r\n"
    stream = [boundary, *chunks(), b"\r\n--xyz--\r\n"]
    response = httpx.post(f"{server.url}/v1/models", content=iter(stream),
                          headers={"content-type": "multipart/form-data; boundary=xyz"}, timeout=30)
    expect_error(response, 413, "payload_too_large", "file")
    assert not list((server.settings.data_dir / "tmp").iterdir())


# ----------------------------------------------------------------------------- 3. ASCII PLY

def test_ascii_ply_upload_gives_the_binary_model(svc_start, svc_model_files, tmp_path):
    import numpy as np

    data = svc_model_files["ply"].read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    names = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    records = np.frombuffer(data[end:], dtype=[(n, "<f4") for n in names])
    rows = "".join(" ".join(f"{records[n][i]:.9g}" for n in names) + "\n" for i in range(len(records)))
    ascii_path = tmp_path / "ascii.ply"
    ascii_path.write_bytes(header.replace("binary_little_endian", "ascii").encode() + rows.encode())
    server = svc_start()
    cams = svc_cameras(2, size=12)
    with PHDClient(server.url) as phd:
        binary = phd.upload_model(svc_model_files["ply"])
        text = phd.upload_model(ascii_path)
        assert text.num_units == binary.num_units == 300
        a = phd.rank(binary.id, cams, samples=3, dropout_ratio=0.2)
        b = phd.rank(text.id, cams, samples=3, dropout_ratio=0.2)
    assert [v.sigma_max for v in a.views] == [v.sigma_max for v in b.views]


# ----------------------------------------------------------------------------- 4. non-finite numbers

NON_FINITE = [("w", "NaN"), ("h", "Infinity"), ("w", "-Infinity"), ("h", "1e309"), ("fl_x", "NaN"),
              ("cx", "1e309"), ("w", "100000000000000000000000000000000000000000")]


def _raw(body: dict, key: str, token: str) -> bytes:
    """The JSON of `body` with its first camera's `key` replaced by a raw token (NaN is not JSON)."""
    body["cameras"][0][key] = "@@"
    return json.dumps(body).replace('"@@"', token).encode()


def test_non_finite_and_overflowing_numbers_are_422_naming_the_field_on_one_connection(svc_up, svc_model_files):
    server, model_id = svc_up
    headers = {"content-type": "application/json"}
    with httpx.Client(base_url=server.url, timeout=30) as client:
        for key, token in NON_FINITE:
            rank = _raw({"cameras": [_frame()], "dropout_ratio": 0.1, "samples": 2}, key, token)
            error = expect_error(client.post(f"/v1/models/{model_id}/rank", content=rank, headers=headers), 422)
            assert error["field"] == f"cameras[0].{key}", (key, token, error)
            select = _raw({"cameras": [_frame()], "model_a": model_id, "model_b": model_id, "ratio_a": 0.1,
                           "ratio_b": 0.1, "samples": 2, "rule": "sigma_mean"}, key, token)
            response = client.post("/v1/select", content=select, headers=headers)
            assert expect_error(response, 422)["field"] == f"cameras[0].{key}"
            calibrate = _raw({"cameras": [_frame()]}, key, token).replace(b'"cameras"', b'"training_cameras"')
            response = client.post(f"/v1/models/{model_id}/calibrate", content=calibrate, headers=headers)
            assert expect_error(response, 422)["field"] == f"training_cameras[0].{key}"
            upload = _raw({"cameras": [_frame()]}, key, token)
            files = {"file": ("m.ply", svc_model_files["ply"].read_bytes()),
                     "cameras": (None, upload[len(b'{"cameras": '):-1])}
            assert expect_error(client.post("/v1/models", files=files), 422)["field"] == f"cameras[0].{key}"
        for downscale in ("1e-320", "5e-324"):
            body = b'{"cameras": [%s], "dropout_ratio": 0.1, "downscale": %s}' % (
                json.dumps(_frame()).encode(), downscale.encode())
            expect_error(client.post(f"/v1/models/{model_id}/rank", content=body, headers=headers), 422,
                   field="downscale")
        blender = {"camera_angle_x": 5e-324, "w": 16, "h": 16, "frames": [{"transform_matrix":
                                                                        _frame()["transform_matrix"]}]}
        tiny_angle = client.post(f"/v1/models/{model_id}/rank", json={"cameras": blender, "dropout_ratio": 0.1})
        expect_error(tiny_angle, 422, field="cameras[0].camera_angle_x")          # found by the 10k fuzz run
        assert client.get("/health").status_code == 200       # still the same live connection
    assert not list((server.settings.data_dir / "tmp").iterdir())


def test_an_unexpected_error_is_a_json_500_that_keeps_the_connection(svc_up, monkeypatch):
    server, model_id = svc_up
    from service.routes import models

    def broken(record):
        raise RuntimeError("a bug")

    monkeypatch.setattr(models, "model_info", broken)
    with httpx.Client(base_url=server.url, timeout=30) as client:
        first = client.get(f"/v1/models/{model_id}")
        expect_error(first, 500, "internal_error")
        assert "a bug" not in first.text and first.headers.get("connection") != "close"
        second = client.get("/health")
        assert second.status_code == 200
        pool = client._transport._pool
        assert len(pool.connections) == 1                       # the same connection served both


def _deep(depth: int, kind: str) -> bytes:
    return b"[" * depth + b"]" * depth if kind == "array" else b'{"a":' * depth + b"1" + b"}" * depth


@pytest.mark.parametrize("kind", ["array", "object"])
def test_json_nested_past_the_decoder_is_invalid_json_or_names_the_cameras_part(svc_up, svc_model_files, kind):
    server, model_id = svc_up
    deep = _deep(100_000, kind)
    headers = {"content-type": "application/json"}
    with httpx.Client(base_url=server.url, timeout=30) as client:
        for body in (deep, b'{"cameras": %s, "dropout_ratio": 0.1}' % deep):       # the body, or one field of it
            response = client.post(f"/v1/models/{model_id}/rank", content=body, headers=headers)
            error = expect_error(response, 400, "invalid_json")
            assert "nested too deeply" in error["message"]
        files = {"file": ("m.ply", svc_model_files["ply"].read_bytes()), "cameras": (None, deep)}
        error = expect_error(client.post("/v1/models", files=files), 422, "invalid_input", "cameras")
        assert "nested too deeply" in error["message"]
        not_utf8 = client.post("/v1/select", content=b'{"model_a": "\xff"}', headers=headers)
        assert "utf-8" in expect_error(not_utf8, 400, "invalid_json")["message"]
        assert client.get("/health").status_code == 200
        assert len(client._transport._pool.connections) == 1
    assert len(list((server.settings.data_dir / "models").iterdir())) == 1      # svc_up's model only


def test_multipart_boundaries_the_parser_refuses_are_400_naming_content_type(svc_start, svc_model_files):
    server = svc_start()
    ply = svc_model_files["ply"].read_bytes()

    def upload(boundary: str, part_headers: bytes = b"") -> httpx.Response:
        body = (f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="m.ply"\r\n'.encode() +
                part_headers + b"\r\n" + ply + f"\r\n--{boundary}--\r\n".encode())
        return httpx.post(f"{server.url}/v1/models", content=body, timeout=30,
                          headers={"content-type": f"multipart/form-data; boundary={boundary}"})

    assert upload("b" * 256).status_code == 201                  # the parser's longest boundary
    error = expect_error(upload("b" * 257), 400, "invalid_multipart", "Content-Type")
    assert "257" in error["message"] and "256" in error["message"]
    expect_error(upload("b" * 5000), 400, "invalid_multipart", "Content-Type")
    expect_error(upload("b", b"Not A Header\r\n"), 400, "invalid_multipart", "file")
    assert not list((server.settings.data_dir / "tmp").iterdir())


# ----------------------------------------------------------------------------- 5. jobs survive a restart

def test_jobs_and_heat_maps_survive_kill_9_and_running_jobs_report_interrupted(tmp_path, svc_model_files):
    data_dir = tmp_path / "data"
    server = SvcProcess(data_dir)
    try:
        with PHDClient(server.url) as phd:
            model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
            done = phd.rank(model.id, svc_cameras(3, size=12), samples=3, dropout_ratio=0.2, heatmaps="files",
                            run_async=True, wait=False)
            result = phd.wait_job(done.id, timeout=60)
            before = phd.get_job(done.id)
            maps = {v.heatmap_url: phd.download(v.heatmap_url) for v in result.views}
            assert len(maps) == 3 and all(png.startswith(b"\x89PNG") for png in maps.values())
            slow = phd.rank(model.id, svc_cameras(400, size=64), samples=64, dropout_ratio=0.2, run_async=True,
                            wait=False)
            deadline = time.monotonic() + 60
            while phd.get_job(slow.id).state != "running":
                assert time.monotonic() < deadline
                time.sleep(0.05)
        server.kill()                                           # SIGKILL while a job runs
    finally:
        server.kill()
    restarted = SvcProcess(data_dir)
    try:
        with PHDClient(restarted.url) as phd:
            assert phd.get_job(done.id) == before
            assert {url: phd.download(url) for url in maps} == maps
            interrupted = phd.get_job(slow.id)
            assert interrupted.state == "failed" and interrupted.error.code == "interrupted"
            assert "restart" in interrupted.error.message
        expect_error(httpx.get(f"{restarted.url}/v1/jobs/0123456789abcdef"), 404, "job_not_found")
        expect_error(httpx.get(f"{restarted.url}/v1/jobs/{done.id}/artifacts/..%2Fphd.sqlite3"), 404)
    finally:
        restarted.kill()


def test_graceful_restart_keeps_finished_jobs(svc_start, svc_model_files):
    first = svc_start()
    with PHDClient(first.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
        job = phd.rank(model.id, svc_cameras(2, size=12), samples=2, dropout_ratio=0.1, run_async=True, wait=False)
        phd.wait_job(job.id, timeout=60)
        before = phd.get_job(job.id)
    first.stop()
    second = svc_start()
    with PHDClient(second.url) as phd:
        assert phd.get_job(job.id) == before
        assert phd.cancel_job(job.id) == before                 # nothing left to cancel


# ----------------------------------------------------------------------------- also

def test_messages_never_name_the_servers_temp_files(svc_start, svc_model_files):
    server = svc_start()
    broken = svc_model_files["ply"].read_bytes()[:-100]
    response = httpx.post(f"{server.url}/v1/models", files={"file": ("mine.ply", broken)})
    error = expect_error(response, 422, "invalid_input")
    assert "upload-" not in error["message"] and ".part" not in error["message"]
    assert "mine.ply" in error["message"]


def _open(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.settimeout(10)
    return sock


def test_slow_headers_and_slow_bodies_are_cut_off(svc_start):
    server = svc_start(header_timeout=0.5, body_timeout=0.5)
    with _open(server.port) as silent, _open(server.port) as trickle:
        trickle.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")   # headers never finished
        time.sleep(1.5)
        assert silent.recv(100) == b"" and trickle.recv(100) == b""  # both closed by the server
    with _open(server.port) as slow_body:
        slow_body.sendall(b"POST /v1/select HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                          b"Content-Length: 1000\r\n\r\n{\"cameras\": ")
        answer = b""
        while b"request_timeout" not in answer and (chunk := slow_body.recv(4096)):
            answer += chunk                                     # headers and body may come apart
        assert answer.startswith(b"HTTP/1.1 408") and b"request_timeout" in answer
    with _open(server.port) as ok:                             # a prompt client is unaffected
        ok.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        assert ok.recv(4096).startswith(b"HTTP/1.1 200")


def _answer(sock: socket.socket) -> bytes:
    """Everything the server sends until it closes or an error body has arrived."""
    answer = b""
    while not answer.endswith(b"}}") and (chunk := sock.recv(4096)):
        answer += chunk
    return answer


def _send_slowly(sock: socket.socket, body: bytes, size: int, every: float) -> threading.Thread:
    """Send `body` in pieces of `size` bytes, one every `every` seconds, from a thread."""
    def run() -> None:
        for i in range(0, len(body), size):
            try:
                sock.sendall(body[i:i + size])
            except OSError:                                     # the server closed the connection
                return
            time.sleep(every)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_trickled_body_is_cut_at_its_rate_deadline_and_a_slow_steady_one_is_not(svc_start):
    server = svc_start(body_timeout=1.0, min_body_rate=100)       # a body may take 1 s + 1 s per 100 bytes
    head = b"POST /v1/select HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n"
    body = json.dumps({"cameras": "x" * 380}).encode()
    with _open(server.port) as trickle:                          # 5 bytes/s, never pausing for 1 s
        trickle.sendall(head % len(body))
        start = time.monotonic()
        _send_slowly(trickle, body, 1, 0.2)
        answer = _answer(trickle)
        assert answer.startswith(b"HTTP/1.1 408") and b"slower than 100 bytes per second" in answer
        assert time.monotonic() - start < 3
    with _open(server.port) as steady:                           # 250 bytes/s: 1.6 s in all, past 1 s
        steady.sendall(head % len(body))
        start = time.monotonic()
        _send_slowly(steady, body, 50, 0.2)
        answer = _answer(steady)
        assert answer.startswith(b"HTTP/1.1 422") and time.monotonic() - start > 1.2, answer


def test_headers_past_64_kib_are_431_naming_the_largest(svc_start):
    server = svc_start()
    assert httpx.get(f"{server.url}/health", headers={"x-big": "a" * 60 * 1024}).status_code == 200
    error = expect_error(httpx.get(f"{server.url}/health", headers={"x-big": "a" * 70 * 1024}), 431,
                         "headers_too_large")
    assert error["field"] == "x-big" and "65536" in error["message"]
    many = {f"x-h{i}": "a" * 1000 for i in range(70)}
    error = expect_error(httpx.get(f"{server.url}/health", headers=many), 431, "headers_too_large")
    assert error["field"].startswith("x-h")
    with _open(server.port) as unfinished:                      # still arriving past the cap: h11 refuses them
        unfinished.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 70 * 1024)
        answer = _answer(unfinished)
        assert answer.startswith(b"HTTP/1.1 431") and b'"code": "headers_too_large"' in answer


def test_cors_is_closed_by_default_and_opens_to_configured_origins(svc_start):
    preflight = {"origin": "https://page.example", "access-control-request-method": "POST",
                 "access-control-request-headers": "authorization,content-type"}
    closed = svc_start()
    response = httpx.options(f"{closed.url}/v1/models", headers=preflight)
    assert "access-control-allow-origin" not in response.headers
    assert "access-control-allow-origin" not in httpx.get(f"{closed.url}/health",
                                                          headers={"origin": "https://page.example"}).headers
    opened = svc_start(cors_origins=["https://page.example"], api_key="k" * 16, data_dir=closed.settings.data_dir
                       .parent / "other")
    response = httpx.options(f"{opened.url}/v1/models", headers=preflight)
    assert response.status_code == 200
    assert response.headers["access-control-allow-origin"] == "https://page.example"
    assert "authorization" in response.headers["access-control-allow-headers"].lower()
    other = httpx.options(f"{opened.url}/v1/models", headers={**preflight, "origin": "https://evil.example"})
    assert "access-control-allow-origin" not in other.headers


def test_security_headers_on_every_answer(svc_start):
    server = svc_start()
    for response in (httpx.get(f"{server.url}/health"), httpx.get(f"{server.url}/v1/models/nope"),
                     httpx.post(f"{server.url}/v1/select", content=b"{", headers={"content-type": "application/json"})):
        assert response.headers["x-content-type-options"] == "nosniff"
        assert response.headers["x-frame-options"] == "DENY"
        assert response.headers["referrer-policy"] == "no-referrer"
        csp = response.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "img-src 'self' blob: data:" in csp and "'unsafe-inline'" not in csp
    assert "content-security-policy" not in httpx.get(f"{server.url}/docs").headers   # its CDN scripts


def test_each_key_sees_and_deletes_only_its_models_and_jobs(svc_start, svc_model_files, tmp_path):
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"alice": "alice-key-123", "bob": "bob-key-4567"}))
    server = svc_start(keys_file=keys, api_key="admin-key-89")
    cams = svc_cameras(2, size=12)
    with PHDClient(server.url, api_key="alice-key-123") as alice, \
            PHDClient(server.url, api_key="bob-key-4567") as bob, \
            PHDClient(server.url, api_key="admin-key-89") as admin:
        mine = alice.upload_model(svc_model_files["ply"], cameras=cams)
        theirs = bob.upload_model(svc_model_files["ply_b"])
        assert [m.id for m in alice.list_models()] == [mine.id]
        assert [m.id for m in bob.list_models()] == [theirs.id]
        assert {m.id for m in admin.list_models()} == {mine.id, theirs.id}
        job = alice.rank(mine.id, cams, samples=2, dropout_ratio=0.1, run_async=True, wait=False)
        alice.wait_job(job.id, timeout=60)
    bob_headers = {"authorization": "Bearer bob-key-4567"}
    for method, path in (("GET", f"/v1/models/{mine.id}"), ("DELETE", f"/v1/models/{mine.id}"),
                         ("GET", f"/v1/jobs/{job.id}"), ("DELETE", f"/v1/jobs/{job.id}")):
        expect_error(httpx.request(method, server.url + path, headers=bob_headers), 404)
    rank = {"cameras": [_frame()], "dropout_ratio": 0.1, "samples": 2}
    expect_error(httpx.post(f"{server.url}/v1/models/{mine.id}/rank", json=rank, headers=bob_headers), 404,
           "model_not_found")
    select = {"model_a": theirs.id, "model_b": mine.id, "cameras": [_frame()], "ratio_a": 0.1, "ratio_b": 0.1,
              "rule": "sigma_mean"}
    expect_error(httpx.post(f"{server.url}/v1/select", json=select, headers=bob_headers), 404, field="model_b")
    expect_error(httpx.get(f"{server.url}/v1/models", headers={"authorization": "Bearer nobody"}), 401)
    admin_headers = {"authorization": "Bearer admin-key-89"}
    assert httpx.get(f"{server.url}/v1/jobs/{job.id}", headers=admin_headers).status_code == 200
    assert httpx.delete(f"{server.url}/v1/models/{mine.id}", headers=admin_headers).status_code == 204
    with PHDClient(server.url, api_key="alice-key-123") as alice:
        assert alice.list_models() == []


@pytest.mark.parametrize("content", ['{"alice": "short"}', '{"a": "same-key-1", "b": "same-key-1"}', "[1]", "{",
                                     '{"admin": "admin-key-1"}'])
def test_a_bad_keys_file_stops_the_service_from_starting(tmp_path, content):
    from phd_core.errors import InputError
    from service.app import create_app
    from service.settings import Settings

    keys = tmp_path / "keys.json"
    keys.write_text(content)
    with pytest.raises(InputError) as exc:
        create_app(Settings(data_dir=tmp_path / "data", keys_file=keys))
    assert exc.value.field == "keys_file"
