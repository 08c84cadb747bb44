"""The capture loop through a real uvicorn server and the real client (issue 49): photos in
(structure-from-motion), a model trained, the next views out, photos added, trained again
warm, round after round; a photo of something else, bad input, another key's capture, and a
kill -9 mid-training."""

from __future__ import annotations

import json
import time
import zipfile

import httpx
import numpy as np
import pytest

from client import ConflictError, InvalidInputError, JobFailedError, NotFoundError, PHDClient
from support.captures_loop import LoopPhotos, loop_photos
from support.fixtures import SvcProcess

ITERATIONS = 60                     # training steps per round: seconds on these photos


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> LoopPhotos:
    return loop_photos(tmp_path_factory.mktemp("loop"))


def error_of(response: httpx.Response) -> dict:
    return response.json()["error"]


def test_the_loop_round_after_round(svc_start, shots) -> None:
    server = svc_start(capture_max_size=shots.max_size)
    with PHDClient(server.url) as phd:
        capture = phd.create_capture(shots.initial, test=shots.test, name="scene", **shots.sfm)
        info = capture.info
        assert info.state == "ready" and info.name == "scene" and len(info.rounds) == 1
        first = info.rounds[0]
        assert sorted(first.registered) == sorted(first.photos) and len(first.photos) == shots.initial_count
        assert sorted(info.test_photos) == sorted(shots.test) and info.num_photos == shots.initial_count
        assert len(first.captured) == len(first.registered)      # every registered photo's camera, for the page

        trained = capture.train(iterations=ITERATIONS, samples=4)
        summary = trained.summary
        assert trained.round == 0 and summary.warm_from is None and summary.iterations == ITERATIONS
        assert summary.train_views == shots.initial_count - len(shots.test) and summary.test_views == len(shots.test)
        model = phd.get_model(summary.model_id)
        assert model.details["capture_id"] == capture.id and model.has_calibration
        assert model.num_training_cameras == summary.train_views and model.camera_format == "colmap"
        assert model.calibration.r_drop == summary.r_drop > 0
        assert summary.test_psnr is not None and np.isfinite(summary.test_psnr)
        assert summary.sigma_max_bar is not None and summary.sigma_max_bar > 0

        ranked = capture.next_views(2, targets="capture", samples=4)
        assert ranked.model_id == summary.model_id and len(ranked.views) == 2 and ranked.num_targets > 0
        assert capture.info.rounds[0].next == [v.camera for v in ranked.views]

        capture.add_photos(shots.more)
        info = capture.info
        assert len(info.rounds) == 2 and info.num_photos == shots.initial_count + shots.more_count
        added = info.rounds[1]
        assert sorted(added.registered) == sorted(added.photos) and len(added.photos) == shots.more_count
        # The earlier photos keep their poses (registration fixes them): round 0's cameras read back the same.
        assert phd.get_capture(capture.id).info.rounds[0].captured == first.captured

        warm = capture.train(iterations=ITERATIONS, samples=4).summary
        assert warm.warm_from == summary.model_id and warm.train_views == summary.train_views + shots.more_count
        assert capture.info.model_id == warm.model_id and capture.info.rounds[1].train == warm
        assert [c.id for c in phd.list_captures()] == [capture.id]


def test_a_photo_of_something_else_is_named_and_the_capture_is_unchanged(svc_start, shots) -> None:
    server = svc_start(capture_max_size=shots.max_size)
    with PHDClient(server.url) as phd:
        capture = phd.create_capture(shots.initial, **shots.sfm)
        before = capture.info
        with pytest.raises(JobFailedError) as failed:
            capture.add_photos([shots.other])
        assert failed.value.field == "photos" and shots.other.name in failed.value.message
        after = phd.get_capture(capture.id).info
        assert after.state == "ready" and after.rounds == before.rounds and after.num_photos == before.num_photos


