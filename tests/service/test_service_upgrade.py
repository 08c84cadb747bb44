"""Upgrades (issue 36): the store carries a schema version (SQLite's user_version and the file
`schema-version`). A store written by the code before versions (tests/service/store_v0, made by
its make.sh from that commit's `git archive`) is backed up, migrated at start-up, and every model
and job reads back as that code answered; a store newer than the code is refused, untouched."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from contextlib import closing
from pathlib import Path
from typing import Any

import httpx
import pytest

from client import PHDClient
from phd_core.errors import InputError
from service import store as store_module
from service.app import create_app
from service.settings import Settings
from service.store import DB_NAME, SCHEMA_VERSION, VERSION_FILE, ModelStore
from support.fixtures import svc_cameras

FIXTURE = Path(__file__).parent / "store_v0"


@pytest.fixture
def old_store(tmp_path) -> tuple[Path, dict]:
    """A copy of the earlier code's data directory (the fixture itself is never changed), and what
    that code answered."""
    data = tmp_path / "data"
    shutil.copytree(FIXTURE / "data", data)
    keys = tmp_path / "keys.json"
    expected = json.loads((FIXTURE / "expected.json").read_text())
    keys.write_text(json.dumps(expected["keys"]))
    expected["keys_file"] = keys
    return data, expected


def rows(db_path: Path) -> list[str]:
    """The database's content as SQL, the schema version aside."""
    with closing(sqlite3.connect(db_path)) as db:
        return list(db.iterdump())


def as_answered(now: Any, then: Any) -> bool:
    """`now` says everything `then` said: equal, except that objects may have gained fields (a
    later release may add to the answers, never change or drop what they held)."""
    if isinstance(then, dict):
        return isinstance(now, dict) and all(k in now and as_answered(now[k], v) for k, v in then.items())
    if isinstance(then, list):
        return isinstance(now, list) and len(now) == len(then) and all(map(as_answered, now, then))
    return now == then


def file_digests(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_the_earlier_codes_store_is_migrated_and_reads_back_as_it_answered(old_store, svc_start):
    data, expected = old_store
    before = rows(data / DB_NAME)
    with closing(sqlite3.connect(data / DB_NAME)) as db:
        assert db.execute("PRAGMA user_version").fetchone() == (0,)     # the earlier code set no version
    server = svc_start(data_dir=data, api_key=expected["admin_key"], keys_file=expected["keys_file"])

    # Backed up first, as it was; then at the new version, in the database and the file.
    assert rows(data / f"{DB_NAME}.v0.bak") == before
    with closing(sqlite3.connect(data / DB_NAME)) as db:
        assert db.execute("PRAGMA user_version").fetchone() == (SCHEMA_VERSION,)
    assert (data / VERSION_FILE).read_text() == f"{SCHEMA_VERSION}\n"

    with PHDClient(server.url, api_key=expected["admin_key"]) as admin:
        assert as_answered([m.model_dump(mode="json") for m in admin.list_models()], expected["models"])
        for job_id, answered in expected["jobs"].items():
            assert as_answered(admin.get_job(job_id).model_dump(mode="json"), answered["job"])
            for name, digest in answered["artifacts"].items():
                artefact = admin.download(f"/v1/jobs/{job_id}/artifacts/{name}")
                assert hashlib.sha256(artefact).hexdigest() == digest
        calibrated = next(m for m in expected["models"] if m["has_calibration"])
        ranked = admin.rank(calibrated["id"], svc_cameras(2, size=8, phase=0.25), samples=2)
        assert ranked.ratio_source == "calibration"              # the stored calibration is used
    with PHDClient(server.url, api_key=expected["keys"]["alice"]) as alice:   # owners kept: alice sees hers
        assert sorted(m.id for m in alice.list_models()) == sorted(
            i for i, owner in expected["owners"].items() if owner == "alice")
    server.stop()

    again = svc_start(data_dir=data, api_key=expected["admin_key"], keys_file=expected["keys_file"])
    assert sorted(p.name for p in data.iterdir() if ".bak" in p.name) == [f"{DB_NAME}.v0.bak"]  # migrated once
    with PHDClient(again.url, api_key=expected["admin_key"]) as admin:
        assert len(admin.list_models()) == len(expected["models"])


@pytest.mark.parametrize("newer", ["both", "database"])     # "database": a later release stopped before the file
def test_a_store_newer_than_the_code_is_refused_and_left_untouched(old_store, newer):
    data, expected = old_store
    ModelStore(data).close()                                   # now at this code's version
    if newer == "both":
        (data / VERSION_FILE).write_text(f"{SCHEMA_VERSION + 1}\n")
    with closing(sqlite3.connect(data / DB_NAME)) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
        db.commit()
    before = file_digests(data)
    with pytest.raises(InputError) as refused:
        create_app(Settings(data_dir=data))
    assert refused.value.field == "data_dir"
    assert f"schema version {SCHEMA_VERSION + 1}, newer than this release's {SCHEMA_VERSION}" in refused.value.reason
    assert file_digests(data) == before                        # not a byte changed, no file added


def test_a_migration_that_fails_changes_nothing(old_store, monkeypatch, svc_start):
    """Migrations run in one transaction: one that fails halfway leaves the store as it was
    (the backup made), and the next start with working code migrates it."""
    data, expected = old_store
    before = rows(data / DB_NAME)

    def half_done(db: sqlite3.Connection) -> None:
        db.execute("CREATE TABLE half (x)")
        raise RuntimeError("a migration step failed")

    monkeypatch.setattr(store_module, "MIGRATIONS", [*store_module.MIGRATIONS, half_done])
    monkeypatch.setattr(store_module, "SCHEMA_VERSION", SCHEMA_VERSION + 1)
    with pytest.raises(RuntimeError):
        ModelStore(data)
    assert rows(data / DB_NAME) == before and not (data / VERSION_FILE).exists()
    monkeypatch.undo()
    server = svc_start(data_dir=data, api_key=expected["admin_key"], keys_file=expected["keys_file"])
    models = httpx.get(f"{server.url}/v1/models", headers={"Authorization": f"Bearer {expected['admin_key']}"})
    assert as_answered(models.json()["models"], expected["models"])
