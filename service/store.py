"""Model store: model files on disk, their metadata and calibrations in SQLite.

Layout of the data directory:

    phd.sqlite3          metadata: tables `models` (one row per model, calibration included), `jobs` and
                         `captures` (service.captures)
    schema-version       the store's schema version (also SQLite's `PRAGMA user_version`)
    models/<id>.<ext>    the uploaded model file, byte for byte (.ply or .nerf)
    models/<id>.<ext>.phd-cache/   results derived from it (`cache`), deleted with it
    captures/<id>/       a capture's photos and reconstruction (service.captures)
    tmp/                 uploads in progress (swept at startup)

Crash safety comes from the order of operations. An upload is written to `tmp/`, fsynced,
then renamed into `models/` (atomic on one file system), and only then is its row
inserted, in one transaction. Deleting removes the row first, then the file. So a crash
can leave at most a temp file or a model file without a row; `sweep()` (run at startup)
removes both, and a row never points at a missing or partial file.

A full disk is an answer, not a crash: every write goes through `writing()` (rows:
through `transaction()`), which turns ENOSPC/EDQUOT and SQLite's "disk full"
into 507 `insufficient_storage` naming what could not be written, after removing what the
write had begun. One SQLite connection stays open for the store's life, so the write-ahead
log and its index (`-wal`, `-shm`) are never deleted and re-created: reads need no new disk
space, and what was stored before is served while the disk is full.

Upgrades: the schema carries a version (`SCHEMA_VERSION`, in `PRAGMA user_version` and the
file `schema-version`). At start-up an older store is backed up (`phd.sqlite3.v<N>.bak`) and
migrated in one transaction; a store newer than this code is refused, untouched.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import sqlite3
import threading
import uuid
from contextlib import closing, contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from phd_core.errors import InputError
from phd_core.io import ModelCache, fsync_path, write_bytes_atomic
from phd_core.renderers import FAMILIES

from .errors import ServiceError, insufficient_storage

DB_NAME = "phd.sqlite3"
VERSION_FILE = "schema-version"
FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
SQLITE_FULL = 13            # sqlite3.Error.sqlite_errorcode of "database or disk is full" (primary code)
SQLITE_IOERR_SHMSIZE = 4874  # the write-ahead log's index could not grow: no room for it on the disk


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


# ----------------------------------------------------------------------------- schema and its migrations

def _to_v1(db: sqlite3.Connection) -> None:
    """Version 1, the first versioned schema: the tables as the earlier code made them (a store from
    before per-key ownership gains `owner`), and an index for the pruning of finished jobs."""
    db.execute("""
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
        )""")
    if "owner" not in {row["name"] for row in db.execute("PRAGMA table_info(models)")}:
        db.execute("ALTER TABLE models ADD COLUMN owner TEXT")
    db.execute("""
        CREATE TABLE IF NOT EXISTS jobs (
            id TEXT PRIMARY KEY,
            kind TEXT NOT NULL,
            owner TEXT,
            state TEXT NOT NULL,
            progress REAL NOT NULL,
            created_at TEXT NOT NULL,
            started_at TEXT,
            finished_at TEXT,
            estimated_pixels REAL NOT NULL,
            result_json TEXT,
            error_json TEXT,
            artifacts_json TEXT NOT NULL
        )""")
    db.execute("CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, finished_at)")


def _to_v2(db: sqlite3.Connection) -> None:
    """Version 2: the `captures` table (issue 49, the capture loop)."""
    db.execute("""
        CREATE TABLE IF NOT EXISTS captures (
            id TEXT PRIMARY KEY,
            name TEXT NOT NULL,
            state TEXT NOT NULL,
            created_at TEXT NOT NULL,
            updated_at TEXT NOT NULL,
            test_json TEXT NOT NULL,
            settings_json TEXT NOT NULL,
            report_json TEXT,
            rounds_json TEXT NOT NULL,
            error_json TEXT,
            owner TEXT
        )""")


# MIGRATIONS[v] takes a store at version v to v + 1; version 0 is any store from before versions.
MIGRATIONS: list[Callable[[sqlite3.Connection], None]] = [_to_v1, _to_v2]
SCHEMA_VERSION = len(MIGRATIONS)


def stored_version(root: Path) -> int | None:
    """The schema version of the store in `root`, read without opening it for writing: the larger of
    the version file and the database header's user_version; None when there is no store yet."""
    db_path, version_file = root / DB_NAME, root / VERSION_FILE
    versions = []
    if version_file.is_file():
        text = version_file.read_text().strip()
        if not text.isdigit():
            raise InputError("data_dir", f"{version_file} should hold a schema version number, not {text[:40]!r}")
        versions.append(int(text))
    if db_path.is_file() and db_path.stat().st_size > 0:
        with open(db_path, "rb") as f:
            header = f.read(100)            # SQLite's header: user_version is the big-endian int at 60
        versions.append(int.from_bytes(header[60:64], "big") if len(header) == 100 else 0)
    return max(versions) if versions else None


# ----------------------------------------------------------------------------- a full disk

def disk_full(exc: BaseException) -> bool:
    """Whether an exception says the disk (or the user's quota) is full."""
    if isinstance(exc, OSError):
        return exc.errno in FULL_ERRNOS
    code = getattr(exc, "sqlite_errorcode", 0) if isinstance(exc, sqlite3.Error) else 0
    return code & 0xFF == SQLITE_FULL or code == SQLITE_IOERR_SHMSIZE


