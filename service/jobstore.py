"""Jobs on disk: every state change of a job goes to the `jobs` table of the store's SQLite
database, and its artefacts (PNG heat maps, selected images) to `jobs/<id>/<name>`, each
written atomically before the row that names them. So after a restart (or a kill -9) a
finished job and its files answer exactly as before; a job that was queued or running is
reported `failed` with the code `interrupted` (work is not re-run behind the user's back),
and an id that never existed is still a 404.
"""

from __future__ import annotations

import json
import shutil
from typing import Any

from phd_core.io import fsync_path, write_bytes_atomic

from .errors import error_detail
from .schemas import Job
from .store import ModelStore, utc_now

SCHEMA = """
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
)
"""
# A job in one of these states is over (service.jobs uses the same ones).
FINAL_STATES = ("succeeded", "failed", "cancelled")
# (code, message) of a job that a restart or a shutdown cut short (service.jobs fails it with the same).
INTERRUPTED = ("interrupted", "the job was interrupted by a restart of the service; submit it again")


class JobStore:
    """Thread-safe like `ModelStore`, whose database and write lock it shares."""

    def __init__(self, store: ModelStore, retention: int):
        self.store = store
        self.retention = retention
        self.root = store.root / "jobs"
        self.root.mkdir(parents=True, exist_ok=True)
        with store._connect() as db:
            db.execute(SCHEMA)

    def recover(self) -> int:
        """At startup: jobs left queued or running by the last process become failed (interrupted)."""
        with self.store._write_lock, self.store._connect() as db:
            cursor = db.execute("UPDATE jobs SET state = 'failed', error_json = ?, finished_at = ? "
                                f"WHERE state NOT IN ({', '.join('?' * len(FINAL_STATES))})",
                                (error_detail(*INTERRUPTED).model_dump_json(), utc_now(), *FINAL_STATES))
            return cursor.rowcount

    def save(self, job: Job, owner: str | None, artifacts: dict[str, bytes] | None = None) -> None:
        """Record a job's state (artefact files first, then the row that names them)."""
        if artifacts:
            folder = self.root / job.id
            folder.mkdir(exist_ok=True)
            for name, data in artifacts.items():
                write_bytes_atomic(folder / name, data)
            fsync_path(folder)
        result = None if job.result is None else job.result.model_dump_json()
        error = None if job.error is None else job.error.model_dump_json()
        with self.store._write_lock, self.store._connect() as db:
            db.execute(
                "INSERT OR REPLACE INTO jobs (id, kind, owner, state, progress, created_at, started_at, finished_at, "
                "estimated_pixels, result_json, error_json, artifacts_json) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job.id, job.kind, owner, job.state, job.progress, job.created_at, job.started_at, job.finished_at,
                 job.estimated_pixels, result, error, json.dumps(job.artifacts)))
        if job.state in FINAL_STATES:
            self._prune()

    def get(self, job_id: str) -> tuple[Job, str | None] | None:
        """(the job, its owner) or None."""
        with self.store._connect() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            return None
        job = Job.model_validate({
            "id": row["id"], "kind": row["kind"], "state": row["state"], "progress": row["progress"],
            "created_at": row["created_at"], "started_at": row["started_at"], "finished_at": row["finished_at"],
            "estimated_pixels": row["estimated_pixels"], "result": _decode(row["result_json"]),
            "error": _decode(row["error_json"]), "artifacts": json.loads(row["artifacts_json"])})
        return job, row["owner"]

    def artifact(self, job_id: str, name: str) -> bytes | None:
        found = self.get(job_id)
        if found is None or name not in found[0].artifacts:   # only names the job recorded: no path games
            return None
        path = self.root / job_id / name
        return path.read_bytes() if path.is_file() else None

    def _prune(self) -> None:
        """Forget the oldest finished jobs (rows and files) past `retention`."""
        with self.store._write_lock, self.store._connect() as db:
            old = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE state IN ('succeeded', 'failed', 'cancelled') "
                "ORDER BY finished_at DESC, id LIMIT -1 OFFSET ?", (self.retention,))]
            db.executemany("DELETE FROM jobs WHERE id = ?", [(i,) for i in old])
        for job_id in old:
            shutil.rmtree(self.root / job_id, ignore_errors=True)


def _decode(text: str | None) -> Any:
    return None if text is None else json.loads(text)
