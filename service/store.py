"""Model store: model files on disk, their metadata and calibrations in SQLite.

Layout of the data directory:

    phd.sqlite3          metadata: table `models` (one row per model, calibration included)
    models/<id>.<ext>    the uploaded model file, byte for byte (.ply or .nerf)
    models/<id>.<ext>.phd-cache/   results derived from it (`cache`), deleted with it
    tmp/                 uploads in progress (swept at startup)

Crash safety comes from the order of operations. An upload is written to `tmp/`, fsynced,
then renamed into `models/` (atomic on one file system), and only then is its row
inserted, in one transaction. Deleting removes the row first, then the file. So a crash
can leave at most a temp file or a model file without a row; `sweep()` (run at startup)
removes both, and a row never points at a missing or partial file.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import threading
import uuid
from contextlib import closing
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from phd_core.io import ModelCache, fsync_path
from phd_core.renderers import FAMILIES

DB_NAME = "phd.sqlite3"
SCHEMA = """
CREATE TABLE IF NOT EXISTS models (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    kind TEXT NOT NULL,
    file TEXT NOT NULL,
    size_bytes INTEGER NOT NULL,
    sha256 TEXT NOT NULL,
    num_units INTEGER NOT NULL,
    describe_json TEXT NOT NULL,
    training_frames_json TEXT,
    calibration_json TEXT,
    created_at TEXT NOT NULL,
    owner TEXT
)
"""


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class ModelRecord:
    """One stored model as SQLite holds it (JSON columns decoded)."""

    id: str
    name: str
    kind: str
    file: str                              # file name inside models/
    size_bytes: int
    sha256: str
    num_units: int
    describe: dict[str, Any]
    training_frames: list[dict] | None     # nerfstudio-style frames (Camera.to_frame())
    calibration: dict[str, Any] | None     # CalibrationResult.to_dict() + num_cameras, created_at
    created_at: str
    owner: str | None = None               # name of the API key that uploaded it (None: no named keys)


class ModelStore:
    """Thread-safe: every call opens its own SQLite connection; writes are serialised."""

    def __init__(self, data_dir: Path):
        self.root = Path(data_dir)
        self.models_dir = self.root / "models"
        self.tmp_dir = self.root / "tmp"
        self.models_dir.mkdir(parents=True, exist_ok=True)
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        self.db_path = self.root / DB_NAME
        self._write_lock = threading.Lock()
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(SCHEMA)
            columns = {row["name"] for row in db.execute("PRAGMA table_info(models)")}
            if "owner" not in columns:  # a data directory from before per-key ownership
                db.execute("ALTER TABLE models ADD COLUMN owner TEXT")

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.db_path, timeout=30.0, isolation_level=None)  # explicit transactions
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA synchronous=FULL")
        return closing(db)  # type: ignore[return-value]

    # ------------------------------------------------------------------ crash recovery

    def sweep(self) -> list[Path]:
        """Delete unfinished uploads and model files that no row refers to. Returns what went."""
        with self._connect() as db:
            known = {row["file"] for row in db.execute("SELECT file FROM models")}
        removed = [p for p in self.tmp_dir.iterdir() if p.is_file()]
        removed += [p for p in self.models_dir.iterdir() if p.is_file() and p.name not in known]
        for path in removed:
            path.unlink(missing_ok=True)
        caches = [p for p in self.models_dir.iterdir() if p.is_dir() and p.name.removesuffix(".phd-cache") not in known]
        for path in caches:
            shutil.rmtree(path, ignore_errors=True)
        return removed + caches

    # ------------------------------------------------------------------ writes

    def new_temp_path(self) -> Path:
        """A fresh path in tmp/ for an upload in progress."""
        return self.tmp_dir / f"upload-{uuid.uuid4().hex}.part"

    def add(self, temp_path: Path, *, name: str, kind: str, size_bytes: int, sha256: str, num_units: int,
            describe: dict[str, Any], training_frames: list[dict] | None, owner: str | None = None) -> ModelRecord:
        """Move a complete, validated upload into the store and record it.

        The temp file must already be fsynced. On any failure neither file nor row remains.
        """
        model_id = uuid.uuid4().hex[:16]
        file = model_id + FAMILIES[kind].extension
        target = self.models_dir / file
        record = ModelRecord(id=model_id, name=name, kind=kind, file=file, size_bytes=size_bytes, sha256=sha256,
                             num_units=num_units, describe=describe, training_frames=training_frames,
                             calibration=None, created_at=utc_now(), owner=owner)
        os.replace(temp_path, target)
        try:
            fsync_path(self.models_dir)
            with self._write_lock, self._connect() as db:
                db.execute("BEGIN IMMEDIATE")
                db.execute(
                    "INSERT INTO models (id, name, kind, file, size_bytes, sha256, num_units, describe_json, "
                    "training_frames_json, calibration_json, created_at, owner) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, NULL, ?, ?)",
                    (model_id, name, kind, file, size_bytes, sha256, num_units, json.dumps(describe),
                     None if training_frames is None else json.dumps(training_frames), record.created_at, owner))
                db.execute("COMMIT")
        except BaseException:
            target.unlink(missing_ok=True)
            raise
        return record

    def set_calibration(self, model_id: str, calibration: dict[str, Any]) -> bool:
        """Store a calibration with its model; False if the model no longer exists."""
        with self._write_lock, self._connect() as db:
            cursor = db.execute("UPDATE models SET calibration_json = ? WHERE id = ?",
                                (json.dumps(calibration), model_id))
            return cursor.rowcount == 1

    def set_training_frames(self, model_id: str, frames: list[dict]) -> bool:
        with self._write_lock, self._connect() as db:
            cursor = db.execute("UPDATE models SET training_frames_json = ? WHERE id = ?",
                                (json.dumps(frames), model_id))
            return cursor.rowcount == 1

    def delete(self, model_id: str) -> bool:
        """Remove the row, then the file. False if there was no such model."""
        with self._write_lock, self._connect() as db:
            row = db.execute("SELECT file FROM models WHERE id = ?", (model_id,)).fetchone()
            if row is None:
                return False
            db.execute("DELETE FROM models WHERE id = ?", (model_id,))
        (self.models_dir / row["file"]).unlink(missing_ok=True)
        shutil.rmtree(ModelCache(self.models_dir / row["file"]).dir, ignore_errors=True)
        return True

    # ------------------------------------------------------------------ reads

    def get(self, model_id: str) -> ModelRecord | None:
        with self._connect() as db:
            row = db.execute("SELECT * FROM models WHERE id = ?", (model_id,)).fetchone()
        return None if row is None else _record(row)

    def list(self) -> list[ModelRecord]:
        with self._connect() as db:
            rows = db.execute("SELECT * FROM models ORDER BY created_at, id").fetchall()
        return [_record(row) for row in rows]

    def path(self, record: ModelRecord) -> Path:
        return self.models_dir / record.file

    def cache(self, record: ModelRecord) -> ModelCache:
        """Results derived from the model (what its captured views saw), kept beside its file and
        deleted with it; each entry is written atomically and keyed by the model's sha256."""
        return ModelCache(self.path(record), digest=record.sha256)


def _record(row: sqlite3.Row) -> ModelRecord:
    def decode(text: str | None) -> Any:
        return None if text is None else json.loads(text)

    return ModelRecord(id=row["id"], name=row["name"], kind=row["kind"], file=row["file"],
                       size_bytes=row["size_bytes"], sha256=row["sha256"], num_units=row["num_units"],
                       describe=decode(row["describe_json"]), training_frames=decode(row["training_frames_json"]),
                       calibration=decode(row["calibration_json"]), created_at=row["created_at"], owner=row["owner"])
