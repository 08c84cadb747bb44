"""Bring your own capture through the service and the real client: a reference-trainer output
folder uploaded as is, nerfstudio splatfacto and gsplat folders uploaded with poses in the
user's frame, cameras from COLMAP and LLFF files, rank requests that name a
candidate generator instead of a camera list, and 4xx (never 5xx) for malformed input."""

from __future__ import annotations

import json
import warnings

import httpx
import numpy as np
import pytest

from client import InvalidInputError, PHDClient
from phd_core import uq as phd
from phd_core.data.inria import camera_from_entry
from phd_core.errors import ModelNote
from phd_core.io.configs import SPLATFACTO_BACKGROUNDS as BACKGROUNDS
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.scene import Camera
from phd_core.uq.candidates import candidate_cameras
from support.captures import colmap_pose as written_colmap_pose
from support.captures import inria_entries, write_colmap, write_llff, write_output_folder
from support.cli import run
from support.fixtures import svc_cameras, svc_random_gaussians
from support.trainers import gsplat_scene, splatfacto_scene


@pytest.fixture(scope="module")
def output_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("svc_capture")
    return write_output_folder(root / "output", svc_random_gaussians(300, seed=0), svc_cameras(3))


def test_upload_an_output_folder_calibrate_and_rank_generated_candidates(svc_start, output_folder) -> None:
    server = svc_start()
    renderer = load_model(output_folder)
    # The service renders over the trainer's background (cfg_args), as the CLI does, not over white.
    served = renderer
    white = load_model(next(output_folder.glob("point_cloud/iteration_30000/point_cloud.ply")))
    assert renderer.background.tolist() != white.background.tolist()
    with PHDClient(server.url) as client:
        info = client.upload_model(output_folder)
        assert info.num_units == 300 and info.num_training_cameras == 3
        assert info.name == f"{output_folder.name}/3dgs"                 # the run, not point_cloud.ply
        calibration = client.calibrate(info.id, epsilon=0.05, samples=3)
        expected = phd.calibrate(served, renderer.training_cameras, epsilon=0.05, samples=3)
        assert calibration.r_drop == expected.r_drop
        ranking = client.rank(info.id, candidates="orbit:5,rings=2", samples=3, dropout_ratio=0.2)
    poses = candidate_cameras("orbit", 5, cameras=renderer.training_cameras, rings=2)
    ranked = phd.rank_views(served, poses, ratio=0.2, samples=3, captured=renderer.training_cameras)
    assert ranking.num_candidates == 5 and (ranking.width, ranking.height) == (24, 24)
    assert [v.index for v in ranking.views] == [r.index for r in ranked]
    assert [v.sigma_max for v in ranking.views] == pytest.approx([r.sigma_max for r in ranked], rel=1e-5)
    # Each ranked view carries the generator's pose, and the same pose as a cameras.json entry.
    assert info.camera_format == ranking.camera_format == "3dgs-output"
    for view in ranking.views:
        assert view.camera == poses[view.index].to_frame() and view.c2w == poses[view.index].c2w.tolist()
        assert view.source_pose["format"] == "3dgs-output"
        assert np.allclose(camera_from_entry(view.source_pose).c2w.numpy(), poses[view.index].c2w.numpy(),
                           atol=1e-12)


@pytest.mark.parametrize("trainer", ["splatfacto checkpoint", "gsplat"])
def test_upload_a_splatfacto_or_gsplat_folder_and_rank_in_the_users_frame(svc_start, tmp_path, trainer) -> None:
    """The client reads the folder (checkpoints without unpickling code), uploads the splats moved
    into the user's frame with the training cameras; the service answers in that frame."""
    if trainer == "gsplat":
        scene, background = gsplat_scene(tmp_path), (0.0, 0.0, 0.0)
    else:
        scene, background = splatfacto_scene(tmp_path, export_ply=False), BACKGROUNDS["random"]
    server = svc_start()
    with PHDClient(server.url) as client:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            info = client.upload_model(scene["folder"])
        assert any(w.category is ModelNote for w in caught)
        assert info.num_units == 300 and info.num_training_cameras == len(scene["training"])
        # Named after the run (<experiment>/<method>), not the timestamp folder.
        assert info.name == {"gsplat": "garden/gsplat", "splatfacto checkpoint": "desk/splatfacto"}[trainer]
        frames = client.training_cameras(info.id)
        ranking = client.rank(info.id, candidates="orbit:5,rings=1", samples=3, dropout_ratio=0.2)
    assert np.allclose([f["transform_matrix"] for f in frames], [c.c2w.tolist() for c in scene["training"]],
                       atol=1e-9)
    reference = GaussianRenderer(scene["user_model"], background, scene["training"])
    poses = candidate_cameras("orbit", 5, cameras=scene["training"], rings=1)
    ranked = phd.rank_views(reference, poses, ratio=0.2, samples=3, captured=scene["training"])
    got = {v.index: v.sigma_max for v in ranking.views}
    assert max(r.sigma_max for r in ranked) > 0.01
    assert [got[r.index] for r in ranked] == pytest.approx([r.sigma_max for r in ranked], rel=1e-3, abs=1e-5)


