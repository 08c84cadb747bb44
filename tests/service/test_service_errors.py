"""Every error class of the API, each from a request a user could plausibly send, and a
bounded fuzz loop: no 5xx from any malformed request, one error shape everywhere."""

from __future__ import annotations

import json
import math
import pickle
import random
import time

import httpx
import pytest
import torch

from client import (
    AuthenticationError,
    ConflictError,
    InvalidInputError,
    NotFoundError,
    PayloadTooLargeError,
    PHDClient,
    UnsupportedModelError,
)
from support.fixtures import expect_error, svc_cameras


def _leftovers(server) -> list:
    root = server.settings.data_dir
    return list((root / "tmp").iterdir()) + list((root / "models").iterdir())


@pytest.fixture
def svc_small(svc_start, svc_model_files):
    """A server with small caps and one uploaded (uncalibrated) PLY without cameras."""
    server = svc_start(max_upload_bytes=200_000, max_samples=8, max_image_size=32, max_candidates=4,
                       max_json_bytes=100_000)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
    return server, model.id


def _frame(**changes) -> dict:
    frame = svc_cameras(1)[0].to_frame()
    frame.update(changes)
    return frame


def test_not_found_everywhere(svc_small):
    server, model_id = svc_small
    url = server.url
    ok_rank = {"cameras": [_frame()], "dropout_ratio": 0.1, "samples": 2}
    expect_error(httpx.get(f"{url}/v1/models/nope"), 404, "model_not_found")
    expect_error(httpx.delete(f"{url}/v1/models/nope"), 404, "model_not_found")
    expect_error(httpx.post(f"{url}/v1/models/nope/rank", json=ok_rank), 404, "model_not_found")
    expect_error(httpx.post(f"{url}/v1/models/nope/calibrate", json={}), 404, "model_not_found")
    select = {"cameras": [_frame()], "samples": 2, "model_a": model_id, "model_b": "nope", "ratio_a": 0.1,
              "ratio_b": 0.1}
    expect_error(httpx.post(f"{url}/v1/select", json=select), 404, "model_not_found", "model_b")
    expect_error(httpx.get(f"{url}/v1/jobs/nope"), 404, "job_not_found")
    expect_error(httpx.delete(f"{url}/v1/jobs/nope"), 404, "job_not_found")
    expect_error(httpx.get(f"{url}/v1/nothing-here"), 404, "not_found")
    expect_error(httpx.get(f"{url}/v2/models"), 404, "not_found")
    expect_error(httpx.put(f"{url}/v1/models"), 405, "method_not_allowed")
    with PHDClient(url) as phd, pytest.raises(NotFoundError) as exc:
        phd.rank("nope", svc_cameras(1), dropout_ratio=0.1)
    assert exc.value.status == 404 and "nope" in exc.value.message


def test_oversized_uploads_and_bodies_get_413_and_leave_nothing(svc_small, tmp_path):
    server, _ = svc_small
    big = tmp_path / "big.ply"
    big.write_bytes(b"ply\nformat binary_little_endian 1.0\n" + bytes(300_000))
    with PHDClient(server.url) as phd, pytest.raises(PayloadTooLargeError) as exc:
        phd.upload_model(big)
    assert exc.value.status == 413 and exc.value.field == "file"
    # Without a Content-Length (chunked), the running count stops it just the same.
    chunks = iter([b"--b\r\nContent-Disposition: form-data; name=\"file\"; filename=\"x.ply\"\r\n\r\nply\n"]
                  + [bytes(50_000)] * 6 + [b"\r\n--b--\r\n"])
    answer = httpx.post(f"{server.url}/v1/models", content=chunks,
                        headers={"content-type": "multipart/form-data; boundary=b"})
    expect_error(answer, 413, "payload_too_large", "file")
    cameras = [_frame()] * 2000  # a JSON body past max_json_bytes
    expect_error(httpx.post(f"{server.url}/v1/models/x/rank", json={"cameras": cameras}), 413, "payload_too_large")
    assert len(_leftovers(server)) == 1  # only the fixture's model


