"""Training cameras of another capture are refused at upload, through the real server and client:
422 `cameras_of_another_capture` naming `cameras` and how many of them see the model, unless the
upload sets `other_capture`; and a capture's own frames written by `phd candidates frames` rank
through the client at exactly the capture's poses."""

from __future__ import annotations

import json

import httpx
import pytest

from client import InvalidInputError, PHDClient
from phd_cli import main
from phd_core.data import load_dataset, select_views
from phd_core.scene import Camera
from support.fixtures import LEGO, expect_error, svc_cameras


def elsewhere(cameras: list[Camera], offset: float = 100.0) -> list[Camera]:
    """The same cameras (looking about level) raised by `offset`: another capture's frame, where they see
    nothing."""
    moved = []
    for camera in cameras:
        c2w = camera.c2w.clone()
        c2w[2, 3] += offset
        moved.append(Camera(c2w, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height))
    return moved


@pytest.mark.parametrize("kind", ["ply", "nerf"])
def test_cameras_that_see_none_of_the_model_are_refused_unless_told(svc_start, svc_model_files, kind) -> None:
    server = svc_start()
    with PHDClient(server.url) as phd:
        with pytest.raises(InvalidInputError) as refused:
            phd.upload_model(svc_model_files[kind], cameras=elsewhere(svc_cameras(3)))
        error = refused.value
        assert (error.status, error.code, error.field) == (422, "cameras_of_another_capture", "cameras")
        assert "3 of the 3 training cameras see almost none of the model" in error.message
        assert "other_capture" in error.message and phd.list_models() == []
        stored = phd.upload_model(svc_model_files[kind], cameras=elsewhere(svc_cameras(3)), other_capture=True)
        assert stored.num_training_cameras == 3
        assert phd.upload_model(svc_model_files[kind], cameras=svc_cameras(3)).num_training_cameras == 3
        assert len(phd.list_models()) == 2


def test_other_capture_must_say_yes_or_no(svc_start, svc_model_files) -> None:
    server = svc_start()
    with open(svc_model_files["ply"], "rb") as f:
        answer = httpx.post(server.url + "/v1/models", files={"file": ("m.ply", f)},
                            data={"other_capture": "perhaps", "cameras": json.dumps([c.to_frame()
                                                                                     for c in svc_cameras(3)])})
    assert "must be true or false" in expect_error(answer, 422, "invalid_input", "other_capture")["message"]


def test_a_captures_frames_from_phd_candidates_rank_through_the_client(svc_start, svc_trained, tmp_path) -> None:
    frames = tmp_path / "test_views.json"
    assert main(["candidates", "frames:3", "--data", str(LEGO), "--split", "test", "--out", str(frames)]) == 0
    expected = [load_dataset(LEGO, "test", with_images=False).cameras[i] for i in select_views(200, 3)]
    server = svc_start()
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_trained)                     # its sidecar brings the training cameras
        ranked = phd.rank(model.id, cameras=frames, dropout_ratio=0.3, samples=2, downscale=8)
    assert ranked.num_candidates == 3 and sorted(v.index for v in ranked.views) == [0, 1, 2]
    for view in ranked.views:
        camera = expected[view.index]
        assert max(abs(a - b) for row, ref in zip(view.camera["transform_matrix"], camera.c2w.tolist())
                   for a, b in zip(row, ref)) <= 1e-9
        assert (view.camera["fl_x"], view.camera["w"], view.camera["h"]) == (camera.fx, camera.width, camera.height)
