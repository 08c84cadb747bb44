"""A full disk (issue 36): the data directory on a real small tmpfs, filled by the test. Every
write the service makes answers 507 `insufficient_storage` naming what it could not write,
leaves nothing half-written (files and rows), keeps serving what was stored before, and works
again once space returns. Mounting needs root (CI runs as root); elsewhere these tests skip."""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import time
from contextlib import closing
from pathlib import Path

import httpx
import pytest

from client import PHDClient
from client.client import JobFailedError, ServerError
from phd_core.errors import InputError
from service.app import create_app
from service.settings import Settings
from service.store import DB_NAME
from support.fixtures import expect_error, svc_cameras

DISK_BYTES = 8 << 20
CUP = Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap" / "images"


class Disk:
    """A tmpfs of DISK_BYTES mounted for one test; `fill` takes its free space, `free` gives it back."""

    def __init__(self, root: Path):
        self.root = root
        self.filler = root / "filler"

    def fill(self, leave: int = 0) -> None:
        """Fill the disk, then give back `leave` bytes (tmpfs counts whole 4 KiB pages)."""
        with open(self.filler, "ab", buffering=0) as f:
            for block in (1 << 20, 1 << 12):
                try:
                    while True:
                        f.write(bytes(block))
                except OSError:
                    pass
            if leave:
                f.truncate(max(0, f.tell() - leave))
        assert os.statvfs(self.root).f_bavail * os.statvfs(self.root).f_frsize <= leave + 4096

    def free(self) -> None:
        self.filler.unlink()

    def files(self, folder: str) -> list[str]:
        return sorted(str(p.relative_to(self.root / "data" / folder)) for p in (self.root / "data" / folder).rglob("*")
                      if p.is_file())


@pytest.fixture
def disk(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs for a full disk needs root (CI runs the tests as root)")
    root = tmp_path / "disk"
    root.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK_BYTES}", "tmpfs", str(root)], check=True)
    yield Disk(root)
    subprocess.run(["umount", "-l", str(root)], check=True)


@pytest.fixture
def served(disk, svc_start, svc_model_files):
    """A service on the small disk with a calibrated model, a ranking with heat maps stored as
    artefacts, and its client: (server, client, model, job id, its heat map bytes)."""
    server = svc_start(data_dir=disk.root / "data", keep_free_bytes=0)
    phd = PHDClient(server.url, timeout=120)
    model = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3, size=12))
    phd.calibrate(model.id, epsilon=0.5, step=0.5, samples=2)
    job = phd.rank(model.id, svc_cameras(2, size=12, phase=0.5), samples=2, heatmaps="files", run_async=True,
                   wait=False)
    ranked = phd.wait_job(job.id)
    heatmap = phd.download(ranked.views[0].heatmap_url)
    yield server, phd, phd.get_model(model.id), job.id, heatmap
    phd.close()


def stored_as_before(phd: PHDClient, model, job_id: str, heatmap: bytes) -> None:
    """What was stored before the disk filled is served unchanged."""
    assert phd.list_models() == [model]
    assert phd.get_model(model.id).calibration == model.calibration
    assert phd.get_job(job_id).state == "succeeded"
    ranked = phd.get_job(job_id).result
    assert phd.download(ranked.views[0].heatmap_url) == heatmap


def no_partial_files(disk: Disk, model_ids: list[str], job_ids: list[str]) -> None:
    assert disk.files("tmp") == []
    models = disk.files("models")       # each model's file, and what a rank stored beside it (whole entries)
    assert [name.split(".")[0] for name in models if ".phd-cache/" not in name] == sorted(model_ids)
    assert all(re.fullmatch(r"[0-9a-f]+\.ply\.phd-cache/captured-coverage-[0-9a-f]+\.(pt|json)", name)
               for name in models if ".phd-cache/" in name)
    assert sorted({name.split("/")[0] for name in disk.files("jobs")}) == sorted(job_ids)
    with closing(sqlite3.connect(disk.root / "data" / DB_NAME)) as db:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        assert sorted(r[0] for r in db.execute("SELECT id FROM models")) == sorted(model_ids)


def test_an_upload_on_a_full_disk_is_507_and_leaves_nothing(disk, served, svc_model_files):
    server, phd, model, job_id, heatmap = served
    disk.fill()
    with pytest.raises(ServerError) as refused:           # refused by its Content-Length, before it is read
        phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(3, size=12))
    assert (refused.value.status, refused.value.code, refused.value.field) == (507, "insufficient_storage", "file")
    assert "the upload (" in refused.value.message and "could not be written" in refused.value.message
    stored_as_before(phd, model, job_id, heatmap)
    no_partial_files(disk, [model.id], [job_id])
    with pytest.raises(ServerError) as refused:           # a delete writes too: refused whole, the model kept
        phd.delete_model(model.id)
    assert refused.value.status == 507 and f"the removal of model '{model.id}'" in refused.value.message
    stored_as_before(phd, model, job_id, heatmap)
    scraped = httpx.get(f"{server.url}/metrics").text      # the operator sees it, also on a full disk
    assert 'phd_error_answers_total{code="insufficient_storage",status="507"} 2.0' in scraped

    disk.free()                                   # space returns: the same upload succeeds
    again = phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(3, size=12))
    assert phd.get_model(again.id).num_units == 200
    phd.delete_model(model.id)
    assert phd.list_models() == [phd.get_model(again.id)]