@contextmanager
def writing(what: str, field: str | None = None, undo: Iterable[Path] = ()) -> Iterator[None]:
    """Run a write to the data directory. On a full disk the paths in `undo` (files or folders the
    write had begun) are removed and the write becomes 507 `insufficient_storage` naming `what`.
    Nested, the innermost names what failed and every level removes its `undo`."""
    try:
        yield
    except (OSError, sqlite3.Error, ServiceError) as exc:
        full = exc.code == "insufficient_storage" if isinstance(exc, ServiceError) else disk_full(exc)
        if not full:
            raise
        for path in undo:
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        if isinstance(exc, ServiceError):
            raise
        raise insufficient_storage(what, field) from None


# ----------------------------------------------------------------------------- the store

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
        self.db_path = self.root / DB_NAME
        self._write_lock = threading.Lock()
        found = stored_version(self.root) if self.root.is_dir() else None
        if found is not None and found > SCHEMA_VERSION:
            raise InputError("data_dir", f"the store in {self.root} has schema version {found}, newer than this "
                             f"release's {SCHEMA_VERSION}: it was written by a later release of the service. Run "
                             "that release (or a later one); this one leaves the store untouched")
        self.models_dir.mkdir(parents=True, exist_ok=True)
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        self.migrated_from = self._migrate(found)
        # Held open until close(): the WAL and its index stay on disk, so reads need no new space.
        self._keeper = sqlite3.connect(self.db_path, check_same_thread=False)
        self._keeper.execute("SELECT COUNT(*) FROM models").fetchone()

    def close(self) -> None:
        self._keeper.close()

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.db_path, timeout=30.0, isolation_level=None)  # explicit transactions
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA synchronous=FULL")
        return closing(db)  # type: ignore[return-value]

    def _migrate(self, found: int | None) -> int | None:
        """Bring the store to SCHEMA_VERSION in one transaction (backing up an existing database
        first); returns the version it had when older, else None. A full disk stops the start."""
        older = found is not None and found < SCHEMA_VERSION and self.db_path.is_file()
        try:
            if older:
                self._backup(self.root / f"{DB_NAME}.v{found}.bak")
            with self._connect() as db:
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("BEGIN IMMEDIATE")
                current = db.execute("PRAGMA user_version").fetchone()[0]
                if current < SCHEMA_VERSION:      # nothing is written to a store that is up to date
                    for migrate in MIGRATIONS[current:]:
                        migrate(db)
                    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                db.execute("COMMIT")
            version_file = self.root / VERSION_FILE
            if not version_file.is_file() or version_file.read_text().strip() != str(SCHEMA_VERSION):
                write_bytes_atomic(version_file, f"{SCHEMA_VERSION}\n".encode())
        except (OSError, sqlite3.Error) as exc:
            if not disk_full(exc):
                raise
            raise InputError("data_dir", f"the disk of {self.root} is full: the store could not be brought to "
                             f"schema version {SCHEMA_VERSION} (nothing was changed); free space and start "
                             "again") from None
        return found if older else None

    def _backup(self, target: Path) -> None:
        """A consistent copy of the database (what its write-ahead log holds included), fsynced."""
        partial = target.with_name(target.name + ".part")
        try:
            with closing(sqlite3.connect(self.db_path)) as source, closing(sqlite3.connect(partial)) as copy:
                source.backup(copy)
            fsync_path(partial)
            os.replace(partial, target)
            fsync_path(self.root)
        finally:
            partial.unlink(missing_ok=True)

    @contextmanager
    def transaction(self, what: str, field: str | None = None) -> Iterator[sqlite3.Connection]:
        """A write transaction (serialised with every other write): committed at the end of the
        block, rolled back on any error; a full disk is 507 naming `what`."""
        with writing(what, field), self._write_lock, self._connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise

    def free_bytes(self) -> int:
        """Free space on the data directory's file system, for an unprivileged writer."""
        return shutil.disk_usage(self.root).free

    # ------------------------------------------------------------------ crash recovery

    def sweep(self) -> list[Path]:
        """Delete unfinished uploads and model files that no row refers to. Returns what went."""
        with self._connect() as db:
            known = {row["file"] for row in db.execute("SELECT file FROM models")}
        removed = list(self.tmp_dir.iterdir())    # files, and folders an upload was unpacked into (service.folders)
        removed += [p for p in self.models_dir.iterdir() if p.is_file() and p.name not in known]
        for path in removed:
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        caches = [p for p in self.models_dir.iterdir() if p.is_dir() and p.name.endswith(".phd-cache")
                  and p.name.removesuffix(".phd-cache") not in known]       # what was derived from a model gone
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
            with self.transaction(f"the record of model '{name}'", "file") as db:
                db.execute(
                    "INSERT INTO models (id, name, kind, file, size_bytes, sha256, num_units, describe_json, "
                    "training_frames_json, calibration_json, created_at, owner) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, NULL, ?, ?)",
                    (model_id, name, kind, file, size_bytes, sha256, num_units, json.dumps(describe),
                     None if training_frames is None else json.dumps(training_frames), record.created_at, owner))
        except BaseException:
            target.unlink(missing_ok=True)
            raise
        return record

    def set_calibration(self, model_id: str, calibration: dict[str, Any]) -> bool:
        """Store a calibration with its model; False if the model no longer exists."""
        with self.transaction(f"the calibration of model '{model_id}'") as db:
            cursor = db.execute("UPDATE models SET calibration_json = ? WHERE id = ?",
                                (json.dumps(calibration), model_id))
            return cursor.rowcount == 1

    def set_training_frames(self, model_id: str, frames: list[dict]) -> bool:
        with self.transaction(f"the training cameras of model '{model_id}'") as db:
            cursor = db.execute("UPDATE models SET training_frames_json = ? WHERE id = ?",
                                (json.dumps(frames), model_id))
            return cursor.rowcount == 1

    def delete(self, model_id: str) -> bool:
        """Remove the row, then the file. False if there was no such model."""
        with self.transaction(f"the removal of model '{model_id}' from the database") as db:
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
