"""Models uploaded as the folders their trainers wrote (service.folders), through a real server:
the same model, cameras, background and pose convention as the Python client reads from the
same folder (which uploads the splats it reads as a PLY written by the same writer, so the two
stored files are byte for byte the same); zips that point outside or inflate past the budget
refused; and ranked poses downloaded exactly as `phd rank --export` writes them."""

from __future__ import annotations

import io
import json
import os
import warnings
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest

from client import PHDClient
from phd_cli import main as phd
from phd_core.data import POSES
from phd_core.renderers.outputs import read_output
from service.budget import largest_model_file
from service.errors import ServiceError
from service.folders import unpack_zip
from support.captures import write_output_folder
from support.fixtures import svc_cameras, svc_random_gaussians
from support.trainers import gsplat_scene, splatfacto_scene


def _zip(root: Path, under: Path | None = None) -> bytes:
    """The files under `root` as a zip (paths relative to `under`, default root's parent: the
    folder itself is the zip's top entry, as an archiver makes it)."""
    buffer = io.BytesIO()
    base = under or root.parent
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zipped:
        for path in sorted(root.rglob("*")):
            if path.is_file():
                zipped.write(path, path.relative_to(base).as_posix())
    return buffer.getvalue()


def _files(root: Path) -> list[tuple[str, tuple[str, bytes]]]:
    """The files under `root` as `files` parts named by their path, as a browser's folder pick sends them."""
    return [("files", (path.relative_to(root.parent).as_posix(), path.read_bytes()))
            for path in sorted(root.rglob("*")) if path.is_file()]


def _leftovers(server) -> list[str]:
    return sorted(p.name for p in (server.settings.data_dir / "tmp").iterdir())


@pytest.mark.parametrize("trainer", ["phd train", "reference 3DGS", "splatfacto", "gsplat"])
def test_a_folder_uploads_as_the_client_reads_it(svc_start, svc_trained, tmp_path, trainer) -> None:
    if trainer == "phd train":
        folder, zip_root = tmp_path / "run", None
        folder.mkdir()
        for name in ("model.ply", "model.json"):
            (folder / name).write_bytes((svc_trained.parent / name).read_bytes())
        source = folder / "model.ply"
    elif trainer == "reference 3DGS":
        folder = source = write_output_folder(tmp_path / "output" / "lego", svc_random_gaussians(200),
                                              svc_cameras(3), white=True)
        zip_root = None
    else:   # the capture the run read travels in the zip beside the run, where its config says
        scene = splatfacto_scene(tmp_path, export_ply=False) if trainer == "splatfacto" else gsplat_scene(tmp_path)
        folder = source = scene["folder"]
        zip_root = tmp_path
    server = svc_start()
    with PHDClient(server.url) as client:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")        # the readers' notes, issued as Python warnings
            expected = client.upload_model(source)
        expected_frames = client.training_cameras(expected.id)
        client.delete_model(expected.id)            # else the same model again answers the stored one
        zipped = _zip(zip_root or folder, zip_root.parent if zip_root else None)
        uploads = [{"archive": ("run.zip", zipped)}]
        if trainer in ("phd train", "reference 3DGS"):   # also picked as a folder, one part per file
            uploads.append(_files(folder))
        for parts in uploads:
            answer = httpx.post(f"{server.url}/v1/models", files=parts, timeout=120)
            assert answer.status_code == 201, answer.text
            got = answer.json()
            assert got["sha256"] == expected.sha256 and got["num_units"] == expected.num_units
            assert got["camera_format"] == expected.camera_format
            assert got["num_training_cameras"] == expected.num_training_cameras > 0
            assert got["details"]["background"] == expected.details["background"]
            assert np.allclose([f["transform_matrix"] for f in client.training_cameras(got["id"])],
                               [f["transform_matrix"] for f in expected_frames], atol=1e-9)
            client.delete_model(got["id"])
    if trainer == "phd train":     # what its sidecar says, and where the background came from
        sidecar = json.loads((folder / "model.json").read_text())
        assert got["camera_format"] == sidecar["dataset_format"] == "blender"
        assert got["details"]["background"] == sidecar["background"]
        assert got["details"]["background_source"] == "the sidecar its trainer wrote"
        assert got["name"] == "run"                 # the folder's, not the file's (model.ply every time)
    else:
        assert got["name"] == expected.name         # the run's name, as the client gives it
        # What the reader noted (the frame it undid, the checkpoint it read) is kept with the model.
        assert bool(got["details"].get("notes")) == (trainer != "reference 3DGS")
    assert _leftovers(server) == []