def test_unknown_content_and_pickles_get_415(svc_small, tmp_path):
    server, _ = svc_small
    marker = tmp_path / "pwned"

    class Exploit:  # unpickling this would create the marker file
        def __reduce__(self):
            return (open, (str(marker), "w"))

    candidates = {
        "model.ckpt": pickle.dumps({"state": Exploit()}),             # a pickle disguised as a checkpoint
        "model.ply": pickle.dumps(Exploit(), protocol=2),             # ... or as a PLY (name is ignored)
        "notes.txt": b"these are not the splats you are looking for",
        "empty.ply": b"",
    }
    torch.save({"w": torch.zeros(3)}, tmp_path / "torch.pt")           # a zip-based torch checkpoint
    candidates["weights.nerf"] = (tmp_path / "torch.pt").read_bytes()
    with PHDClient(server.url) as phd:
        for name, data in candidates.items():
            (tmp_path / name).write_bytes(data)
            with pytest.raises(UnsupportedModelError) as exc:
                phd.upload_model(tmp_path / name)
            assert exc.value.status == 415 and exc.value.code == "unsupported_model" and exc.value.field == "file"
    assert not marker.exists()
    answer = httpx.post(f"{server.url}/v1/models", json={"file": "model.ply"})  # not multipart at all
    expect_error(answer, 415, "unsupported_media_type")
    assert len(_leftovers(server)) == 1


def test_broken_models_and_camera_files_get_422(svc_small, svc_model_files, tmp_path):
    server, _ = svc_small
    data = svc_model_files["ply"].read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:len(data) // 2])
    nan = bytearray(data)
    nan[-4:] = b"\x00\x00\xc0\x7f"  # the last float (rot_3 of the last splat) becomes NaN
    (tmp_path / "nan.ply").write_bytes(bytes(nan))
    nerf = svc_model_files["nerf"].read_bytes()
    (tmp_path / "cut.nerf").write_bytes(nerf[:len(nerf) - 100])
    with PHDClient(server.url) as phd:
        for name, field in (("cut.ply", "ply.vertex"), ("nan.ply", "ply.rot_3"), ("cut.nerf", "model")):
            with pytest.raises(InvalidInputError) as exc:
                phd.upload_model(tmp_path / name)
            assert (exc.value.status, exc.value.field) == (422, field), name
        bad_cameras = [_frame(), _frame(fl_x=-5.0)]
        with pytest.raises(InvalidInputError) as exc:
            phd.upload_model(svc_model_files["ply"], cameras=bad_cameras)
        assert exc.value.field == "cameras[1].fl_x"
    files = {"file": ("m.ply", data), "cameras": (None, "{not json")}
    expect_error(httpx.post(f"{server.url}/v1/models", files=files), 422, "invalid_input", "cameras")
    files = {"file": ("m.ply", data), "extra": (None, "1")}
    expect_error(httpx.post(f"{server.url}/v1/models", files=files), 422, "invalid_input", "extra")
    expect_error(httpx.post(f"{server.url}/v1/models", files={"cameras": (None, "[]")}), 422, "invalid_input", "file")
    assert len(_leftovers(server)) == 1


def test_invalid_cameras_and_parameters_get_422(svc_small):
    server, model_id = svc_small
    rank = f"{server.url}/v1/models/{model_id}/rank"
    rotation = _frame()["transform_matrix"]
    skewed = [row[:] for row in rotation]
    skewed[0][0] += 0.5
    cases = [  # (body changes, field)
        ({"cameras": [_frame(transform_matrix=[[math.nan] * 4] * 4)]}, "cameras[0].transform_matrix"),
        ({"cameras": [_frame(transform_matrix=skewed)]}, "cameras[0].transform_matrix"),
        ({"cameras": [_frame(), _frame(fl_x=0)]}, "cameras[1].fl_x"),
        ({"cameras": [_frame(w=100_000, h=100_000)]}, "cameras[0].w"),
        ({"cameras": [_frame(w=64, h=64, fl_x=50.0, fl_y=50.0, cx=32, cy=32)]}, "cameras[0]"),  # > 32 px cap
        ({"cameras": [_frame()] * 5}, "cameras"),                                          # > 4 candidates
        ({"cameras": []}, "cameras"),
        ({"cameras": [{"fl_x": 10, "w": 8, "h": 8}]}, "cameras[0].transform_matrix"),
        ({"cameras": {"camera_angle_x": 0.7, "frames": [{"transform_matrix": rotation}]}}, "cameras[0].w"),
        ({"samples": 9}, "samples"),
        ({"samples": 1}, "samples"),
        ({"samples": "many"}, "samples"),
        ({"dropout_ratio": 1.0}, "dropout_ratio"),
        ({"dropout_ratio": -0.1}, "dropout_ratio"),
        ({"top_k": 0}, "top_k"),
        ({"downscale": 0}, "downscale"),
        ({"width": 16}, "height"),
        ({"seed": -1}, "seed"),
        ({"heatmaps": "jpeg"}, "heatmaps"),
        ({"strategy": "sharpest"}, "strategy"),
        ({"strategy": 3}, "strategy"),
        ({"signal": "straight"}, "signal"),
        ({"captured": [_frame(fl_x=-1)]}, "captured[0].fl_x"),
        ({"sample": 4}, "sample"),                                                         # a typo
    ]
    for changes, field in cases:
        body = {"cameras": [_frame()], "dropout_ratio": 0.1, "samples": 2, **changes}
        expect_error(httpx.post(rank, content=json.dumps(body), headers={"content-type": "application/json"}),
               422, "invalid_input", field)
    expect_error(httpx.post(rank, content=b'{"cameras": [', headers={"content-type": "application/json"}),
           400, "invalid_json")
    expect_error(httpx.post(rank), 422, "invalid_input")  # no body
    calibrate = f"{server.url}/v1/models/{model_id}/calibrate"
    expect_error(httpx.post(calibrate, json={"epsilon": 0}), 422, "invalid_input", "epsilon")
    expect_error(httpx.post(calibrate, json={"method": "ssim"}), 422, "invalid_input", "method")
    expect_error(httpx.post(calibrate, json={"signal": "straight"}), 422, "invalid_input", "signal")
    # r_drop = 0 (epsilon too small for this model) is a clear 422, not a crash.
    error = expect_error(httpx.post(calibrate, json={"epsilon": 1e-9, "step": 0.5, "samples": 2,
                                               "training_cameras": [_frame()]}), 422, "calibration_failed", "epsilon")
    assert "r_drop = 0" in error["message"]