BOUNDARY = "b0undary"
FILE_PART = f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"b.ply\"\r\n\r\n".encode()


def upload_filling_the_disk(url: str, disk: Disk, first: bytes, rest: bytes, written: int) -> httpx.Response:
    """POST a multipart upload in two steps: `first`, then (once the server's temp file holds
    `written` bytes) the disk is filled and `rest` follows."""
    tmp = disk.root / "data" / "tmp"

    def parts():
        yield first
        deadline = time.monotonic() + 30
        while not any(tmp.iterdir()) or sum(p.stat().st_size for p in tmp.iterdir()) < written:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        disk.fill()
        for i in range(0, len(rest), 1 << 16):
            yield rest[i:i + (1 << 16)]

    return httpx.post(f"{url}/v1/models", content=parts(), timeout=60,
                      headers={"content-type": f"multipart/form-data; boundary={BOUNDARY}"})


def test_a_disk_that_fills_during_an_upload_is_507_and_leaves_nothing(disk, served, svc_model_files):
    """The disk fills while the model's parts stream in (another writer took the space): the
    write that finds no room is 507 naming the model file, and its temp file goes."""
    server, phd, model, job_id, heatmap = served
    body = FILE_PART + svc_model_files["ply_b"].read_bytes() + bytes(1 << 20) + f"\r\n--{BOUNDARY}--\r\n".encode()
    answer = upload_filling_the_disk(server.url, disk, body[:1 << 14], body[1 << 14:], written=0)
    error = expect_error(answer, 507, "insufficient_storage", "file")
    assert "the uploaded model file could not be written" in error["message"]
    stored_as_before(phd, model, job_id, heatmap)
    no_partial_files(disk, [model.id], [job_id])
    disk.free()
    assert phd.upload_model(svc_model_files["ply_b"]).num_units == 200


def test_a_model_whose_record_does_not_fit_is_507_and_its_file_is_removed(disk, served, svc_model_files):
    """The model's file is written, then the disk fills: its row (with 60 training cameras) does not
    fit, as SQLite's write-ahead journal cannot grow. The file moved into models/ goes again, no row
    stays, and the database is intact."""
    server, phd, model, job_id, heatmap = served
    ply = svc_model_files["ply_b"].read_bytes()
    cameras = json.dumps([c.to_frame() for c in svc_cameras(60, size=12)]).encode()
    rest = (f"\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"cameras\"\r\n\r\n".encode() + cameras
            + f"\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"name\"\r\n\r\nmany cameras"
              f"\r\n--{BOUNDARY}--\r\n".encode())
    answer = upload_filling_the_disk(server.url, disk, FILE_PART + ply, rest, written=len(ply))
    error = expect_error(answer, 507, "insufficient_storage", "file")
    assert "the record of model 'many cameras' could not be written" in error["message"]
    stored_as_before(phd, model, job_id, heatmap)
    no_partial_files(disk, [model.id], [job_id])
    disk.free()
    assert phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(60, size=12)).num_training_cameras == 60


def _job_fills_the_disk(disk: Disk, phd: PHDClient, job) -> JobFailedError:
    """Fill the disk as soon as the job's running state is stored (its work has begun), then wait
    for its end."""
    deadline = time.monotonic() + 120
    with closing(sqlite3.connect(disk.root / "data" / DB_NAME)) as db:
        while db.execute("SELECT state FROM jobs WHERE id = ?", (job.id,)).fetchone() != ("running",):
            assert time.monotonic() < deadline and phd.get_job(job.id).state in ("queued", "running")
            time.sleep(0.005)
    disk.fill()
    with pytest.raises(JobFailedError) as failed:
        phd.wait_job(job.id, poll_interval=0.05)
    return failed.value


# Each write a job makes at its end: the calibration (a row), heat maps and selected images (files),
# and a result (the job's row).
JOB_WRITES = {
    "calibration": "the calibration of model",
    "heatmap": "the artefact 'heatmap_",
    "selected image": "the artefact 'selected_",
    "result": "the succeeded state of job",
}


