"""The service end to end: a real uvicorn server on 127.0.0.1, the real client, real model
files. Every number the service returns must equal `phd_core` called directly with the
same arguments and seed."""

from __future__ import annotations

import base64
import json
import time

import httpx
import imageio.v3 as iio
import numpy as np
import pytest
import torch

import phd_core
from client import ConflictError, InvalidInputError, JobCancelledError, NotFoundError, PHDClient, camera_frames
from phd_core import uq
from phd_core.io import colorize
from phd_core.renderers import NO_CAMERAS_NOTE
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from phd_core.renderers.nerf import load_nerf
from support.fixtures import LEGO, svc_cameras


def _png(data: str | bytes) -> np.ndarray:
    return iio.imread(base64.b64decode(data) if isinstance(data, str) else data)


def _assert_ranking_equal(got, expected) -> None:
    assert [v.index for v in got.views] == [r.index for r in expected]
    assert [v.rank for v in got.views] == [r.rank for r in expected]
    assert [v.sigma_max for v in got.views] == pytest.approx([r.sigma_max for r in expected], rel=1e-6, abs=1e-9)
    assert [v.sigma_mean for v in got.views] == pytest.approx([r.sigma_mean for r in expected], rel=1e-6, abs=1e-9)
    assert [v.score for v in got.views] == pytest.approx([r.score for r in expected], rel=1e-6, abs=1e-9)


def test_ply_upload_calibrate_rank_equal_the_library(svc_start, svc_model_files):
    server = svc_start()
    path = svc_model_files["ply"]
    model = read_ply(path)
    train, candidates = svc_cameras(3), svc_cameras(6, phase=0.3)
    renderer = GaussianRenderer(model, training_cameras=train)
    with PHDClient(server.url) as phd:
        assert phd.health().version == phd_core.__version__
        info = phd.upload_model(path, cameras=train)
        lo, hi = model.bounds()
        assert (info.kind, info.num_units, info.sh_degree) == ("3dgs", 300, 1)
        assert info.bounds == {"min": pytest.approx(lo), "max": pytest.approx(hi)}
        assert info.has_training_cameras and info.num_training_cameras == 3
        assert not info.has_calibration and info.calibration is None
        assert info.size_bytes == path.stat().st_size and info.name == "splats.ply"
        assert [m.id for m in phd.list_models()] == [info.id]

        calibration = phd.calibrate(info.id, epsilon=0.05, step=0.2, samples=3, seed=1)
        direct = uq.calibrate(renderer, train, epsilon=0.05, step=0.2, samples=3, seed=1)
        assert calibration.r_drop == direct.r_drop and calibration.ratios == direct.ratios
        assert calibration.errors == pytest.approx(direct.errors, rel=1e-9)
        assert (calibration.capped, calibration.num_cameras) == (direct.capped, 3)
        stored = phd.get_model(info.id)
        assert stored.has_calibration and stored.calibration == calibration  # stored with the model

        ranking = phd.rank(info.id, candidates, samples=6, seed=2, heatmaps="base64")
        expected = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=6, seed=2)
        _assert_ranking_equal(ranking, expected)
        assert [v.rank for v in ranking.views] == list(range(1, len(candidates) + 1))    # #1 first, as the CLI says
        assert ranking.strategy == uq.DEFAULT_STRATEGY
        assert (ranking.ratio_source, ranking.dropout_ratio, ranking.width) == ("calibration", direct.r_drop, 24)
        # Another strategy and other captured poses give the library's answer for the same arguments.
        paper = phd.rank(info.id, candidates, samples=6, seed=2, strategy="sigma_max", top_k=3)
        _assert_ranking_equal(paper, uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=6,
                                                   seed=2, strategy="sigma_max", top_k=3))
        moved = phd.rank(info.id, candidates, samples=6, seed=2, captured=candidates[:2], top_k=2)
        _assert_ranking_equal(moved, uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=6,
                                                   seed=2, captured=candidates[:2], top_k=2))
        assert not {0, 1} & {v.index for v in moved.views}   # captured poses are not worth capturing again
        coarse = phd.rank(info.id, candidates, samples=6, seed=2, coarse=0.5, refine=2)
        _assert_ranking_equal(coarse, uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=6, seed=2,
                                                    coarse=0.5, refine=2))
        assert [v.refined for v in coarse.views] == [True] * 2 + [False] * 4
        assert ranking.heatmap_vmax == pytest.approx(max(r.sigma_max for r in expected), rel=1e-6)
        for view in ranking.views[:2]:  # the PNG is zeta of that view on the shared colour scale
            zeta = uq.view_uncertainty(renderer, candidates[view.index], ratio=direct.r_drop, samples=6,
                                       seed=2, keep_maps=True).zeta
            assert np.array_equal(_png(view.heatmap_png), colorize(zeta, ranking.heatmap_vmax)[0])

        top = phd.rank(info.id, [c.to_frame() for c in candidates], samples=6, seed=2, top_k=2, dropout_ratio=0.3)
        _assert_ranking_equal(top, uq.rank_views(renderer, candidates, ratio=0.3, samples=6, seed=2, top_k=2))
        assert top.ratio_source == "request" and top.num_candidates == 6

        phd.delete_model(info.id)
        with pytest.raises(NotFoundError):
            phd.get_model(info.id)
        assert phd.list_models() == []
    assert list((server.settings.data_dir / "models").iterdir()) == []