@pytest.mark.parametrize("trainer", ["splatfacto", "gsplat"])
def test_a_folder_is_read_without_a_capture_outside_the_upload(svc_start, tmp_path, trainer) -> None:
    """A run's config names its capture by a path; uploaded alone, the service must not find that
    path on its own disk (here the capture sits, readable, beside the run on the server's disk,
    and the config names it by its absolute path): the model arrives without training cameras."""
    scene = splatfacto_scene(tmp_path, export_ply=False) if trainer == "splatfacto" else gsplat_scene(tmp_path)
    config = scene["folder"] / ("config.yml" if trainer == "splatfacto" else "cfg.yml")
    named = "- data\n- desk" if trainer == "splatfacto" else "data/garden"      # YAML of a PosixPath, or a string
    capture = tmp_path / "data" / ("desk" if trainer == "splatfacto" else "garden")
    text = config.read_text()
    assert named in text and capture.is_dir()
    config.write_text(text.replace(named, f"- {capture}" if trainer == "splatfacto" else str(capture)))
    assert read_output(scene["folder"]).cameras                 # read where it lies, the run has its cameras
    server = svc_start()
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("run.zip", _zip(scene["folder"]))}, timeout=120)
    assert answer.status_code == 201, answer.text
    assert answer.json()["num_training_cameras"] == 0
    assert _leftovers(server) == []


def test_the_sidecar_as_the_cameras_field_gives_its_cameras_background_and_format(svc_start, svc_trained) -> None:
    server = svc_start()
    sidecar = svc_trained.with_name("model.json")
    with open(svc_trained, "rb") as f:
        answer = httpx.post(f"{server.url}/v1/models", files={"file": ("model.ply", f)},
                            data={"cameras": sidecar.read_text()}, timeout=60)
    assert answer.status_code == 201, answer.text
    data = json.loads(sidecar.read_text())
    got = answer.json()
    assert got["num_training_cameras"] == len(data["training_cameras"]) == 4
    assert got["camera_format"] == "blender" and got["details"]["background"] == data["background"]
    with PHDClient(server.url) as client:
        assert client.training_cameras(got["id"]) == data["training_cameras"]


@pytest.mark.parametrize("member", ["../outside.ply", "/etc/outside.ply", "run/../../outside.ply", "C:/outside.ply",
                                    "run/\\..\\..\\outside.ply"])
def test_a_zip_member_pointing_outside_the_folder_is_refused(svc_start, tmp_path, member) -> None:
    server = svc_start()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zipped:
        zipped.writestr(member, b"ply\n")
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("evil.zip", buffer.getvalue())})
    assert answer.status_code == 422 and answer.json()["error"]["field"] == "archive"
    assert "not a path inside the folder" in answer.json()["error"]["message"]
    assert not (server.settings.data_dir / "outside.ply").exists() and not Path("/etc/outside.ply").exists()
    assert _leftovers(server) == []