@pytest.mark.parametrize("write", JOB_WRITES)
def test_a_job_whose_output_does_not_fit_fails_507_and_leaves_nothing(disk, served, svc_model_files, write):
    server, phd, model, job_id, heatmap = served
    many = svc_cameras(32, size=40, phase=0.25)    # long enough to fill the disk while it runs
    if write == "calibration":
        job = phd.calibrate(model.id, cameras=many, epsilon=0.5, step=0.1, samples=8, run_async=True, wait=False)
    elif write == "selected image":
        job = phd.select(model.id, model.id, many, samples=8, ratio_a=0.1, ratio_b=0.2, rule="sigma_mean",
                         images="files", run_async=True, wait=False)
    else:
        job = phd.rank(model.id, many, samples=8, heatmaps="files" if write == "heatmap" else "base64",
                       run_async=True, wait=False)
    failed = _job_fills_the_disk(disk, phd, job)
    assert failed.code == "insufficient_storage" and JOB_WRITES[write] in failed.message
    assert phd.get_job(job.id).state == "failed"          # the failed state answers, from memory if not on disk
    stored_as_before(phd, model, job_id, heatmap)
    no_partial_files(disk, [model.id], [job_id])

    disk.free()                                           # space returns: the same work succeeds and is stored
    if write == "calibration":
        calibration = phd.calibrate(model.id, cameras=many, epsilon=0.5, step=0.1, samples=8)
        assert phd.get_model(model.id).calibration == calibration
    else:
        done = phd.rank(model.id, many[:2], samples=2, heatmaps="files", run_async=True, wait=False)
        assert phd.download(phd.wait_job(done.id).views[0].heatmap_url).startswith(b"\x89PNG")


def test_a_job_that_cannot_be_queued_is_507(disk, served):
    """On a full disk even the queued job's row does not fit: the request is refused before any work."""
    server, phd, model, job_id, heatmap = served
    disk.fill()
    body = {"cameras": [c.to_frame() for c in svc_cameras(1, size=12)], "samples": 2}
    error = expect_error(httpx.post(f"{server.url}/v1/models/{model.id}/rank", json=body, timeout=60), 507,
                         "insufficient_storage")
    assert "the queued state of job" in error["message"]
    stored_as_before(phd, model, job_id, heatmap)
    with closing(sqlite3.connect(disk.root / "data" / DB_NAME)) as db:
        assert db.execute("SELECT COUNT(*) FROM jobs").fetchone() == (2,)   # the calibration and the ranking


def test_uploads_keep_the_free_space_setting(disk, svc_start, svc_model_files):
    """PHD_KEEP_FREE_BYTES: an upload that would leave less free is refused up front by its
    Content-Length, or as it streams without one; smaller ones are stored."""
    server = svc_start(data_dir=disk.root / "data", keep_free_bytes=DISK_BYTES - (2 << 20))
    big = svc_model_files["ply"].read_bytes() + bytes(3 << 20)
    url = f"{server.url}/v1/models"
    error = expect_error(httpx.post(url, files={"file": ("big.ply", big)}, timeout=60), 507, "insufficient_storage",
                         "file")
    assert "kept free" in error["message"] and "the upload (" in error["message"]

    body = FILE_PART + big + f"\r\n--{BOUNDARY}--\r\n".encode()
    streamed = httpx.post(                        # no Content-Length: refused as the bytes arrive
        url, content=(body[i:i + (1 << 16)] for i in range(0, len(body), 1 << 16)),
                          headers={"content-type": f"multipart/form-data; boundary={BOUNDARY}"}, timeout=60)
    assert "the model file (" in expect_error(streamed, 507, "insufficient_storage", "file")["message"]
    assert Disk(disk.root).files("tmp") == [] and Disk(disk.root).files("models") == []
    with PHDClient(server.url) as phd:
        assert phd.upload_model(svc_model_files["ply"]).num_units == 300


def test_a_start_on_a_full_disk_says_so_and_the_next_start_serves(disk, svc_start, svc_model_files):
    """SQLite needs room for its log's index (32 KiB) to open the store: on a full disk the start
    is refused with a clear message, nothing changed; once space returns the store is served."""
    server = svc_start(data_dir=disk.root / "data", keep_free_bytes=0)
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
    server.stop()
    disk.fill()
    with pytest.raises(InputError) as refused:
        create_app(Settings(data_dir=disk.root / "data"))
    assert refused.value.field == "data_dir" and "is full" in refused.value.reason
    disk.free()
    with PHDClient(svc_start(data_dir=disk.root / "data").url) as phd:
        assert phd.list_models() == [model]


def test_photos_for_a_capture_on_a_full_disk_are_507_and_leave_nothing(disk, served, tmp_path):
    """A capture's photos: refused as they stream (or by their length) when the disk is full, and
    before structure-from-motion when what it would write does not fit; nothing is kept."""
    server, phd, model, job_id, heatmap = served
    photos = tmp_path / "photos"
    photos.mkdir()
    for n in range(18, 22):
        (photos / f"{n}.jpg").write_bytes((CUP / f"{n}.jpg").read_bytes())
    disk.fill()
    with pytest.raises(ServerError) as refused:
        phd.create_capture(photos)
    assert (refused.value.status, refused.value.code, refused.value.field) == (507, "insufficient_storage", "photos")
    disk.free()
    disk.fill(leave=2 << 20)        # room for the photos, not for what structure-from-motion writes
    with pytest.raises(ServerError) as refused:
        phd.create_capture(photos)
    assert (refused.value.status, refused.value.field) == (507, "photos")
    assert "the reconstruction of 4 photos" in refused.value.message
    assert phd.list_captures() == [] and disk.files("captures") == []
    stored_as_before(phd, model, job_id, heatmap)
    no_partial_files(disk, [model.id], [job_id])
