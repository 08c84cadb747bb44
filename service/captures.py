"""Captures on disk: each capture's folder (what `phd capture` writes: photos, COLMAP's
reconstruction, the undistorted images) under `captures/<id>/`, its record in the `captures`
table of the store's SQLite database.

A capture lives through rounds. Round 0 is the photos it was created with; every later round
the photos added to it. A round gains a model when the capture is trained (the model is an
ordinary stored model, linked back by `describe["capture_id"]`) and the next views when they
are asked for. `state` says what its folder is doing:

    reconstructing   structure-from-motion on the first photos (no folder yet)
    registering      new photos being registered into the folder
    ready            the folder holds a whole reconstruction
    failed           the first reconstruction failed (`error` says why); only deleting it is left

Crash safety, as the model store's: the first photos are written to `captures/<id>.photos/`
and the row inserted before any work; structure-from-motion builds the folder beside its place
and renames it in (phd_core.process.capture), so `captures/<id>/` is a whole capture or absent.
At start-up (`recover`) a capture left `reconstructing` becomes `failed` (interrupted), one left
`registering` is `ready` again with the folder it had (the new photos were not added; a crash
between add_photos' two renames leaves that folder under `.<id>.old-*/`, from where it is put
back), and partial folders and leftover photos are removed.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import error_detail
from .jobstore import INTERRUPTED
from .store import ModelStore, utc_now

STATES = ("reconstructing", "registering", "ready", "failed")


@dataclass(frozen=True)
class CaptureRecord:
    """One capture as SQLite holds it (JSON columns decoded)."""

    id: str
    name: str
    state: str
    created_at: str
    updated_at: str
    test_photos: list[str]               # photo names held out of training: each round's test PSNR
    settings: dict[str, Any]             # structure-from-motion's settings, kept for every later addition
    report: dict[str, Any] | None        # phd_core.process.capture.CaptureReport of the latest reconstruction
    rounds: list[dict[str, Any]] = field(default_factory=list)   # service.schemas.CaptureRound, as dicts
    error: dict[str, Any] | None = None  # why the first reconstruction failed
    owner: str | None = None

    @property
    def model_id(self) -> str | None:
        """The latest round's model, else the latest model of an earlier round."""
        return next((r["train"]["model_id"] for r in reversed(self.rounds) if r.get("train")), None)