def test_a_zip_that_inflates_past_the_budget_or_like_a_bomb_is_refused(svc_start) -> None:
    budget = 64 << 20
    server = svc_start(memory_budget_bytes=budget)
    cap = largest_model_file(budget)
    block = (b"\0" * 900 + os.urandom(100))                     # inflates about 10 times: no bomb, just big
    big = io.BytesIO()
    with zipfile.ZipFile(big, "w", zipfile.ZIP_DEFLATED) as zipped:
        for k in range(3):
            zipped.writestr(f"run/part{k}.bin", block * (cap // 2 // len(block)))
    assert len(big.getvalue()) < cap < 3 * (cap // 2)           # the upload fits; what it unpacks to does not
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("big.zip", big.getvalue())}, timeout=60)
    assert answer.status_code == 413 and answer.json()["error"]["field"] == "archive", answer.text
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zipped:
        zipped.writestr("run/model.ply", b"\0" * (8 << 20))   # 8 MiB of zeros inflate about 1,000 times
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("bomb.zip", bomb.getvalue())}, timeout=60)
    assert answer.status_code == 422 and "zip bomb" in answer.json()["error"]["message"], answer.text
    assert _leftovers(server) == []


def test_a_zip_unpacks_only_into_the_room_kept_free(tmp_path) -> None:
    """What a zip inflates to counts against the disk's room outside PHD_KEEP_FREE_BYTES: past
    it the upload is 507 naming the archive (the compressed upload alone fitted)."""
    archive = tmp_path / "run.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zipped:
        zipped.writestr("run/model.ply", os.urandom(4096))
    folder = tmp_path / "unpacked"
    folder.mkdir()
    with pytest.raises(ServiceError) as refused:
        unpack_zip(archive, folder, max_bytes=1 << 20, room=1000)
    assert refused.value.status == 507 and refused.value.field == "archive"
    assert unpack_zip(archive, tmp_path / "roomy", max_bytes=1 << 20, room=1 << 20) == 4096


def test_a_run_at_the_zips_top_is_named_after_the_zip_and_errors_name_its_files(svc_start, tmp_path) -> None:
    """A zip holding a run's files at its top (no folder around them): the model is named after
    the zip, not the server's temp folder; a reader's error names the upload's files, never where
    the server unpacked them."""
    folder = write_output_folder(tmp_path / "output" / "lego", svc_random_gaussians(200), svc_cameras(3))
    server = svc_start()
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("bench.zip", _zip(folder, folder))}, timeout=60)
    assert answer.status_code == 201, answer.text
    assert answer.json()["name"] == "bench/3dgs"
    broken = gsplat_scene(tmp_path / "g")["folder"]
    checkpoint = next((broken / "ckpts").glob("ckpt_*.pt"))
    checkpoint.write_bytes(b"not a checkpoint")
    for other in (broken / "ckpts").glob("ckpt_*.pt"):
        if other != checkpoint:
            other.unlink()
    answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("g.zip", _zip(broken))}, timeout=60)
    error = answer.json()["error"]
    assert answer.status_code == 422 and error["field"] == "archive", answer.text
    assert checkpoint.name in error["message"] and str(server.settings.data_dir) not in error["message"]
    assert "/tmp" not in error["message"] and "upload-" not in error["message"]
    assert _leftovers(server) == []


def test_a_folder_without_one_model_says_what_it_holds(svc_start, svc_model_files) -> None:
    server = svc_start()
    none = httpx.post(f"{server.url}/v1/models", files=[("files", ("run/notes.txt", b"hello"))])
    assert none.status_code == 422 and "holds no model" in none.json()["error"]["message"]
    two = httpx.post(f"{server.url}/v1/models", files=[
        ("files", (f"run/{name}.ply", svc_model_files[name].read_bytes())) for name in ("ply", "ply_b")])
    assert two.status_code == 422 and "holds 2 models (run/ply.ply, run/ply_b.ply)" in two.json()["error"]["message"]
    both = httpx.post(f"{server.url}/v1/models", files=[("file", ("a.ply", svc_model_files["ply"].read_bytes())),
                                                       ("files", ("run/a.ply", b"ply"))])
    assert both.status_code == 422 and both.json()["error"]["field"] == "files"
    assert _leftovers(server) == []


