"""Folder uploads that cannot bomb (issue 46), through real servers, with files the builders
make (tests/support/trainers.py, archives.py): each case the probe found answers a 4xx naming
the file and the rule. Those that inflated are refused before they take memory: a separate
`phd serve` under a 256 MiB budget peaks within it (its own /proc VmHWM over its RSS before the
request). That server's log is /dev/full, so every log write fails: no request may fail with it."""

from __future__ import annotations

import re
import warnings
import zipfile
from pathlib import Path
from typing import Callable

import httpx
import pytest

from client import PHDClient
from phd_core.errors import NOTE_CHARS, ModelWarning
from support.archives import BOMBS, Member, folder_files, gsplat_zip, raw_zip, stored, zero_checkpoint, zip_of
from support.captures import write_output_folder
from support.fixtures import SvcProcess, expect_error, proc_bytes, svc_cameras, svc_random_gaussians
from support.fuzz import alias_bomb
from support.trainers import gsplat_scene, splatfacto_scene

BUDGET = 256 << 20
DEEP_JSON = b"[" * 100_000 + b"]" * 100_000


@pytest.fixture(scope="module")
def full_log_server(tmp_path_factory):
    """`phd serve` under a 256 MiB budget keeping one idle model, its log (stderr) on /dev/full."""
    server = SvcProcess(tmp_path_factory.mktemp("bombs") / "data", log=Path("/dev/full"),
                        PHD_MEMORY_BUDGET_BYTES=str(BUDGET), PHD_CACHE_SIZE="1", OMP_NUM_THREADS="1")
    yield server
    server.kill()


def _upload(url: str, archive: bytes) -> httpx.Response:
    return httpx.post(f"{url}/v1/models", files={"archive": ("run.zip", archive)}, timeout=300)


def _scene_zip(root: Path, change: Callable[[Path], None]) -> bytes:
    """The files under `root` (a run and the capture beside it) zipped after `change(root)`,
    stored (brackets nested 100,000 deep deflate like a zip bomb)."""
    change(root)
    return zip_of(folder_files(root, root), zipfile.ZIP_STORED)


# ----------------------------------------------------------------------------- what inflated

REFUSED = {   # a bomb (tests/support/archives.py): the file the answer names, the rule it names
    "20 M zero splats deflated in a checkpoint deflated again in the zip (4 KB)": ("ckpt_29999_rank0.pt", "zip bomb"),
    "20 M splats each a view of one stored zero": ("ckpt_29999_rank0.pt", "more than the"),
    "a checkpoint's pickle calling bytearray(1 GiB)": ("ckpt_29999_rank0.pt", "builtins.bytearray"),
    "1 M directory entries (47 MB)": ("run.zip", "1000000 entries"),
}


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc peak-RSS reset")
@pytest.mark.parametrize("bomb", BOMBS)
def test_an_upload_that_inflates_is_refused_before_it_takes_memory(full_log_server, bomb):
    archive = BOMBS[bomb]()
    file, rule = REFUSED[bomb]
    pid = full_log_server.proc.pid
    Path(f"/proc/{pid}/clear_refs").write_text("5")                # VmHWM starts again from VmRSS
    before = proc_bytes(pid, "VmRSS")
    answer = _upload(full_log_server.url, archive)
    peak = proc_bytes(pid, "VmHWM") - before
    assert peak < BUDGET, f"the server took {peak >> 20} MiB ({answer.text[:300]})"
    error = expect_error(answer, 422, "invalid_input", "archive")
    assert file in error["message"] and rule in error["message"], error


def test_a_checkpoint_past_the_model_cap_is_413_before_it_is_loaded(svc_start):
    # 400k zero splats (22 MB of tensors) deflated 280 times inside the checkpoint, stored in
    # the zip: no member of either zip inflates like a bomb, but the model is past the 16 MiB a
    # 64 MiB budget can load.
    server = svc_start(memory_budget_bytes=64 << 20)
    archive = gsplat_zip(zero_checkpoint(400_000, chunk=8192), zipfile.ZIP_STORED)
    error = expect_error(_upload(server.url, archive), 413, "payload_too_large", "archive")
    assert "inflates to 22400" in error["message"] and "memory budget" in error["message"]
    assert server.app.state.service.ledger.used == 0


# ----------------------------------------------------------------------------- 422 naming the file and the rule

CONFIG_VALUES = [("dataparser", "train_split_fraction", value) for value in ("abc", ".inf", ".nan", "-1")] + [
    ("dataparser", "eval_interval", value) for value in ("0", "x")] + [("model", "background_color", "[1, 2]")]


@pytest.mark.parametrize("section, key, value", CONFIG_VALUES)
def test_a_splatfacto_config_value_of_the_wrong_kind_is_422_naming_it(svc_start, tmp_path, section, key, value):
    def wrong(root: Path) -> None:
        config = next(root.rglob("config.yml"))
        text = re.sub(rf"(?m)^(\s*{key}:).*$", rf"\1 {value}", config.read_text())
        config.write_text(text.replace("eval_mode: fraction", "eval_mode: interval" if key == "eval_interval" else
                                       "eval_mode: fraction"))

    splatfacto_scene(tmp_path, export_ply=False)
    error = expect_error(_upload(svc_start().url, _scene_zip(tmp_path, wrong)), 422, "invalid_input", "archive")
    where = "pipeline.datamanager.dataparser" if section == "dataparser" else "pipeline.model"
    assert f"config.yml.{where}.{key}: " in error["message"] and "got" in error["message"], error


def _deep(name: str) -> Callable[[Path], None]:
    """Replace the file called `name` with JSON (or YAML: flow sequences) nested 100,000 deep."""
    def change(root: Path) -> None:
        path = next(root.rglob(name))
        path.write_bytes((b"data_dir: " if name.endswith(".yml") else b"") + DEEP_JSON)
    return change