def test_missing_calibration_or_cameras_is_409(svc_small):
    server, model_id = svc_small
    with PHDClient(server.url) as phd:
        with pytest.raises(ConflictError) as exc:
            phd.rank(model_id, svc_cameras(2), samples=2)
        assert (exc.value.status, exc.value.code, exc.value.field) == (409, "not_calibrated", "dropout_ratio")
        with pytest.raises(ConflictError) as exc:
            phd.calibrate(model_id)
        assert (exc.value.code, exc.value.field) == ("no_training_cameras", "training_cameras")
        with pytest.raises(ConflictError) as exc:
            phd.select(model_id, model_id, svc_cameras(1), samples=2, ratio_b=0.1)
        assert exc.value.field == "ratio_a"


def test_api_key_on(svc_start, svc_model_files):
    server = svc_start(api_key="s3cret")
    url = server.url
    assert httpx.get(f"{url}/health").status_code == 200  # liveness never needs the key
    assert httpx.get(f"{url}/health").json()["key_required"] is True      # and says one is needed elsewhere
    schema = httpx.get(f"{url}/openapi.json").json()  # nor do the API docs (they hold no data)
    assert {"/v1/models", "/v1/models/{model_id}/rank", "/v1/select", "/v1/jobs/{job_id}"} <= set(schema["paths"])
    assert httpx.get(f"{url}/docs").status_code == 200
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "s3cret"},
                    {"Authorization": "Basic s3cret"}):
        answer = httpx.get(f"{url}/v1/models", headers=headers)
        expect_error(answer, 401, "unauthorized", "Authorization")
        assert answer.headers["www-authenticate"] == "Bearer"
    expect_error(httpx.post(f"{url}/v1/models", files={"file": ("m.ply", b"ply\n")}), 401, "unauthorized")
    expect_error(httpx.get(f"{url}/v1/nothing-here"), 401, "unauthorized")  # no probing of routes either
    assert httpx.get(f"{url}/v1/models", headers={"Authorization": "Bearer s3cret"}).json() == {"models": []}
    with PHDClient(url) as anonymous, pytest.raises(AuthenticationError) as exc:
        anonymous.list_models()
    assert exc.value.status == 401
    with PHDClient(url, api_key="s3cret") as phd:
        model = phd.upload_model(svc_model_files["ply"])
        assert phd.rank(model.id, svc_cameras(2), samples=2, dropout_ratio=0.1).num_candidates == 2


def test_api_key_off(svc_start):
    server = svc_start()
    assert httpx.get(f"{server.url}/v1/models").json() == {"models": []}
    assert httpx.get(f"{server.url}/v1/models", headers={"Authorization": "Bearer anything"}).status_code == 200


