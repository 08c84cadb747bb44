"""What the page's 3D view reads, through a real server: the scene binary equals the library's
points of the stored model, and the explain job's bytes equal phd_core's explanation of it,
quantized; what cannot be explained is refused naming the field."""

from __future__ import annotations

import base64
import json
import struct

import httpx
import numpy as np
import pytest
import torch

from client import PHDClient
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from phd_core.renderers.points import importance, point_subset, scene_points
from phd_core.scene import capture_up
from phd_core.uq.explain import explain
from support.fixtures import svc_cameras
from support.upright import degrees_from_up, one_side

KEY = "scene-key"
AUTH = {"Authorization": f"Bearer {KEY}"}


def read_scene(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and arrays of a scene binary (format in service/explain.py)."""
    assert data[:4] == b"PHD3"
    (length,) = struct.unpack("<I", data[4:8])
    header = json.loads(data[8:8 + length])
    widths = {"float32": np.dtype("<f4"), "uint8": np.dtype("u1")}
    arrays = {part["name"]: np.frombuffer(data, widths[part["type"]], part["length"], part["offset"])
              for part in header["layout"]}
    assert all(part["offset"] % 4 == 0 for part in header["layout"])     # typed arrays view them in place
    return header, arrays


def test_the_scene_binary_is_the_stored_models_points(svc_start, svc_model_files):
    server = svc_start(api_key=KEY)
    train = one_side()                    # photos from one side, looking down: their mean up leans 38 degrees
    with PHDClient(server.url, api_key=KEY) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
    answer = httpx.get(f"{server.url}/v1/models/{info.id}/scene", params={"cap": 120}, headers=AUTH)
    assert answer.status_code == 200 and answer.headers["content-type"] == "application/octet-stream"
    header, arrays = read_scene(answer.content)
    expected = scene_points(GaussianRenderer(read_ply(svc_model_files["ply"])), cap=120)
    assert (header["total"], header["count"], header["cap"], header["kind"]) == (300, 120, 120, info.kind)
    # The capture's up, as GET /cameras says it: the true up of the generated capture.
    assert header["up"] == pytest.approx(capture_up(train).vector.tolist(), abs=1e-12)
    cameras = httpx.get(f"{server.url}/v1/models/{info.id}/cameras", headers=AUTH).json()
    assert cameras["up"] == header["up"] and cameras["up_rule"] == "horizontal axes"
    assert degrees_from_up(torch.tensor(header["up"], dtype=torch.float64)) < 2.0
    assert np.array_equal(arrays["positions"].reshape(-1, 3), expected.positions.numpy())
    assert np.array_equal(arrays["sigma"], expected.sigma.numpy())
    assert np.array_equal(arrays["colours"].reshape(-1, 4), expected.colours.numpy())
    assert header["bounds"]["min"] == pytest.approx(expected.positions.amin(0).tolist())
    whole = read_scene(httpx.get(f"{server.url}/v1/models/{info.id}/scene", headers=AUTH).content)[0]
    assert (whole["count"], whole["cap"]) == (300, 200_000)            # under the default cap: every splat

    assert httpx.get(f"{server.url}/v1/models/{info.id}/scene").status_code == 401
    refused = httpx.get(f"{server.url}/v1/models/{info.id}/scene", params={"cap": 0}, headers=AUTH)
    assert refused.status_code == 422 and refused.json()["error"]["field"] == "cap"


def test_explain_sends_phd_cores_values_for_the_scenes_points(svc_start, svc_model_files):
    server = svc_start(api_key=KEY)
    train, pick = svc_cameras(3), svc_cameras(4, phase=0.5)[1]
    with PHDClient(server.url, api_key=KEY) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
        nerf = phd.upload_model(svc_model_files["nerf"])
    url = f"{server.url}/v1/models/{info.id}/explain"
    body = {"samples": 3, "seed": 1, "dropout_ratio": 0.2, "pick": pick.to_frame(), "cap": 150}
    answer = httpx.post(url, json=body, headers=AUTH, timeout=60)
    assert answer.status_code == 200, answer.text
    result = answer.json()

    renderer = GaussianRenderer(read_ply(svc_model_files["ply"]))
    direct = explain(renderer, train, ratio=0.2, samples=3, seed=1, pick=pick)
    ids = point_subset(importance(renderer.model), 150)
    assert (result["total"], result["count"], result["num_views"], result["ratio_source"]) == (300, 150, 3, "request")
    assert result["scales"]["coverage"] == 3.0             # three views' worth of sight: the top colour
    novel = direct.novelty[direct.novelty > 0]               # what the pick adds, drawn to the share it reaches
    assert result["scales"]["novelty"] == pytest.approx(float(np.quantile(novel.numpy(), 0.99)))
    assert result["scales"]["novelty"] < 1.0
    fragile = direct.fragility[~torch.isnan(direct.fragility)]
    assert result["scales"]["fragility"] == pytest.approx(float(np.quantile(fragile.numpy(), 0.99)))
    assert result["unseen_share"] == pytest.approx(float((direct.coverage == 0).double().mean()))
    for name, values in (("coverage", direct.coverage), ("fragility", direct.fragility),
                         ("novelty", direct.novelty)):
        got = np.frombuffer(base64.b64decode(result["values"][name]), np.uint8)
        assert values is not None and len(got) == 150
        v = values[ids].numpy()
        scale = result["scales"][name]
        known = ~np.isnan(v)
        assert np.array_equal(got == 255, ~known)
        expected = np.round(np.clip(v[known] / scale, 0, 1) * 254)
        assert np.abs(got[known].astype(int) - expected).max() <= 1      # float32 vs float64 at a rounding edge
        assert len(np.unique(got[known])) > 5                              # the values vary over the model

    # As a job through the client: progress ends at 1 and the job's result is the same.
    with PHDClient(server.url, api_key=KEY) as phd:
        job = phd.explain(info.id, pick=pick, samples=3, seed=1, dropout_ratio=0.2, cap=150, run_async=True,
                          wait=False)
        finished = phd.wait_job(job.id)
        done = phd.get_job(job.id)
    assert done.kind == "explain" and done.progress == 1.0
    assert finished.model_dump(mode="json")["values"] == result["values"]

    # What cannot be explained says which field to change.
    no_ratio = httpx.post(url, json={"samples": 3}, headers=AUTH)
    assert no_ratio.status_code == 409 and no_ratio.json()["error"]["field"] == "dropout_ratio"
    no_cameras = httpx.post(url, json={**body, "captured": []}, headers=AUTH)
    assert no_cameras.status_code == 422 and no_cameras.json()["error"]["field"] == "captured"
    bad_pick = httpx.post(url, json={**body, "pick": {"transform_matrix": [[1, 0, 0]]}}, headers=AUTH)
    assert bad_pick.status_code == 422 and bad_pick.json()["error"]["field"].startswith("pick")
    not_splats = httpx.get(f"{server.url}/v1/models/{nerf.id}/scene", headers=AUTH)
    assert not_splats.status_code == 422 and not_splats.json()["error"]["field"] == "model"


def test_explain_is_planned_within_the_memory_budget(svc_start, svc_model_files):
    """An explanation too large for the budget is a 413 naming the field to lower, before it runs."""
    server = svc_start(memory_budget_bytes=24 << 20)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3))
    body = {"samples": 3, "dropout_ratio": 0.2}
    fits = httpx.post(f"{server.url}/v1/models/{info.id}/explain", json=body, timeout=60)
    assert fits.status_code == 200, fits.text
    big = httpx.post(f"{server.url}/v1/models/{info.id}/explain", json={**body, "width": 800, "height": 800})
    assert big.status_code == 413 and big.json()["error"]["field"] == "downscale"


def test_the_up_is_found_once_at_upload_on_the_floor_the_splats_show(svc_start, tmp_path):
    """A phone held 6 degrees rolled throughout tilts the cameras' own up by about that; the
    model's splats show the floor it stands on. The service finds the up when the model is
    uploaded (loaded then), and /cameras, the scene binary and the poses it generates all stand
    on the floor's normal, not on the cameras' lean."""
    from phd_core.renderers.gs3d import GaussianModel, write_ply
    from phd_core.renderers.splats import SH_C0
    from support.upright import scene_points as floor_scene

    cameras = one_side(rolls=[6.0] * 30)
    means = floor_scene({"floor": 3000, "object": 2000}).float()                  # [G, 3]
    count = len(means)
    model = GaussianModel(means=means, log_scales=torch.full((count, 3), -4.0),
                          quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(count, 1),
                          opacity_logits=torch.full((count,), 4.0),
                          sh=torch.full((count, 1, 3), 0.2 / SH_C0))
    write_ply(model, tmp_path / "floor.ply")
    server = svc_start(api_key=KEY)
    with PHDClient(server.url, api_key=KEY) as phd:
        info = phd.upload_model(tmp_path / "floor.ply", cameras=cameras)
        ranking = phd.rank(info.id, candidates="orbit:6", strategy="random", dropout_ratio=0.2)
        through_client = phd.cameras(info.id)
    served = httpx.get(f"{server.url}/v1/models/{info.id}/cameras", headers=AUTH).json()
    assert (through_client.up, through_client.up_rule) == (served["up"], served["up_rule"])
    assert served["up_rule"] == "support plane"
    assert degrees_from_up(torch.tensor(served["up"], dtype=torch.float64)) < 1.0
    assert degrees_from_up(capture_up(cameras).vector) > 4.0                          # the cameras' own lean
    header, _ = read_scene(httpx.get(f"{server.url}/v1/models/{info.id}/scene", headers=AUTH).content)
    assert header["up"] == served["up"]
    up = torch.tensor(served["up"], dtype=torch.float64)
    for view in ranking.views:                      # each generated pose is level: its right axis is horizontal
        right = torch.tensor(view.camera["transform_matrix"], dtype=torch.float64)[:3, 0]
        assert abs(float(right @ up)) < 1e-6