@pytest.mark.parametrize("kind", ["raw cameras.json", "colmap", "llff"])
def test_upload_cameras_from_any_format(svc_start, output_folder, tmp_path, kind) -> None:
    cameras = svc_cameras(3)
    server = svc_start()
    ply = next(output_folder.glob("point_cloud/iteration_30000/point_cloud.ply"))
    if kind == "raw cameras.json":        # what a curl user sends: the file as the trainer wrote it
        with open(ply, "rb") as f:
            response = httpx.post(f"{server.url}/v1/models", files={"file": ("point_cloud.ply", f)},
                                  data={"cameras": (output_folder / "cameras.json").read_text()})
        assert response.status_code == 201, response.text
        model_id = response.json()["id"]
    else:
        if kind == "colmap":
            write_colmap(tmp_path, cameras, binary=True)
            source = tmp_path
        else:                             # an LLFF capture of 9 frames: frames 0 and 8 are test views
            cameras = [Camera(c.c2w, c.fx, c.fx, 12, 12, 24, 24) for c in svc_cameras(9)]
            source = write_llff(tmp_path, cameras)
        with PHDClient(server.url) as client:
            model_id = client.upload_model(ply, cameras=source).id
    with PHDClient(server.url) as client:
        stored = client.get_model(model_id)
        expected = {"raw cameras.json": 3, "colmap": 2, "llff": 7}[kind]   # train splits hold out every 8th
        assert stored.num_training_cameras == expected
        assert client.calibrate(model_id, epsilon=0.05, samples=2).num_cameras == expected
        # Poses come back in the source's convention; LLFF keeps its name but has no converter, so its
        # poses come back as transforms frames only (source_pose null).
        assert stored.camera_format == {"raw cameras.json": "3dgs-output", "colmap": "colmap", "llff": "llff"}[kind]
        candidates = svc_cameras(2, phase=0.3)
        ranking = client.rank(model_id, candidates, samples=2, dropout_ratio=0.2)
    for view in ranking.views:
        given = candidates[view.index]
        assert view.camera == given.to_frame()
        if kind == "colmap":                         # COLMAP: world-to-camera qvec and tvec, as the files hold
            qvec, tvec = written_colmap_pose(given)
            sign = 1.0 if qvec[0] >= 0 else -1.0
            assert np.allclose(view.source_pose["qvec"], sign * np.array(qvec), atol=1e-9)
            assert np.allclose(view.source_pose["tvec"], tvec, atol=1e-9)
        assert (view.source_pose or {}).get("format") == (None if kind == "llff" else stored.camera_format)
    if kind == "raw cameras.json":                   # no background field: the reference trainer's black, said so
        assert stored.details["background"] == [0.0, 0.0, 0.0] and "guessed" in stored.details["background_source"]


def test_a_capture_format_has_one_name_in_the_cli_and_the_service(svc_start, tmp_path, capsys) -> None:
    """A model `phd train` made of an LLFF capture is "llff" in `phd rank --json`, in the upload's
    answer and in a rank answer (REST and the client), not "nerfstudio" where the service has
    no converter; its poses download as a transforms.json (the default for a format without one)."""
    cameras = [Camera(c.c2w, c.fx, c.fx, 12, 12, 24, 24) for c in svc_cameras(9)]
    reference = GaussianRenderer(svc_random_gaussians(300, seed=0), (1.0, 1.0, 1.0), cameras)
    write_llff(tmp_path / "llff", cameras, images=[reference.render(c)[0].numpy() for c in cameras])
    ply = tmp_path / "m.ply"
    code, _, err = run(capsys, "train", "--data", tmp_path / "llff", "--views", 7, "--iterations", 2, "--downscale", 1,
                       "--out", ply, "--quiet")
    assert code == 0, err
    code, out, err = run(capsys, "rank", "--json", "--model", ply, "--candidates", "orbit:3", "--samples", 2,
                         "--dropout-ratio", 0.2)
    assert code == 0, err
    cli = json.loads(out)
    assert cli["camera_format"] == "llff" and all(r["source_pose"] is None for r in cli["ranking"])
    server = svc_start()
    with PHDClient(server.url) as client:
        info = client.upload_model(ply)                              # its sidecar beside it
        ranking = client.rank(info.id, candidates="orbit:3", samples=2, dropout_ratio=0.2)
    assert info.camera_format == ranking.camera_format == "llff"
    assert httpx.get(f"{server.url}/v1/models/{info.id}").json()["camera_format"] == "llff"
    assert all(v.source_pose is None for v in ranking.views)
    poses = httpx.post(f"{server.url}/v1/models/{info.id}/poses", json={"cameras": [ranking.views[0].camera]})
    assert poses.status_code == 200 and 'filename="transforms.json"' in poses.headers["content-disposition"]