def _mutate(value, rng: random.Random):
    """A random mutation of a JSON value: replaced, dropped into, or left alone."""
    weird = [None, True, -1, 0, 2**70, 1e308, -1e-308, math.nan, math.inf, "", "x" * 50, [], {}, [[1, 2]], {"a": 1},
             [None] * 3, "NaN", 0.5]
    if isinstance(value, dict) and value and rng.random() < 0.7:
        out = dict(value)
        key = rng.choice(list(out))
        choice = rng.random()
        if choice < 0.25:
            del out[key]
        elif choice < 0.35:
            out[rng.choice(["async", "extra", "frames", "w", "seed"])] = rng.choice(weird)
        else:
            out[key] = _mutate(out[key], rng)
        return out
    if isinstance(value, list) and value and rng.random() < 0.7:
        out = list(value)
        i = rng.randrange(len(out))
        out[i] = _mutate(out[i], rng)
        if rng.random() < 0.2:
            out.append(rng.choice(weird))
        return out
    return rng.choice(weird)


def test_fuzzed_bodies_never_give_5xx(svc_start, svc_model_files):
    # Every accepted request becomes a job at once (threshold 1 pixel), so the loop never waits
    # for rendering; the jobs' own outcomes are checked at the end.
    server = svc_start(async_threshold=1, workers=1, queue_size=3, max_samples=8, max_image_size=32,
                       max_candidates=4, max_training_cameras=4)
    with PHDClient(server.url) as phd:
        model_id = phd.upload_model(svc_model_files["ply"]).id
    frames = [c.to_frame() for c in svc_cameras(2, size=8)]
    valid = {
        f"/v1/models/{model_id}/rank": {"cameras": frames, "samples": 2, "dropout_ratio": 0.1, "top_k": 1,
                                       "heatmaps": "base64", "downscale": 2, "seed": 1},
        f"/v1/models/{model_id}/calibrate": {"training_cameras": frames, "samples": 2, "step": 0.5,
                                            "epsilon": 0.9, "method": "bisection"},
        "/v1/select": {"model_a": model_id, "model_b": model_id, "cameras": frames, "samples": 2,
                       "ratio_a": 0.1, "ratio_b": 0.2, "images": "base64", "width": 8, "height": 8},
        "/v1/models": None,
    }
    rng = random.Random(1234)
    statuses: dict[int, int] = {}
    jobs = []
    deadline = time.monotonic() + 20
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for i in range(200):
            if time.monotonic() > deadline:
                break
            path = rng.choice(list(valid))
            if valid[path] is None:  # uploads: random bytes, sometimes with a PLY or safetensors head
                head = rng.choice([b"", b"ply\n", b"ply\nformat ascii 1.0\nelement vertex 2\n",
                                   b"\x08" + bytes(7) + b"{"])
                body = head + rng.randbytes(rng.randrange(0, 300))
                files = {"file": ("m", body)}
                if rng.random() < 0.5:
                    files["cameras"] = (None, json.dumps(_mutate(frames, rng), allow_nan=True))
                answer = http.post(path, files=files)
            elif rng.random() < 0.1:  # not even JSON
                answer = http.post(path, content=rng.randbytes(rng.randrange(1, 200)),
                                   headers={"content-type": rng.choice(["application/json", "text/plain"])})
            else:
                body = _mutate(valid[path], rng) if rng.random() < 0.9 else valid[path]
                answer = http.post(path, content=json.dumps(body, allow_nan=True),
                                   headers={"content-type": "application/json"})
            statuses[answer.status_code] = statuses.get(answer.status_code, 0) + 1
            assert answer.status_code < 500, (path, answer.text)
            if answer.status_code >= 400:
                expect_error(answer, answer.status_code)
            elif answer.status_code == 202:
                jobs.append(answer.json()["id"])
        for job_id in jobs:  # accepted work must never have crashed either
            http.delete(f"/v1/jobs/{job_id}")
            job = http.get(f"/v1/jobs/{job_id}").json()
            assert job["state"] != "failed" or job["error"]["code"] != "internal_error", job
    assert sum(statuses.values()) >= 100
    assert {202, 422} <= set(statuses) and len(jobs) > 0  # both kinds were exercised
    assert len(_leftovers(server)) == 1


def test_settings_come_from_phd_environment_variables(monkeypatch, capsys):
    from phd_cli import main
    from service.settings import Settings

    monkeypatch.setenv("PHD_QUEUE_SIZE", "3")
    monkeypatch.setenv("PHD_API_KEY", "")
    assert (Settings().queue_size, Settings().api_key) == (3, None)
    assert Settings.from_env(queue_size=5, workers=None).queue_size == 5     # a given flag wins
    monkeypatch.setenv("PHD_WORKERS", "many")
    assert main(["serve", "--port", "0"]) == 2                               # refused before serving
    err = capsys.readouterr().err
    assert "workers:" in err and "PHD_WORKERS" in err and "Traceback" not in err
