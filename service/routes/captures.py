"""/v1/captures: the capture loop. Photos in (structure-from-motion), photos added (registered
into the reconstruction), a model trained on it, the next views out (service.loop)."""

from __future__ import annotations

import asyncio
import shutil
from typing import Any, Callable

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse

from ..deps import ACCEPTED, ERRORS, Caller, Service
from ..errors import ServiceError, not_found
from ..jobs import Work
from ..keys import Principal
from ..loop import add_photos_job, capture_info, check_room, check_test, next_job, reconstruct_job, train_job
from ..photos import PhotoUpload, receive_photos
from ..schemas import CaptureInfo, CaptureList, NextRequest, RankResult, TrainRequest, TrainResult
from ..state import ServiceState
from .work import artifact_url

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["captures"])
PHOTOS_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "properties": {
        "photos": {"type": "array", "items": {"type": "string", "format": "binary"},
                   "description": "One part per photo, named by its file name"},
        "archive": {"type": "string", "format": "binary", "description": "Instead of photos: a zip of them"},
        "video": {"type": "string", "format": "binary", "description": "Instead of photos (first upload only): a "
                  "video, sampled at fps frames a second"},
        "name": {"type": "string", "description": "Display name"},
        "test": {"type": "string", "description": "JSON list of photo names held out of training (each round's "
                 "test PSNR and sigma-max-bar)"},
        "matcher": {"type": "string", "description": "auto (default), sequential or exhaustive, as phd capture"},
        "camera_model": {"type": "string", "description": "COLMAP's lens model (default SIMPLE_RADIAL)"},
        "min_registered": {"type": "string", "description": "refuse when fewer photos register (default: the "
                           "larger of 8 and half the photos)"},
        "fps": {"type": "string", "description": "a video's frames sampled per second"},
    }}}}}}
BUSY = ("reconstructing", "registering", "failed")    # no other change to its folder meanwhile


async def _received(request: Request, svc: ServiceState, *, video: bool) -> PhotoUpload:
    folder = svc.store.new_temp_path().with_suffix(".photos")
    try:
        return await receive_photos(request, folder, svc.settings, video=video)
    except BaseException:
        await asyncio.to_thread(_remove, folder)
        raise


def _remove(folder: Any) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    for extra in folder.parent.glob(f"{folder.name}-*"):
        extra.unlink(missing_ok=True)


async def _start(svc: ServiceState, who: Principal, kind: str, work: Work, record_id: str,
                 undo: Callable[[], Any]) -> JSONResponse:
    """Queue a capture's structure-from-motion; 202 with the capture and the job's id. When it
    cannot be queued (429), `undo` takes back what the request did."""
    job_id = svc.jobs.new_id()
    try:
        await svc.run(job_id, kind, work, 0.0, True, who)
    except ServiceError:
        await asyncio.to_thread(undo)
        raise
    record = svc.captures.get(record_id)
    if record is None:
        raise not_found("capture", record_id)
    info = capture_info(record, job=job_id)
    return JSONResponse(info.model_dump(mode="json"), status_code=202,
                        headers={"Location": f"/v1/captures/{record_id}"})


@router.post("/captures", status_code=202, response_model=CaptureInfo, openapi_extra=PHOTOS_BODY)
async def create_capture(request: Request, svc: Service, who: Caller) -> JSONResponse:
    """A capture from photos (or a video): structure-from-motion runs as a job (its id in `job`)."""
    upload = await _received(request, svc, video=True)
    try:
        test = check_test(upload)
        check_room(svc.store, upload, svc.settings)
        settings = upload.sfm_settings()
        name = upload.fields.get("name") or (upload.video.name if upload.video else f"{upload.count} photos")
        record = await asyncio.to_thread(svc.captures.add, name=name[:256], test_photos=[], settings=settings,
                                         owner=who.name)
    except BaseException:
        await asyncio.to_thread(_remove, upload.folder)
        raise
    work = reconstruct_job(record, upload, svc.captures, svc.settings, svc.ledger, test)

    def undo() -> None:
        svc.captures.delete(record.id)
        _remove(upload.folder)

    return await _start(svc, who, "capture", work, record.id, undo)