def _write(name: str, content: bytes) -> Callable[[Path], None]:
    return lambda root: next(root.rglob(name)).write_bytes(content)


BROKEN = {   # name: (the zip from a scratch folder, the file the answer names, the rule it names)
    "a zip with no members": (lambda root: zip_of({}), "run.zip", "holds no files"),
    "a member whose deflate stream is corrupt":
        (lambda root: raw_zip([stored("run/model.ply", b"ply\n"), Member("run/cfg.yml", b"\xff" * 40, 400, 0)]),
         "'run/cfg.yml'", "damaged"),
    "a member path of 5,000 bytes": (lambda root: zip_of({"run/" + ("d" * 200 + "/") * 25 + "model.ply": b"ply\n"}),
                                     "run/ddd", "longer than a path inside the folder may be (1024 bytes"),
    "members of 1 MiB inflating 1,000 times": (lambda root: zip_of({f"run/{k}.bin": bytes(1 << 20) for k in range(3)}),
                                               "'run/0.bin'", "zip bomb"),
    "cameras.json nested 100,000 deep":
        (lambda root: _scene_zip(write_output_folder(root / "lego", svc_random_gaussians(50), svc_cameras(3)).parent,
                                 _deep("cameras.json")), "cameras.json", "deeper than 100 levels"),
    "transforms.json nested 100,000 deep": (lambda root: (splatfacto_scene(root, export_ply=False),
                                                          _scene_zip(root, _deep("transforms.json")))[1],
                                            "transforms.json", "deeper than 100 levels"),
    "cfg.yml nested 100,000 deep": (lambda root: (gsplat_scene(root), _scene_zip(root, _deep("cfg.yml")))[1],
                                    "cfg.yml", "deeper than 100 levels"),
    "cfg.yml whose data_dir is an alias tree of 10^7 leaves":
        (lambda root: (gsplat_scene(root), _scene_zip(root, _write("cfg.yml", alias_bomb(7))))[1],
         "cfg.yml", "aliases expand it past 100000 nodes"),
}


@pytest.mark.parametrize("case", BROKEN)
def test_a_broken_folder_is_422_naming_the_file_and_the_rule(svc_start, tmp_path, case):
    make, file, rule = BROKEN[case]
    server = svc_start()
    error = expect_error(_upload(server.url, make(tmp_path)), 422, "invalid_input", "archive")
    assert file in error["message"] and rule in error["message"], error
    assert not list((server.settings.data_dir / "tmp").iterdir())


def test_a_long_value_a_note_quotes_is_cut(svc_start, tmp_path):
    # cfg.yml names a capture that is not in the upload by a 1,008-byte path: the note saying so
    # quotes it, cut to NOTE_CHARS with the rest of the note.
    gsplat_scene(tmp_path)
    far = "data/" + "/".join(["x" * 250] * 4)
    archive = _scene_zip(tmp_path, _write("cfg.yml", f"data_dir: {far}\n".encode()))
    answer = _upload(svc_start().url, archive)
    assert answer.status_code == 201, answer.text
    notes = answer.json()["details"]["notes"]
    assert any(far[:200] in note for note in notes) and max(map(len, notes)) <= NOTE_CHARS
    assert len(answer.content) < 10 * NOTE_CHARS


# ----------------------------------------------------------------------------- the log, and a stored model's load

def test_a_log_on_a_full_disk_fails_no_request(full_log_server, svc_model_files, tmp_path):
    url = full_log_server.url
    gsplat_scene(tmp_path)
    answer = _upload(url, zip_of(folder_files(tmp_path, tmp_path)))      # the reader's notes
    assert answer.status_code == 201, answer.text
    with PHDClient(url) as phd:
        a = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
        phd.upload_model(svc_model_files["ply_b"])                       # one idle model is kept: a goes
        ranked = httpx.post(f"{url}/v1/models/{a.id}/rank", timeout=120, json={
            "cameras": [c.to_frame() for c in svc_cameras(1)], "samples": 2, "dropout_ratio": 0.1})
    assert ranked.status_code == 200, ranked.text                       # a loaded again from the store


def test_a_stored_model_with_training_cameras_loads_without_a_warning(svc_start, svc_model_files):
    server = svc_start(cache_size=1)
    with PHDClient(server.url) as phd:
        a = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
        phd.upload_model(svc_model_files["ply_b"])                       # a goes out of memory
    assert server.app.state.service.ledger.loaded() != [a.id]
    with warnings.catch_warnings(record=True) as issued:
        warnings.simplefilter("always")
        ranked = httpx.post(f"{server.url}/v1/models/{a.id}/rank", timeout=120, json={
            "cameras": [c.to_frame() for c in svc_cameras(1)], "samples": 2, "dropout_ratio": 0.1})
    assert ranked.status_code == 200, ranked.text
    assert [str(w.message) for w in issued if issubclass(w.category, ModelWarning)] == []


# ----------------------------------------------------------------------------- pose downloads

@pytest.mark.parametrize("index", [-1, 1000, 10**4000], ids=["-1", "1000", "4001 digits"])
def test_a_pose_index_outside_the_candidates_is_422_naming_it(svc_start, svc_model_files, index):
    server = svc_start()
    with PHDClient(server.url) as phd:
        model = phd.upload_model(svc_model_files["ply"])
    answer = httpx.post(f"{server.url}/v1/models/{model.id}/poses",
                        json={"cameras": [svc_cameras(1)[0].to_frame()], "indices": [index]})
    error = expect_error(answer, 422, field="indices[0]")
    assert "[0, 999]" in error["message"]
