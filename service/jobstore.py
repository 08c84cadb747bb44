"""Jobs on disk: every state change of a job goes to the `jobs` table of the store's SQLite
database, and its artefacts (PNG heat maps, selected images) to `jobs/<id>/<name>`, each
written atomically before the row that names them. So after a restart (or a kill -9) a
finished job and its files answer exactly as before; a job that was queued or running is
reported `failed` with the code `interrupted` (work is not re-run behind the user's back),
and an id that never existed is still a 404. On a full disk a save is 507 naming the file or
row it could not write, and leaves neither the job's files nor its new row behind
(`service.store.writing`). The table itself is part of the store's schema (`service.store`).
"""

from __future__ import annotations

import json
import logging
import shutil
from typing import Any

from phd_core.io import fsync_path, write_bytes_atomic

from .errors import ServiceError, error_detail
from .schemas import Job
from .store import ModelStore, utc_now, writing

log = logging.getLogger("phd.service")
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

    def recover(self) -> int:
        """At startup: jobs left queued or running by the last process become failed (interrupted).
        On a full disk they stay as they are until a later start (logged): the service still starts."""
        try:
            with self.store.transaction("the state of the interrupted jobs") as db:
                cursor = db.execute("UPDATE jobs SET state = 'failed', error_json = ?, finished_at = ? "
                                    f"WHERE state NOT IN ({', '.join('?' * len(FINAL_STATES))})",
                                    (error_detail(*INTERRUPTED).model_dump_json(), utc_now(), *FINAL_STATES))
                return cursor.rowcount
        except ServiceError as exc:
            log.error("unfinished jobs not marked interrupted: %s", exc.message)
            return 0

    def save(self, job: Job, owner: str | None, artifacts: dict[str, bytes] | None = None) -> None:
        """Record a job's state (artefact files first, then the row that names them). On a full disk:
        507 naming what could not be written, the job's folder removed with what was written of it."""
        folder = self.root / job.id
        undo = [folder] if artifacts else []
        for name, data in (artifacts or {}).items():
            with writing(f"the artefact '{name}' of job '{job.id}'", undo=undo):
                folder.mkdir(exist_ok=True)
                write_bytes_atomic(folder / name, data)
        result = None if job.result is None else job.result.model_dump_json()
        error = None if job.error is None else job.error.model_dump_json()
        with writing(f"the {job.state} state of job '{job.id}'", undo=undo):
            if artifacts:
                fsync_path(folder)
            self._write_row(job, owner, result, error)
        if job.state in FINAL_STATES:
            try:
                self._prune()
            except ServiceError as exc:   # a full disk: the job is stored; old ones go at a later save
                log.warning("old jobs not pruned: %s", exc.message)

    def _write_row(self, job: Job, owner: str | None, result: str | None, error: str | None) -> None:
        with self.store.transaction(f"the {job.state} state of job '{job.id}'") as db:
            db.execute(
                "INSERT OR REPLACE INTO jobs (id, kind, owner, state, progress, created_at, started_at, finished_at, "
                "estimated_pixels, result_json, error_json, artifacts_json) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job.id, job.kind, owner, job.state, job.progress, job.created_at, job.started_at, job.finished_at,
                 job.estimated_pixels, result, error, json.dumps(job.artifacts)))

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
        with self.store.transaction("the removal of old jobs") as db:
            old = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE state IN ('succeeded', 'failed', 'cancelled') "
                "ORDER BY finished_at DESC, id LIMIT -1 OFFSET ?", (self.retention,))]
            db.executemany("DELETE FROM jobs WHERE id = ?", [(i,) for i in old])
        for job_id in old:
            shutil.rmtree(self.root / job_id, ignore_errors=True)


def _decode(text: str | None) -> Any:
    return None if text is None else json.loads(text)