def test_downloaded_poses_are_what_phd_rank_export_writes(svc_start, svc_trained, tmp_path) -> None:
    """`phd rank --export` and the service's download write the same bytes for the same ranking,
    in every pose convention."""
    server = svc_start()
    with PHDClient(server.url) as client:
        model = client.upload_model(svc_trained)
    for name, convention in POSES.items():
        export = tmp_path / name / (convention.file_name or ("colmap" if convention.suffix == "" else "poses.json"))
        ranking = tmp_path / f"{name}.json"
        assert phd(["rank", "--model", str(svc_trained), "--candidates", "orbit:5", "--dropout-ratio", "0.1",
                    "--samples", "2", "--downscale", "4", "--top-k", "3", "--export", str(export),
                    "--export-format", name, "--out", str(ranking)]) == 0
        ranked = json.loads(ranking.read_text())["ranking"]
        body = {"cameras": [r["camera"] for r in ranked], "indices": [r["index"] for r in ranked], "format": name}
        answer = httpx.post(f"{server.url}/v1/models/{model.id}/poses", json=body)
        assert answer.status_code == 200, answer.text
        if export.is_dir():
            assert answer.headers["content-type"] == "application/zip"
            files = zipfile.ZipFile(io.BytesIO(answer.content))
            assert {n: files.read(n) for n in files.namelist()} == {
                f"colmap/{p.name}": p.read_bytes() for p in export.iterdir()}
        else:
            assert answer.content == export.read_bytes()
            assert answer.headers["content-disposition"] == \
                f'attachment; filename="{convention.file_name or "transforms.json"}"'
    # Without a format, the model's own: its sidecar's capture was a Blender scene (ranks from 1).
    own = httpx.post(f"{server.url}/v1/models/{model.id}/poses", json={"cameras": body["cameras"]})
    assert own.headers["content-disposition"] == 'attachment; filename="transforms_train.json"'
    assert [f["file_path"] for f in own.json()["frames"]] == [f"./images/rank00{k + 1}_candidate000{k}"
                                                              for k in range(3)]
    wrong = httpx.post(f"{server.url}/v1/models/{model.id}/poses", json={**body, "indices": [1]})
    assert wrong.status_code == 422 and "one index per camera" in wrong.json()["error"]["message"]


def test_a_folder_left_by_a_crash_is_swept_at_start(svc_start, tmp_path) -> None:
    """An upload's folder outlives its server only if the process died mid-upload: the next start removes it."""
    left = tmp_path / "data" / "tmp" / "upload-0123.folder" / "run"
    left.mkdir(parents=True)
    (left / "model.ply").write_bytes(b"ply\n")
    (left.parent.with_name("upload-0123.folder.zip")).write_bytes(b"PK")
    server = svc_start()
    assert _leftovers(server) == []


@pytest.mark.parametrize("fit, field", [(float("nan"), "training_fit.psnr"), ("x" * 5000, "training_fit.psnr")])
def test_a_sidecars_record_of_its_capture_is_checked_before_it_is_stored(svc_start, svc_trained, tmp_path, fit,
                                                                          field) -> None:
    """The capture record a sidecar carries reaches the model's facts, which every answer about
    the model shows: a NaN there made each of them a 500 (JSON has no NaN), a long text a long
    answer. Uploaded with its PLY, the folder is refused with 422 naming the field."""
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "model.ply").write_bytes(svc_trained.read_bytes())
    sidecar = json.loads(svc_trained.with_name("model.json").read_text())
    sidecar["training_fit"]["psnr"] = fit
    (folder / "model.json").write_text(json.dumps(sidecar))
    server = svc_start()
    answer = httpx.post(f"{server.url}/v1/models", files=_files(folder), timeout=60)
    assert answer.status_code == 422, answer.text
    assert field in answer.text
    assert httpx.get(f"{server.url}/v1/models", timeout=30).status_code == 200


