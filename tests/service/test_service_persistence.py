"""Restarts and crashes: models and calibrations survive a restart; an upload killed
mid-body (SIGKILL of `phd serve`) leaves nothing behind once the service is back."""

from __future__ import annotations

import socket
import time

import httpx

from client import PHDClient
from support.fixtures import SvcProcess, svc_cameras


def test_restart_keeps_models_and_calibrations(svc_start, svc_model_files):
    train, candidates = svc_cameras(2, size=12), svc_cameras(3, size=12, phase=0.5)
    first = svc_start()
    with PHDClient(first.url) as phd:
        ply = phd.upload_model(svc_model_files["ply"], cameras=train)
        nerf = phd.upload_model(svc_model_files["nerf"])
        calibration = phd.calibrate(ply.id, epsilon=0.5, step=0.5, samples=2)
        before = phd.rank(ply.id, candidates, samples=3)      # the default strategy stores what the training views saw
        models = {m.id: m for m in phd.list_models()}
    first.stop()
    assert (first.settings.data_dir / "models" / f"{ply.id}.ply.phd-cache").is_dir()

    second = svc_start()  # same data directory
    with PHDClient(second.url) as phd:
        assert {m.id: m for m in phd.list_models()} == models
        assert phd.get_model(ply.id).calibration == calibration
        assert phd.get_model(nerf.id).num_training_cameras == 3
        after = phd.rank(ply.id, candidates, samples=3)  # uses the calibration and coverage stored before the restart
        assert after.ratio_source == "calibration" and after == before
        phd.delete_model(nerf.id)
    second.stop()
    third = svc_start()
    with PHDClient(third.url) as phd:
        assert [m.id for m in phd.list_models()] == [ply.id]


def test_killed_upload_leaves_nothing(tmp_path, svc_model_files, svc_start):
    data_dir = tmp_path / "data"
    server = SvcProcess(data_dir)
    try:
        declared = 20_000_000
        head = (b"--xyz\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.ply\"\r\n\r\n"
                + svc_model_files["ply"].read_bytes())
        request = (f"POST /v1/models HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {declared}\r\n"
                   "Content-Type: multipart/form-data; boundary=xyz\r\n\r\n").encode()
        with socket.create_connection(("127.0.0.1", server.port)) as sock:
            sock.sendall(request + head + bytes(1_000_000))
            deadline = time.monotonic() + 30
            while not any(p.stat().st_size > 500_000 for p in (data_dir / "tmp").iterdir()):
                assert time.monotonic() < deadline, "the upload never reached the temp file"
                time.sleep(0.05)
            server.kill()  # SIGKILL in the middle of the body
        assert len(list((data_dir / "tmp").iterdir())) == 1  # the crash left a partial upload
    finally:
        server.kill()

    restarted = svc_start(data_dir=data_dir)
    assert httpx.get(f"{restarted.url}/v1/models").json() == {"models": []}
    assert list((data_dir / "tmp").iterdir()) == [] and list((data_dir / "models").iterdir()) == []
    with PHDClient(restarted.url) as phd:  # and the service works as before
        assert phd.upload_model(svc_model_files["ply"]).num_units == 300


def test_startup_sweeps_orphans_and_keeps_models(svc_start, svc_model_files):
    first = svc_start()
    with PHDClient(first.url) as phd:
        kept = phd.upload_model(svc_model_files["ply"])
    first.stop()
    data = first.settings.data_dir
    (data / "tmp" / "upload-dead.part").write_bytes(b"ply\nhalf")        # crash while receiving
    (data / "models" / "0123456789abcdef.ply").write_bytes(b"ply\nfull")  # crash between rename and insert
    (data / "models" / "0123456789abcdef.ply.phd-cache").mkdir()          # and what was derived from it
    second = svc_start()
    assert sorted(p.name for p in (data / "models").iterdir()) == [kept.id + ".ply"]
    assert list((data / "tmp").iterdir()) == []
    with PHDClient(second.url) as phd:
        assert phd.rank(kept.id, svc_cameras(1, size=8), samples=2, dropout_ratio=0.1).num_candidates == 1