class CaptureStore:
    """Thread-safe like `ModelStore`, whose database and write lock it shares."""

    def __init__(self, store: ModelStore):
        self.store = store
        self.root = store.root / "captures"
        self.root.mkdir(parents=True, exist_ok=True)

    def folder(self, capture_id: str) -> Path:
        """The capture folder (absent until its first reconstruction is in)."""
        return self.root / capture_id

    def photos_dir(self, capture_id: str, round_: int) -> Path:
        """Where a round's uploaded photos wait for structure-from-motion."""
        return self.root / f"{capture_id}.photos-{round_}"

    # ------------------------------------------------------------------ crash recovery

    def recover(self) -> list[Path]:
        """At start-up: interrupted work undone (module docstring). Returns the paths removed."""
        error = json.dumps(error_detail(*INTERRUPTED).model_dump())
        with self.store.transaction("the state of the interrupted captures") as db:
            db.execute("UPDATE captures SET state = 'failed', error_json = ?, updated_at = ? "
                       "WHERE state = 'reconstructing'", (error, utc_now()))
            db.execute("UPDATE captures SET state = 'ready', updated_at = ? WHERE state = 'registering'",
                       (utc_now(),))
            known = {row[0] for row in db.execute("SELECT id FROM captures")}
        for capture_id in known:        # a crash between add_photos' two renames: the earlier folder goes back
            kept = next(iter(self.root.glob(f".{capture_id}.old-*/{capture_id}")), None)
            if kept is not None and not self.folder(capture_id).exists():
                kept.rename(self.folder(capture_id))
        removed = [path for path in self.root.iterdir()
                   if path.name.startswith(".") or "." in path.name or path.name not in known]
        for path in removed:
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        return removed

    # ------------------------------------------------------------------ writes

    def add(self, *, name: str, test_photos: list[str], settings: dict[str, Any], owner: str | None) -> CaptureRecord:
        """A new capture, reconstructing its first photos."""
        now = utc_now()
        record = CaptureRecord(id=uuid.uuid4().hex[:16], name=name, state="reconstructing", created_at=now,
                               updated_at=now, test_photos=test_photos, settings=settings, report=None, owner=owner)
        with self.store.transaction(f"the record of capture '{name}'") as db:
            db.execute("INSERT INTO captures (id, name, state, created_at, updated_at, test_json, settings_json, "
                       "report_json, rounds_json, error_json, owner) VALUES (?, ?, ?, ?, ?, ?, ?, NULL, '[]', NULL, ?)",
                       (record.id, name, record.state, now, now, json.dumps(test_photos), json.dumps(settings),
                        owner))
        return record

    def update(self, capture_id: str, **changes: Any) -> CaptureRecord | None:
        """Set some of state, report, rounds, error, test_photos; None when the capture is gone."""
        columns = {"state": "state", "report": "report_json", "rounds": "rounds_json", "error": "error_json",
                   "test_photos": "test_json"}
        sets = [f"{columns[key]} = ?" for key in changes]
        values = [value if key == "state" else json.dumps(value) for key, value in changes.items()]
        with self.store.transaction(f"the record of capture '{capture_id}'") as db:
            cursor = db.execute(f"UPDATE captures SET {', '.join(sets)}, updated_at = ? WHERE id = ?",
                                (*values, utc_now(), capture_id))
            if cursor.rowcount != 1:
                return None
        return self.get(capture_id)

    def begin(self, capture_id: str, state: str, busy: tuple[str, ...]) -> CaptureRecord | None:
        """Move the capture to `state` unless it is in one of `busy` (returns None then, or when gone):
        one change to a capture's folder at a time."""
        with self.store.transaction(f"the record of capture '{capture_id}'") as db:
            cursor = db.execute(f"UPDATE captures SET state = ?, updated_at = ? WHERE id = ? AND state NOT IN "
                                f"({', '.join('?' * len(busy))})", (state, utc_now(), capture_id, *busy))
            if cursor.rowcount != 1:
                return None
        return self.get(capture_id)

    def delete(self, capture_id: str) -> bool:
        """Remove the row, then the folder and any photos waiting. False if there was no such capture."""
        with self.store.transaction(f"the removal of capture '{capture_id}' from the database") as db:
            if db.execute("DELETE FROM captures WHERE id = ?", (capture_id,)).rowcount != 1:
                return False
        for path in self.root.glob(f"{capture_id}*"):
            shutil.rmtree(path, ignore_errors=True)
        return True

    # ------------------------------------------------------------------ reads

    def get(self, capture_id: str) -> CaptureRecord | None:
        with self.store._connect() as db:
            row = db.execute("SELECT * FROM captures WHERE id = ?", (capture_id,)).fetchone()
        return None if row is None else _record(row)

    def list(self) -> list[CaptureRecord]:
        with self.store._connect() as db:
            rows = db.execute("SELECT * FROM captures ORDER BY created_at, id").fetchall()
        return [_record(row) for row in rows]


def _record(row: sqlite3.Row) -> CaptureRecord:
    def decode(text: str | None) -> Any:
        return None if text is None else json.loads(text)

    return CaptureRecord(id=row["id"], name=row["name"], state=row["state"], created_at=row["created_at"],
                         updated_at=row["updated_at"], test_photos=decode(row["test_json"]),
                         settings=decode(row["settings_json"]), report=decode(row["report_json"]),
                         rounds=decode(row["rounds_json"]), error=decode(row["error_json"]), owner=row["owner"])