def test_bad_requests_are_4xx_naming_the_field(svc_start, shots, tmp_path) -> None:
    server = svc_start(capture_max_size=shots.max_size, max_capture_photos=shots.initial_count + 1)
    url = f"{server.url}/v1/captures"
    photo = next(shots.initial.iterdir())
    sent = {"photos": (photo.name, photo.read_bytes())}
    assert error_of(httpx.post(url, json={})) == {
        "code": "unsupported_media_type", "field": "photos", "message": error_of(httpx.post(url, json={}))["message"]}
    assert error_of(httpx.post(url, files={"name": (None, "x")}))["field"] == "photos"          # no photos
    assert error_of(httpx.post(url, files={**sent, "test": (None, '["nope.png"]')}))["field"] == "test"
    assert error_of(httpx.post(url, files={**sent, "test": (None, "{")}))["field"] == "test"
    assert error_of(httpx.post(url, files={**sent, "matcher": (None, "all")}))["field"] == "matcher"
    assert error_of(httpx.post(url, files={**sent, "colour": (None, "x")}))["field"] == "colour"
    many = [("photos", (f"{i}_{p.name}", p.read_bytes())) for i in range(2) for p in sorted(shots.initial.iterdir())]
    assert error_of(httpx.post(url, files=many))["field"] == "photos"        # past max_capture_photos
    archive = tmp_path / "photos.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zipped:
        zipped.writestr("a/x.png", photo.read_bytes())
        zipped.writestr("b/x.png", photo.read_bytes())
    answer = httpx.post(url, files={"archive": ("photos.zip", archive.read_bytes())})
    assert answer.status_code == 422 and error_of(answer)["field"] == "archive"
    assert "x.png" in error_of(answer)["message"]
    assert httpx.post(url, files={**sent, "archive": ("p.zip", b"PK")}).status_code == 422   # two ways at once
    with PHDClient(server.url) as phd:
        assert phd.list_captures() == []                 # nothing refused was stored
        with pytest.raises(NotFoundError):
            phd.get_capture("0123456789abcdef")
    assert not list((server.settings.data_dir / "tmp").iterdir())


def test_work_in_the_wrong_order_is_a_conflict_and_keys_own_their_captures(svc_start, shots, tmp_path) -> None:
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"ann": "key-of-ann", "bob": "key-of-bob"}))
    server = svc_start(capture_max_size=shots.max_size, keys_file=keys)
    with PHDClient(server.url, api_key="key-of-ann") as ann, PHDClient(server.url, api_key="key-of-bob") as bob:
        archive = tmp_path / "initial.zip"
        with zipfile.ZipFile(archive, "w") as zipped:
            for photo in sorted(shots.initial.iterdir()):
                zipped.write(photo, f"scene/{photo.name}")
        capture = ann.create_capture(archive, **shots.sfm)       # a zip of a folder of photos
        assert capture.info.num_photos == shots.initial_count
        with pytest.raises(ConflictError) as early:
            capture.next_views(2)
        assert early.value.field == "capture_id" and "train" in early.value.message
        with pytest.raises(NotFoundError):
            bob.get_capture(capture.id)
        assert bob.list_captures() == []
        with pytest.raises(InvalidInputError) as wrong:
            capture.train("nosuchfamily")
        assert wrong.value.field == "model"
        for family, options in (("3dgs", {"foo": 1}), ("2dgs", {"depth_distortion": -1.0})):
            with pytest.raises(InvalidInputError) as bad:           # refused before a job, never a 500 in one
                capture.train(family, options=options)
            assert bad.value.field == "options"
        ann.delete_capture(capture.id)
        with pytest.raises(NotFoundError):
            ann.get_capture(capture.id)
        assert not (server.settings.data_dir / "captures" / capture.id).exists()


def test_kill_9_mid_training_then_restart(tmp_path, shots) -> None:
    data_dir = tmp_path / "data"
    server = SvcProcess(data_dir, PHD_CAPTURE_MAX_SIZE=str(shots.max_size))
    try:
        with PHDClient(server.url) as phd:
            capture = phd.create_capture(shots.initial, test=shots.test, **shots.sfm)
            job = capture.train(iterations=100_000, wait=False)
            deadline = time.monotonic() + 60
            while (running := phd.get_job(job.id)).progress <= 0.0:
                assert time.monotonic() < deadline, "training did not report progress"
                time.sleep(0.1)
            # 100,000 steps left at a pace of milliseconds or more: minutes, and at most the bound
            assert running.eta_seconds is not None and running.eta_max_seconds is not None
            assert 100 < running.eta_seconds <= running.eta_max_seconds
            server.kill()                                       # SIGKILL while it trains
    finally:
        server.kill()
    restarted = SvcProcess(data_dir, PHD_CAPTURE_MAX_SIZE=str(shots.max_size))
    try:
        with PHDClient(restarted.url) as phd:
            interrupted = phd.get_job(job.id)
            assert interrupted.state == "failed" and interrupted.error.code == "interrupted"
            assert interrupted.eta_seconds is None
            again = phd.get_capture(capture.id)
            assert again.info.state == "ready" and again.info.rounds == capture.info.rounds
            assert phd.list_models() == []                       # no half-trained model was stored
            assert not list((data_dir / "tmp").iterdir())
            trained = again.train(iterations=ITERATIONS, samples=4)
            assert trained.summary.test_psnr is not None
    finally:
        restarted.kill()