@router.post("/captures/{capture_id}/photos", status_code=202, response_model=CaptureInfo,
             openapi_extra=PHOTOS_BODY)
async def add_capture_photos(capture_id: str, request: Request, svc: Service, who: Caller) -> JSONResponse:
    """Photos added to a capture: registered into its reconstruction (the others' poses fixed) as a job."""
    svc.capture(capture_id, who)                        # 404 before the body is read
    upload = await _received(request, svc, video=False)
    try:
        test = check_test(upload)
        check_room(svc.store, upload, svc.settings)
        record = await asyncio.to_thread(svc.captures.begin, capture_id, "registering", BUSY)
        if record is None:
            current = svc.capture(capture_id, who)
            raise ServiceError(409, "capture_busy", f"capture '{capture_id}' is {current.state}: add photos once it "
                               "is ready" if current.state != "failed" else f"capture '{capture_id}' failed its "
                               "first reconstruction: create a new one", "capture_id")
    except BaseException:
        await asyncio.to_thread(_remove, upload.folder)
        raise
    work = add_photos_job(record, upload, svc.captures, svc.settings, svc.ledger, test)

    def undo() -> None:
        svc.captures.update(record.id, state="ready")
        _remove(upload.folder)

    return await _start(svc, who, "add_photos", work, record.id, undo)


@router.get("/captures", response_model=CaptureList)
async def list_captures(svc: Service, who: Caller) -> CaptureList:
    records = await asyncio.to_thread(svc.captures.list)
    return CaptureList(captures=[capture_info(r) for r in records if who.may_see(r.owner)])


@router.get("/captures/{capture_id}", response_model=CaptureInfo)
async def get_capture(capture_id: str, svc: Service, who: Caller) -> CaptureInfo:
    return capture_info(svc.capture(capture_id, who))


@router.delete("/captures/{capture_id}", status_code=204)
async def delete_capture(capture_id: str, svc: Service, who: Caller) -> Response:
    """The capture's photos and reconstruction; the models trained on it stay (they are models)."""
    record = svc.capture(capture_id, who)
    if record.state in ("reconstructing", "registering"):
        raise ServiceError(409, "capture_busy", f"capture '{capture_id}' is {record.state}: cancel its job first, "
                           "or delete it once the job is over", "capture_id")
    if not await asyncio.to_thread(svc.captures.delete, capture_id):
        raise not_found("capture", capture_id)
    return Response(status_code=204)


@router.post("/captures/{capture_id}/train", response_model=TrainResult, responses=ACCEPTED)
async def train_capture(capture_id: str, svc: Service, who: Caller, body: TrainRequest | None = None) -> Any:
    """A model trained on the capture (less its test photos), from its latest model when warm_start;
    stored as a model linked to it, calibrated, measured on the test photos."""
    body = body or TrainRequest()
    record = svc.capture(capture_id, who)
    work, estimate = await asyncio.to_thread(train_job, record, body, svc.captures, svc.store, svc.settings,
                                             svc.ledger, lambda upload, kind: svc.ingest(upload, kind, who),
                                             svc.executor)
    return await svc.run(svc.jobs.new_id(), "train", work, estimate, body.run_async, who)


@router.post("/captures/{capture_id}/next", response_model=RankResult, responses=ACCEPTED)
async def next_views(capture_id: str, svc: Service, who: Caller, body: NextRequest | None = None) -> Any:
    """The next views to capture: candidates ranked with the capture's latest model, poses in its frame."""
    body = body or NextRequest()
    record = svc.capture(capture_id, who)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(next_job, record, body, svc.captures, svc.store, svc.settings,
                                             artifact_url(job_id), svc.ledger, svc.executor)
    return await svc.run(job_id, "next", work, estimate, body.run_async, who)