def test_nerf_checkpoint_and_selection_equal_the_library(svc_start, svc_model_files):
    server = svc_start()
    nerf = load_nerf(svc_model_files["nerf"])
    splats = GaussianRenderer(read_ply(svc_model_files["ply_b"]))
    views = svc_cameras(3, phase=0.7, size=16)
    with PHDClient(server.url) as phd:
        a = phd.upload_model(svc_model_files["nerf"])  # training cameras travel inside the checkpoint
        assert (a.kind, a.num_units, a.network["width"], a.network["depth"]) == ("nerf", 16, 16, 2)
        assert a.has_training_cameras and a.num_training_cameras == 3
        b = phd.upload_model(svc_model_files["ply_b"], name="b")
        assert b.name == "b" and b.num_training_cameras == 0

        calibration = phd.calibrate(a.id, epsilon=0.5, step=0.25, samples=2)
        direct = uq.calibrate(nerf, nerf.training_cameras, epsilon=0.5, step=0.25, samples=2)
        assert calibration.r_drop == direct.r_drop
        assert calibration.errors == pytest.approx(direct.errors, rel=1e-9)

        ranking = phd.rank(a.id, views, samples=4, seed=3)
        _assert_ranking_equal(ranking, uq.rank_views(nerf, views, ratio=direct.r_drop, samples=4, seed=3))

        with pytest.raises(ConflictError) as no_calibration:  # b has no calibration and no ratio_b
            phd.select(a.id, b.id, views, samples=4)
        assert (no_calibration.value.status, no_calibration.value.field) == (409, "ratio_b")

        with pytest.raises(InvalidInputError) as no_cameras:  # the default rule needs both models' cameras
            phd.select(a.id, b.id, views, samples=4, ratio_b=0.3)
        assert (no_cameras.value.status, no_cameras.value.field) == (422, "model_b")

        result = phd.select(a.id, b.id, views, samples=4, seed=5, ratio_b=0.3, images="base64", rule="sigma_mean")
        expected = uq.select_models(nerf, splats, views, ratio_a=direct.r_drop, ratio_b=0.3, samples=4,
                                    seed=5, keep_images=True, rule="sigma_mean")
        assert result.rule == "sigma_mean"
        assert (result.ratio_a, result.ratio_b) == (direct.r_drop, 0.3)
        assert [v.choice for v in result.views] == [v.choice for v in expected.views]
        assert [v.score_a for v in result.views] == pytest.approx([v.score_a for v in expected.views], rel=1e-6)
        assert [v.score_b for v in result.views] == pytest.approx([v.score_b for v in expected.views], rel=1e-6)
        assert result.counts == {c: sum(v.choice == c for v in expected.views) for c in "ab"}
        for got, exp in zip(result.views, expected.views):
            assert got.model_id == (a.id if exp.choice == "a" else b.id)
            pixels = (exp.image.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
            assert np.array_equal(_png(got.image_png), pixels)


def test_big_work_becomes_a_job_with_progress_and_artifacts(svc_start, svc_model_files):
    # 6 views x 8 samples x 24 x 24 pixels = 27648 > threshold: answered with 202 and a job.
    server = svc_start(async_threshold=1e4)
    candidates = svc_cameras(6, phase=0.1)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
        body = {"cameras": [c.to_frame() for c in candidates], "samples": 8, "dropout_ratio": 0.2,
                "heatmaps": "files"}
        answer = httpx.post(f"{server.url}/v1/models/{model.id}/rank", json=body, timeout=60)
        assert answer.status_code == 202
        job_id = answer.json()["id"]
        assert answer.headers["location"] == f"/v1/jobs/{job_id}"
        seen: list[float] = []
        result = phd.wait_job(job_id, progress=seen.append, poll_interval=0.01, timeout=60)
        assert seen == sorted(seen) and seen[-1] == 1.0
        job = phd.get_job(job_id)
        # Heat maps: no second dropout pass, only one plain render per returned view (6 x 24 x 24).
        assert job.state == "succeeded" and job.progress == 1.0 and job.estimated_pixels == 27648 + 3456
        assert sorted(job.artifacts) == sorted(url.rsplit("/", 1)[1] for v in result.views
                                               for url in (v.heatmap_url, v.render_url))
        for view in result.views:
            assert view.heatmap_png is None
            assert _png(phd.download(view.heatmap_url)).shape == (24, 24, 3)
        with pytest.raises(NotFoundError):
            phd.download(f"/v1/jobs/{job_id}/artifacts/nothing.png")
        # The client waits for such jobs by itself.
        direct = phd.rank(model.id, candidates, samples=8, dropout_ratio=0.2)
        assert [v.index for v in direct.views] == [v.index for v in result.views]
        # The model has no training cameras: the ranking says in what frame its poses are.
        assert NO_CAMERAS_NOTE in direct.notes and direct.notes == model.details["notes"]


def test_cancel_queued_and_running_jobs(svc_start, svc_model_files):
    server = svc_start(workers=1, max_candidates=2000)
    slow = svc_cameras(600, size=32)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
        running = phd.rank(model.id, slow, samples=16, dropout_ratio=0.2, run_async=True, wait=False)
        queued = phd.rank(model.id, slow, samples=16, dropout_ratio=0.2, run_async=True, wait=False)
        deadline = time.monotonic() + 30
        while phd.get_job(running.id).state != "running":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert phd.cancel_job(queued.id).state == "cancelled"  # never started
        phd.cancel_job(running.id)
        with pytest.raises(JobCancelledError):
            phd.wait_job(running.id, timeout=60, poll_interval=0.02)
        job = phd.get_job(running.id)
        assert job.state == "cancelled" and job.result is None and 0 <= job.progress < 1
        # The worker is free again.
        assert phd.rank(model.id, svc_cameras(2), samples=2, dropout_ratio=0.1).num_candidates == 2


def test_client_reads_cameras_from_transforms_and_sidecars(svc_start, svc_model_files, tmp_path):
    from phd_core.renderers.gs3d import SIDECAR_FORMAT

    transforms = LEGO / "transforms_val.json"
    frames = camera_frames(transforms)  # Blender style: no w/h in the JSON, taken from the PNGs
    assert len(frames) == 100 and all(f["w"] == 200 and f["h"] == 200 for f in frames)
    assert all(f["camera_angle_x"] == pytest.approx(0.6911112070083618) for f in frames)
    ply = tmp_path / "trained.ply"
    ply.write_bytes(svc_model_files["ply"].read_bytes())
    train = svc_cameras(5)
    (tmp_path / "trained.json").write_text(json.dumps({"format": SIDECAR_FORMAT,
                                                       "training_cameras": [c.to_frame() for c in train]}))
    server = svc_start()
    with PHDClient(server.url) as phd:
        assert phd.upload_model(ply).num_training_cameras == 5               # the trainer's sidecar
        assert phd.upload_model(ply, cameras=transforms).num_training_cameras == 100
        with pytest.raises(InvalidInputError) as exc:                       # Blender frames need a size
            phd.upload_model(ply, cameras={"camera_angle_x": 0.7,
                                           "frames": [{"transform_matrix": frames[0]["transform_matrix"]}]})
        assert exc.value.field == "cameras[0].w"


def test_a_splat_models_background_is_stored_and_used_after_a_restart(svc_start, svc_model_files, tmp_path):
    # A sidecar that says the model was trained over black: the client sends it, the service
    # renders over it (a ranking equals the library's black-background renderer, not the white one).
    ply = tmp_path / "black.ply"
    ply.write_bytes(svc_model_files["ply"].read_bytes())
    cameras = svc_cameras(4, phase=0.2)
    (tmp_path / "black.json").write_text(json.dumps({"background": [0.0, 0.0, 0.0],
                                                     "training_cameras": camera_frames(cameras)}))
    candidates = svc_cameras(5, phase=0.7)
    model = read_ply(svc_model_files["ply"])
    black = uq.rank_views(GaussianRenderer(model, (0, 0, 0), cameras), candidates, ratio=0.3, samples=5, seed=1)
    white = uq.rank_views(GaussianRenderer(model, (1, 1, 1), cameras), candidates, ratio=0.3, samples=5, seed=1)
    assert [r.sigma_max for r in black] != pytest.approx([r.sigma_max for r in white], rel=1e-6)
    data_dir = tmp_path / "data"
    server = svc_start(data_dir=data_dir)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(ply)
        assert info.details["background"] == [0.0, 0.0, 0.0]
        _assert_ranking_equal(phd.rank(info.id, candidates, samples=5, seed=1, dropout_ratio=0.3), black)
        with pytest.raises(InvalidInputError) as bad:
            phd.upload_model(svc_model_files["ply"], background=[0.0, 2.0, 0.0])
        assert bad.value.field == "background"
        with pytest.raises(InvalidInputError) as nerf:
            phd.upload_model(svc_model_files["nerf"], background="black")
        assert nerf.value.field == "background"
    server.stop()
    with PHDClient(svc_start(data_dir=data_dir).url) as phd:   # reloaded from disk, not the cache
        _assert_ranking_equal(phd.rank(info.id, candidates, samples=5, seed=1, dropout_ratio=0.3), black)