def test_uploads_are_named_by_their_sidecar_or_folder_and_a_repeat_answers_the_stored_model(svc_start, svc_trained,
                                                                                           tmp_path) -> None:
    """`phd train`'s model.ply is named by its sidecar ("<run folder>/model"), a zip or a picked
    folder by the folder, never "model.ply"; the same bytes with the same cameras, background
    and capture format again answer the stored model (200 and a note, no new entry), through
    the client and REST alike, while another background makes another model."""
    server = svc_start()
    sidecar = svc_trained.with_name("model.json")
    with PHDClient(server.url) as client:
        first = client.upload_model(svc_trained)
        assert first.name == f"{svc_trained.parent.name}/model" and first.note is None
        again = client.upload_model(svc_trained, name="another name")
        assert again.id == first.id and again.name == first.name and "no new entry" in (again.note or "")
        # As the page sends them: the PLY, and the sidecar as its cameras.
        answer = httpx.post(f"{server.url}/v1/models", files={"file": ("model.ply", svc_trained.read_bytes())},
                            data={"cameras": sidecar.read_text()})
        assert answer.status_code == 200 and answer.json()["id"] == first.id and "no new entry" in answer.json()["note"]
        other = client.upload_model(svc_trained, background="black")
        assert other.id != first.id and other.note is None
        assert sorted(m.id for m in client.list_models()) == sorted([first.id, other.id])
        for model in (first, other):
            client.delete_model(model.id)

    run = tmp_path / "desk_run"
    run.mkdir()
    for path in (svc_trained, sidecar):
        (run / path.name).write_bytes(path.read_bytes())
    for parts, name in (({"archive": ("desk_run.zip", _zip(run))}, "desk_run"),             # the folder inside
                        ({"archive": ("flat.zip", _zip(run, under=run))}, "flat"),          # its files at the top
                        (_files(run), "desk_run")):                                         # picked as a folder
        answer = httpx.post(f"{server.url}/v1/models", files=parts, timeout=120)
        assert answer.status_code == 201 and answer.json()["name"] == name, answer.text
        httpx.delete(f"{server.url}/v1/models/{answer.json()['id']}")


def test_a_folder_brings_the_calibration_phd_stored_for_its_model_and_cameras(svc_start, svc_trained,
                                                                               tmp_path, capsys) -> None:
    """What `phd train` wrote, calibrated by `phd calibrate` (its model.ply.phd-cache/), zipped: the
    stored calibration is the model's (same file, cameras and background), said in its notes; one
    made on other cameras (at half their size) is not used, and the notes say why."""
    import shutil

    run = tmp_path / "run"
    run.mkdir()
    for path in (svc_trained, svc_trained.with_name("model.json")):
        shutil.copy(path, run / path.name)
    calibrate = ["calibrate", "--model", str(run / "model.ply"), "--samples", "2", "--quiet", "--out"]
    assert phd([*calibrate, str(tmp_path / "full.json")]) == 0
    r_drop = json.loads((tmp_path / "full.json").read_text())["r_drop"]
    server = svc_start()
    used = httpx.post(f"{server.url}/v1/models", files=[("archive", ("run.zip", _zip(run)))], timeout=60)
    assert used.status_code == 201, used.text
    assert used.json()["calibration"]["r_drop"] == r_drop
    assert any("not run again" in note for note in used.json()["details"]["notes"])

    httpx.delete(f"{server.url}/v1/models/{used.json()['id']}")     # else the same model answers again
    for entry in (run / "model.ply.phd-cache").glob("calibration-*.json"):
        entry.unlink()
    assert phd([*calibrate, str(tmp_path / "half.json"), "--downscale", "2"]) == 0
    capsys.readouterr()
    other = httpx.post(f"{server.url}/v1/models", files=[("archive", ("run.zip", _zip(run)))], timeout=60)
    assert other.status_code == 201, other.text
    assert other.json()["calibration"] is None
    assert any("made on other training cameras" in note for note in other.json()["details"]["notes"])
