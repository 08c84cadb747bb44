"""The Ray executor on a local Ray instance started here (2 CPUs): the same ranking,
calibration and selection as one process, a worker killed mid-job is retried, and the
service sends its jobs to Ray and still fails a job for a deleted model cleanly.

Skipped without ray (`pip install '.[ray]'`). Ray's start-up and its workers' first torch
import cost seconds: the instance is shared by the module."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed (pip install '.[ray]'): the Ray executor is untested")

from client import JobFailedError, NotFoundError, PHDClient  # noqa: E402
from phd_cli import main  # noqa: E402
from phd_core import uq  # noqa: E402
from phd_core.executors import make_executor  # noqa: E402
from phd_core.executors.ray import RayExecutor  # noqa: E402
from phd_core.renderers import load_model  # noqa: E402
from phd_core.renderers.gs3d import write_ply  # noqa: E402
from support.fixtures import svc_cameras, svc_random_gaussians  # noqa: E402
from support.stall_renderer import StallOnceRenderer  # noqa: E402
from support.toy_renderers import BlobRenderer, ring_cameras  # noqa: E402

TESTS = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cluster():
    """A private 2-CPU Ray instance; its workers import the test helpers (PYTHONPATH)."""
    if ray.is_initialized():
        ray.shutdown()
    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), saved) if p)
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    finally:
        if saved is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = saved
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ray") / "splats.ply"
    write_ply(svc_random_gaussians(300, seed=4), path)
    return path


def test_ray_gives_the_local_ranking_calibration_and_selection(cluster, model) -> None:
    renderer = load_model(model)
    executor = make_executor("ray", "auto")
    candidates = svc_cameras(10, phase=0.2)
    assert len(executor.split(candidates)) == 4                      # 2 CPUs x 2 chunks
    for strategy in ("sigma_max", uq.DEFAULT_STRATEGY):
        local = uq.rank_views(renderer, candidates, ratio=0.3, samples=8, seed=7, strategy=strategy,
                              captured=svc_cameras(3))
        spread = uq.rank_views(renderer, candidates, ratio=0.3, samples=8, seed=7, strategy=strategy,
                               captured=svc_cameras(3), executor=executor)
        assert [r.to_dict() for r in spread] == [r.to_dict() for r in local]
    assert len({r.sigma_max for r in local}) == len(local)          # distinct values: the order is meaningful
    other = uq.rank_views(renderer, candidates, ratio=0.3, samples=8, seed=8, executor=executor)
    assert [r.sigma_max for r in other] != [r.sigma_max for r in local]   # the seed matters on Ray too

    train = svc_cameras(4)
    local = uq.calibrate(renderer, train, epsilon=0.02, step=0.1, samples=3, seed=2)
    assert uq.calibrate(renderer, train, epsilon=0.02, step=0.1, samples=3, seed=2,
                        executor=executor).to_dict() == local.to_dict()
    assert 0 < local.r_drop < 0.9

    second = load_model(model)
    local = uq.select_models(renderer, second, candidates[:5], ratio_a=0.1, ratio_b=0.4, samples=4,
                             rule="sigma_mean")
    assert uq.select_models(renderer, second, candidates[:5], ratio_a=0.1, ratio_b=0.4, samples=4,
                            rule="sigma_mean", executor=executor).to_dict() == local.to_dict()


def test_a_worker_killed_mid_job_is_retried_and_the_ranking_still_finishes(cluster, tmp_path) -> None:
    inner = BlobRenderer.random(30, seed=6)
    marker = tmp_path / "stalled.pid"
    candidates = ring_cameras(6, size=12, height=1.1)
    executor = RayExecutor("auto", max_retries=2)
    start = time.monotonic()
    with ThreadPoolExecutor(1) as pool:
        job = pool.submit(uq.rank_views, StallOnceRenderer(inner, marker), candidates, ratio=0.25, samples=5,
                          seed=3, executor=executor)
        while not (marker.exists() and marker.read_text()):
            assert time.monotonic() - start < 120 and not job.done(), "no task reached the stalling render"
            time.sleep(0.1)
        pid = int(marker.read_text())
        assert pid != os.getpid()                                    # the render runs in a Ray worker
        os.kill(pid, signal.SIGKILL)
        ranked = job.result(timeout=180)
    # Well before the stall would have ended: the killed task ran again on another worker.
    assert time.monotonic() - start < 100
    expected = uq.rank_views(inner, candidates, ratio=0.25, samples=5, seed=3)
    assert [r.to_dict() for r in ranked] == [r.to_dict() for r in expected]


def test_a_cancelled_job_does_not_wait_for_its_outstanding_chunks(cluster, tmp_path) -> None:
    class Cancelled(Exception):
        pass

    def cancel(fraction: float) -> None:
        raise Cancelled

    marker = tmp_path / "stalled.pid"
    start = time.monotonic()
    with pytest.raises(Cancelled):       # one chunk stalls for 120 s; the first finished one cancels
        uq.rank_views(StallOnceRenderer(BlobRenderer.random(20, seed=1), marker), ring_cameras(6, size=12),
                      ratio=0.2, samples=3, progress=cancel, executor=make_executor("ray"))
    assert marker.exists() and time.monotonic() - start < 60


def test_errors_in_the_work_come_back_as_themselves(cluster) -> None:
    from phd_core.errors import InputError

    class Broken(BlobRenderer):
        def render(self, camera, keep=None, signal="composited"):
            raise InputError("cameras", "this camera cannot be rendered")

    with pytest.raises(InputError) as info:                         # not wrapped, not retried
        uq.rank_views(Broken.random(5), ring_cameras(3), ratio=0.2, samples=2, executor=make_executor("ray"))
    assert (info.value.field, info.value.reason) == ("cameras", "this camera cannot be rendered")


def test_phd_rank_gives_the_same_ranking_with_ray(cluster, model, tmp_path, capsys) -> None:
    candidates = tmp_path / "candidates.json"
    candidates.write_text(json.dumps([c.to_frame() for c in svc_cameras(8, phase=0.5)]))
    outputs = {}
    for name, extra in (("local", []), ("ray", ["--ray", "auto"]), ("address", ["--ray", cluster])):
        out = tmp_path / f"{name}.json"
        assert main(["rank", "--model", str(model), "--candidates", str(candidates), "--dropout-ratio", "0.3",
                     "--samples", "6", "--seed", "4", "--out", str(out), *extra]) == 0
        outputs[name] = json.loads(out.read_text())
    capsys.readouterr()
    assert outputs["ray"] == outputs["local"] == outputs["address"]
    assert sorted(outputs["local"]["order"]) == list(range(8))


def test_the_service_runs_its_jobs_on_ray(cluster, model, svc_start, monkeypatch) -> None:
    maps = []
    real_map = RayExecutor.map

    def counted(self, fn, chunks, *shared, done=None):
        maps.append((getattr(fn, "func", fn).__name__, threading.current_thread().name))
        return real_map(self, fn, chunks, *shared, done=done)

    monkeypatch.setattr(RayExecutor, "map", counted)
    models_put = []
    real_put = ray.put

    def put(value, **kw):
        if hasattr(value, "num_units"):
            models_put.append(value)
        return real_put(value, **kw)

    monkeypatch.setattr(ray, "put", put)
    server = svc_start(executor="ray", executor_address="auto")
    train, candidates = svc_cameras(3), svc_cameras(6, phase=0.3)
    renderer = load_model(model)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(model, cameras=train)
        calibration = phd.calibrate(info.id, epsilon=0.05, step=0.2, samples=3, seed=1)
        direct = uq.calibrate(renderer, train, epsilon=0.05, step=0.2, samples=3, seed=1)
        assert (calibration.r_drop, calibration.ratios, calibration.errors) == (direct.r_drop, direct.ratios,
                                                                                 direct.errors)
        ranked = phd.rank(info.id, candidates, samples=6, seed=3, heatmaps="base64", top_k=3)
        expected = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=6, seed=3, top_k=3,
                                   captured=train)
        assert [(v.index, v.rank, v.sigma_max, v.score) for v in ranked.views] == \
               [(r.index, r.rank, r.sigma_max, r.score) for r in expected]
        assert all(v.heatmap_png for v in ranked.views)
        assert {name for name, _ in maps} == {"dropout_errors", "measure_views"}
        assert all(thread.startswith("phd-worker") for _, thread in maps)   # dispatched from the job workers
        assert len(models_put) == 1          # the cached model went to the object store once for all jobs

        # A job for a model deleted while it is queued or running fails cleanly (not found), whatever
        # moment the delete lands: before the job loads the model, or before it stores the calibration.
        # (A large epsilon makes the scan evaluate all 19 ratios: 19 rounds on Ray, far longer than a delete.)
        job = phd.calibrate(info.id, epsilon=1.0, step=0.05, samples=3, run_async=True, wait=False)
        phd.delete_model(info.id)
        with pytest.raises(JobFailedError) as failed:
            phd.wait_job(job.id, timeout=120)
        assert (failed.value.code, failed.value.job.state) == ("model_not_found", "failed")
        assert info.id in failed.value.message
        with pytest.raises(NotFoundError):
            phd.rank(info.id, candidates, dropout_ratio=0.2)
        assert phd.health().status == "ok"


def test_a_capture_trains_on_ray(cluster, svc_start, tmp_path, monkeypatch) -> None:
    """The capture loop's training runs as a Ray task that gets the capture's images and cameras as
    bytes (no shared file system) and returns the model file; the model is stored and measured."""
    from support.captures_loop import loop_photos

    maps = []
    real_map = RayExecutor.map

    def counted(self, fn, chunks, *shared, done=None):
        maps.append(getattr(fn, "func", fn).__name__)
        return real_map(self, fn, chunks, *shared, done=done)

    monkeypatch.setattr(RayExecutor, "map", counted)
    shots = loop_photos(tmp_path)
    server = svc_start(executor="ray", executor_address="auto", capture_max_size=shots.max_size)
    with PHDClient(server.url) as phd:
        capture = phd.create_capture(shots.initial, test=shots.test, **shots.sfm)
        summary = capture.train(iterations=20, samples=3).summary
        assert summary.test_psnr is not None and summary.r_drop is not None, summary
        assert maps[0] == "train_shipped" and {"dropout_errors", "measure_views"} <= set(maps), maps
        model = phd.get_model(summary.model_id)
        assert model.details["capture_id"] == capture.id and model.num_training_cameras == summary.train_views
