"""The service's state and what it does with it: the settings, the model store, the memory
ledger, the jobs and the executor, with the steps the routes share (look a model or a job up
for a caller, queue work, ingest an upload). `service.deps` hands it to the routes."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fastapi.responses import JSONResponse

from phd_core.errors import InputError, TooLarge, bounded_notes, cut
from phd_core.executors import LOCAL, Executor
from phd_core.io.cache import matching_calibration
from phd_core.renderers import (
    FAMILIES,
    NO_CAMERAS_NOTE,
    SNIFF_BYTES,
    Renderer,
    accepts_background,
    load_model_bytes,
    set_background,
    unseen_views,
)
from phd_core.scene import UNSEEN_SHARE, Camera, capture_up
from phd_core.uq.candidates import scene_points

from .budget import READ_BYTES_PER_MODEL_BYTE, MemoryLedger, Reservation, largest_model_file, load_bytes, read_bytes
from .captures import CaptureRecord, CaptureStore
from .errors import ServiceError, busy, from_exception, not_found
from .folders import folder_bytes, read_folder, unpack_zip, upload_relative
from .jobs import JobManager, JobRecord, QueueFull, Work
from .jobstore import JobStore
from .keys import Principal
from .metrics import Metrics
from .requests import parse_cameras
from .schemas import Calibration, Job, RenderSize
from .settings import Settings
from .store import ModelRecord, ModelStore, writing
from .upload import (
    MAX_NAME_BYTES,
    Upload,
    guess_background,
    parse_background,
    parse_camera_format,
    parse_camera_json,
    sniff_kind,
    unwrap_sidecar,
)


@dataclass
class ServiceState:
    settings: Settings
    store: ModelStore
    ledger: MemoryLedger                # the memory budget, and the models in memory
    job_store: JobStore
    captures: CaptureStore              # the capture loop's captures (service.captures)
    # Made by the app's lifespan (service.app.create_app), so every request sees it; unset before.
    jobs: JobManager = field(init=False)
    executor: Executor = LOCAL          # where the jobs' rendering runs (settings.executor)
    metrics: Metrics = field(default_factory=Metrics)      # what GET /metrics shows (service.metrics)

    def model(self, model_id: str, who: Principal, field: str | None = None) -> ModelRecord:
        """The model, or 404 when it does not exist or belongs to another key."""
        record = self.store.get(model_id)
        if record is None or not who.may_see(record.owner):
            raise not_found("model", model_id, field)
        return record

    def capture(self, capture_id: str, who: Principal) -> CaptureRecord:
        """The capture, or 404 when it does not exist or belongs to another key."""
        record = self.captures.get(capture_id)
        if record is None or not who.may_see(record.owner):
            raise not_found("capture", capture_id)
        return record

    def job(self, job_id: str, who: Principal) -> Job:
        """The job as the API shows it: live from memory until it is final and persisted, then from
        the store (also after a restart)."""
        live = self.jobs.get(job_id)
        found: tuple[Job, str | None] | None
        if live is not None and not live.on_disk:
            found = (live.to_schema(), live.owner)
        else:
            found = self.job_store.get(job_id)
        if found is None or not who.may_see(found[1]):
            raise not_found("job", job_id)
        return found[0]

    def artifact(self, job_id: str, name: str, who: Principal) -> bytes | None:
        self.job(job_id, who)
        live = self.jobs.get(job_id)
        if live is not None and name in live.artifacts:     # a job whose final state could not be persisted
            return live.artifacts[name]
        return self.job_store.artifact(job_id, name)

    def persist_job(self, job: JobRecord) -> None:
        """JobManager's on_change: the job's state, and once final its artefacts, to disk."""
        self.job_store.save(job.to_schema(), job.owner, job.artifacts if job.state == "succeeded" else None)
        self.metrics.job_stored(job)

    async def run(self, job_id: str, kind: str, work: Work, estimate: float, run_async: bool,
                  who: Principal) -> Any:
        """Queue the work; answer 202 with the job when asked or when it is big, else wait for it."""
        try:
            job = self.jobs.submit(job_id, kind, work, estimate, owner=who.name)
        except QueueFull as exc:
            raise ServiceError(429, "queue_full", f"the work queue is full ({exc}); retry later", None,
                               {"Retry-After": str(self.settings.retry_after)}) from None
        if run_async or estimate > self.settings.async_threshold:
            return JSONResponse(job.to_schema().model_dump(mode="json"), status_code=202,
                                headers={"Location": f"/v1/jobs/{job.id}"})
        result = await asyncio.wrap_future(job.done)
        if job.state == "succeeded":
            return result
        if job.state == "cancelled":
            raise ServiceError(409, "job_cancelled", f"job '{job.id}' was cancelled before it finished")
        assert job.error is not None               # a failed job always carries its error (JobQueue)
        raise job.error

    def ingest(self, upload: Upload, kind: str, who: Principal) -> ModelRecord:
        """Load the uploaded file fully (worker thread), then move it into the store."""
        cameras = source = None
        if upload.cameras is not None:  # the cheap checks first
            source = unwrap_sidecar(parse_camera_json(upload.cameras), upload)
            cameras = parse_cameras(source, RenderSize(), self.settings, field="cameras",
                                    cap=self.settings.max_training_cameras)
        camera_format = parse_camera_format(upload.camera_format, source)
        # Parsed under the shared memory budget, which the model then stays in (if the parse's
        # bytes hold it); by content and the client's file name, so no message ever names the
        # server's temp file.
        try:
            with self.ledger.reserve(load_bytes(upload.size), timeout=self.settings.upload_wait) as parse:
                return self._store(upload, kind, who, cameras, camera_format, parse)
        except TimeoutError:
            raise busy("file", self.settings.retry_after) from None

    def ingest_folder(self, upload: Upload, who: Principal) -> ModelRecord:
        """A folder upload (`service.folders`): unpacked, and read within the memory budget for
        what its model inflates to (a checkpoint's records, not its bytes on disk), then ingested
        as the model file it holds, with what its trainer wrote beside it as the fields the
        request left out. Every refusal names the file and the rule: 413 past the model cap,
        else 422."""
        assert upload.folder is not None          # receive_upload set it for `files` and `archive` parts
        field = "archive" if upload.archive is not None else "files"
        budget = self.settings.memory_budget_bytes
        cap, read_cap = largest_model_file(budget), largest_model_file(budget, READ_BYTES_PER_MODEL_BYTE)
        named = cut(Path(upload.filename).stem, MAX_NAME_BYTES) if upload.filename else None
        with writing("the uploaded folder", field):        # a full disk: 507 (service.store.writing)
            try:
                if upload.archive is not None:
                    unpack_zip(upload.archive, upload.folder, cap,
                               self.store.free_bytes() - self.settings.keep_free_bytes, f"{named or 'folder'}.zip")
                inflated = folder_bytes(upload.folder)
                if inflated > read_cap:
                    raise TooLarge(field, f"its model inflates to {inflated} bytes in memory, more than the {read_cap} "
                                          "this service's memory budget can read")
                with self.ledger.reserve(read_bytes(inflated), timeout=self.settings.upload_wait):
                    found = read_folder(upload.folder, named, upload.path.with_suffix(".ply"), cap)
            except TimeoutError:
                raise busy(field, self.settings.retry_after) from None
            except InputError as exc:       # the readers name files by their paths: the upload's, not the server's
                known = from_exception(exc)
                assert known is not None   # from_exception answers every InputError
                raise ServiceError(known.status, known.code, upload_relative(f"{exc.field}: {exc.reason}",
                                                                             upload.folder), field) from None
        os.replace(found.model, upload.path)
        with open(upload.path, "rb") as f:
            upload.head = f.read(SNIFF_BYTES)
        upload.size = upload.path.stat().st_size
        upload.sha256 = file_sha256(upload.path)
        upload.filename = found.model.name
        if upload.cameras is None and found.cameras is not None:
            upload.cameras = json.dumps(found.cameras).encode()
        if upload.background is None and found.background is not None:
            upload.background, upload.background_source = json.dumps(found.background).encode(), found.background_source
        upload.camera_format = upload.camera_format or found.camera_format
        upload.name = upload.name or found.name
        upload.notes = found.notes
        upload.calibrations = found.calibrations
        return self.ingest(upload, sniff_kind(upload.head), who)

    def _store(self, upload: Upload, kind: str, who: Principal, cameras: list[Camera] | None,
               camera_format: str | None, parse: Reservation) -> ModelRecord:
        renderer = load_model_bytes(upload.path.read_bytes(), upload.filename or "the uploaded file")
        background_source = None
        if upload.background is not None:
            set_background(renderer, parse_background(upload.background))    # refused by a model with its own
            background_source = upload.background_source or "the upload's background field"
        elif accepts_background(renderer):                      # a bare PLY carries no background
            color, background_source = guess_background(camera_format)
            set_background(renderer, color)
        if cameras is not None and not upload.other_capture:
            check_cameras_see(renderer, cameras)
        cameras = cameras if cameras is not None else renderer.training_cameras
        frames = None if not cameras else [c.to_frame() for c in cameras]
        name = cut(upload.name or upload.filename or f"model{FAMILIES[kind].extension}", MAX_NAME_BYTES)
        # The stored cameras are the truth about training cameras, not what the file carried.
        facts = {k: v for k, v in renderer.describe().items() if k != "has_training_cameras"}
        facts["camera_format"] = camera_format or facts.get("camera_format")
        # The capture's up, found once while the model is loaded: its splats show the floor the
        # cameras' estimate may lean from; /cameras, the 3D view and generated poses use it.
        up = capture_up(cameras or [], scene_points(renderer))
        facts["up"], facts["up_rule"] = up.vector.tolist(), up.rule
        if background_source is not None:
            facts["background_source"] = background_source
        facts.update(upload.facts)
        # What loading the file noted, then what reading its trainer's folder noted; and a model
        # stored without training cameras says so (its poses are in the file's frame).
        notes = [*facts.get("notes", []), *upload.notes]
        if not frames and NO_CAMERAS_NOTE not in notes:
            notes.append(NO_CAMERAS_NOTE)
        stored, note = folder_calibration(upload.calibrations, frames, facts.get("background"))
        if note:
            notes.append(note)
        if notes:
            facts["notes"] = bounded_notes(notes)
        same = identical(self.store.list(), upload.sha256, who.name, frames, facts)
        if same is not None:
            if same.calibration is None and stored is not None and self.store.set_calibration(same.id, stored):
                same = replace(same, calibration=stored)          # what the repeat carried is still used
            upload.note = (f"the same file with the same training cameras, background and capture format is stored "
                           f"already under this key, as {same.name!r} ({same.id}, uploaded {same.created_at}): this "
                           "is that model, no new entry")
            return same
        record = self.store.add(upload.path, name=name, kind=renderer.kind, size_bytes=upload.size,
                                sha256=upload.sha256, num_units=renderer.num_units, describe=facts,
                                training_frames=frames, owner=who.name)
        if stored is not None and self.store.set_calibration(record.id, stored):
            record = replace(record, calibration=stored)
        parse.keep(record.id, renderer, record.size_bytes)
        self.metrics.uploads.labels(record.kind).inc()
        return record


def identical(records: list[ModelRecord], sha256: str, owner: str | None, frames: list[dict] | None,
              facts: dict) -> ModelRecord | None:
    """The stored model an upload would repeat: the same key's, of the same bytes, training
    cameras, background and capture format (the name alone does not make another model)."""
    for record in records:
        if ((record.owner, record.sha256, record.training_frames) == (owner, sha256, frames)
                and all(record.describe.get(k) == facts.get(k) for k in ("background", "camera_format"))):
            return record
    return None


def check_cameras_see(renderer: Renderer, cameras: list[Camera]) -> None:
    """422 naming `cameras` when most of them see almost none of the model: another capture's
    cameras, or cameras in another frame, whose renders would be empty (`other_capture` stores
    the model all the same)."""
    unseen = unseen_views(renderer, cameras)
    if unseen:
        raise ServiceError(422, "cameras_of_another_capture", f"{len(unseen)} of the {len(cameras)} training cameras "
                           f"see almost none of the model (fewer than {UNSEEN_SHARE:.0%} of its content in view): they "
                           "are another capture's, or in another frame, so its renders would be empty and its "
                           "rankings meaningless; send the cameras it was trained on, or set other_capture to store "
                           "it with these all the same", "cameras")


def folder_calibration(entries: list[dict], frames: list[dict] | None,
                       background: Any) -> tuple[dict[str, Any] | None, str | None]:
    """The stored calibration (as the calibrate job stores one) of the entries a folder's
    .phd-cache/ holds for its model file, when one was made on these training cameras over this
    background; and a note that says it was used, or why none was."""
    if not entries:
        return None, None
    entry = matching_calibration(entries, frames or [], background)
    if entry is None:
        return None, (f"the calibration `{entries[0].get('by', 'phd')}` stored in .phd-cache/ was made on other "
                      "training cameras or another background than those stored: not used (calibrate here)")
    try:
        calibration = Calibration(**entry["result"], num_cameras=entry["views"], created_at=entry["created_at"])
    except (KeyError, TypeError, ValueError):
        return None, "the calibration stored in .phd-cache/ could not be read: not used (calibrate here)"
    return calibration.model_dump(), (f"r_drop {calibration.r_drop} from the calibration `{entry.get('by', 'phd')}` "
                                      f"stored on {calibration.created_at} in .phd-cache/ for this model file, "
                                      "training cameras and background: not run again")


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()