def test_malformed_capture_input_is_a_4xx(svc_start, output_folder) -> None:
    server = svc_start(max_candidates=10)
    url = server.url
    with PHDClient(server.url) as client:
        model_id = client.upload_model(output_folder).id
    ply = next(output_folder.glob("point_cloud/iteration_30000/point_cloud.ply"))
    entries = inria_entries(svc_cameras(2))
    entries[1]["rotation"] = [[1, 0, 0], [0, 1, 0], [0, 0, 5]]
    with open(ply, "rb") as f:
        response = httpx.post(f"{url}/v1/models", files={"file": ("p.ply", f)}, data={"cameras": json.dumps(entries)})
    assert response.status_code == 422 and response.json()["error"]["field"] == "cameras[1].rotation", response.text
    for body, field in (({"candidates": {"generator": "zigzag", "count": 3}}, "candidates.generator"),
                        ({"candidates": {"generator": "orbit", "count": 11}}, "candidates.count"),
                        ({"candidates": {"generator": "orbit", "count": 3, "options": {"tilt": 1}}},
                         "candidates.options.tilt"),
                        ({"candidates": {"generator": "orbit", "count": 3, "options": {"rings": 9}}},
                         "candidates.options.rings"),
                        # candidate_cameras' own parameters are no option: they would bind to them
                        ({"candidates": {"generator": "orbit", "count": 3, "options": {"cameras": 3}}},
                         "candidates.options.cameras"),
                        ({"candidates": {"generator": "orbit", "count": 3, "options": {"points": 3}}},
                         "candidates.options.points"),
                        ({"candidates": {"generator": "orbit", "count": 0}}, "candidates.count"),
                        ({}, None),
                        ({"candidates": {"generator": "orbit"}, "cameras": [svc_cameras(1)[0].to_frame()]}, None)):
        response = httpx.post(f"{url}/v1/models/{model_id}/rank", json={"dropout_ratio": 0.1, "samples": 2, **body})
        assert response.status_code == 422, (body, response.text)
        error = response.json()["error"]
        assert field is None or error["field"] == field, (body, error)
        assert "candidates" in error["message"] or "generator" in error["message"] or field, error
    bad = np.zeros((2, 5))
    with pytest.raises(InvalidInputError):
        with PHDClient(server.url) as client:
            np.save(output_folder.parent / "bad.npy", bad)
            client.upload_model(ply, cameras=output_folder.parent / "bad.npy")


def test_generated_candidates_for_a_model_without_cameras_come_from_its_splats(svc_start, svc_model_files) -> None:
    server = svc_start()
    with PHDClient(server.url) as client:
        info = client.upload_model(svc_model_files["ply"])
        assert info.num_training_cameras == 0
        ranking = client.rank(info.id, candidates={"generator": "hemisphere", "count": 4, "options": {}},
                              width=16, height=16, samples=2, dropout_ratio=0.2)
    renderer = load_model(svc_model_files["ply"])
    poses = [c.resized(16, 16) for c in candidate_cameras("hemisphere", 4, renderer=renderer)]
    ranked = phd.rank_views(renderer, poses, ratio=0.2, samples=2, captured=[])
    assert [v.index for v in ranking.views] == [r.index for r in ranked]
    assert [v.sigma_max for v in ranking.views] == pytest.approx([r.sigma_max for r in ranked], rel=1e-5)
    full_size = candidate_cameras("hemisphere", 4, renderer=renderer)     # poses at their own size, not 16x16
    assert [v.camera for v in ranking.views] == [full_size[v.index].to_frame() for v in ranking.views]
    assert ranking.camera_format is None and all(v.source_pose is None for v in ranking.views)


def test_upload_fields_camera_format_and_background_are_checked(svc_start, output_folder) -> None:
    server = svc_start()
    ply = next(output_folder.glob("point_cloud/iteration_30000/point_cloud.ply"))
    frames = json.dumps([c.to_frame() for c in svc_cameras(3)])
    for data, field in (({"cameras": frames, "camera_format": "ply"}, "camera_format"),
                        ({"cameras": frames, "background": "purple"}, "background")):
        with open(ply, "rb") as f:
            response = httpx.post(f"{server.url}/v1/models", files={"file": ("m.ply", f)}, data=data)
        assert response.status_code == 422 and response.json()["error"]["field"] == field, response.text
        assert "colmap" in response.json()["error"]["message"] or field == "background"
    with PHDClient(server.url) as client:
        info = client.upload_model(ply, cameras=svc_cameras(3), background="grey", camera_format="colmap")
        assert info.details["background"] == [0.5, 0.5, 0.5] and info.camera_format == "colmap"
        assert info.details["background_source"] == "the upload's background field"
        bare = client.upload_model(ply)              # no cameras, no background: the stated default
        assert bare.details["background"] == [1.0, 1.0, 1.0] and bare.camera_format is None
