"""The REST API: thin routes over `phd_core`, versioned under /v1.

`create_app(settings)` builds the FastAPI app. Routes check requests (parsing a thousand
cameras takes a few hundred ms, so on a thread) and hand the work to the bounded worker
pool (`service.jobs`); nothing heavy runs on the event loop. Every
error, FastAPI's own included, answers with `{"error": {"code", "message", "field"}}`.

    GET    /health                          liveness and version (never needs the API key)
    POST   /v1/models                       upload a model (multipart: file, cameras, name)
    GET    /v1/models                       list models
    GET    /v1/models/{id}                  one model
    DELETE /v1/models/{id}                  delete it (file, metadata and calibration)
    POST   /v1/models/{id}/calibrate        PH-Dropout calibration -> r_drop, stored with the model
    POST   /v1/models/{id}/rank             candidate poses, most uncertain first
    POST   /v1/select                       per view, which of two models to trust
    GET    /v1/jobs/{id}                    state, progress, result of a job
    DELETE /v1/jobs/{id}                    cancel a job
    GET    /v1/jobs/{id}/artifacts/{name}   a PNG a job produced (heat map, selected image)
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

import phd_core
from phd_core.errors import InputError
from phd_core.models import FAMILIES, load_model

from .errors import ServiceError, from_exception, not_found
from .guard import Guard
from .jobs import JobManager, JobRecord, QueueFull, Work
from .schemas import (Calibration, CalibrateRequest, ErrorResponse, Health, Job, ModelInfo, ModelList, RankRequest,
                      RankResult, RenderSize, SelectRequest, SelectResult)
from .settings import Settings
from .store import ModelRecord, ModelStore
from .upload import Upload, parse_camera_json, receive_upload, sniff_kind
from .work import RendererCache, calibrate_job, parse_cameras, rank_job, select_job

log = logging.getLogger("phd.service")

ERRORS: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse, "description": text} for status, text in (
        (401, "Missing or wrong API key"), (404, "Unknown id"), (409, "No calibration / training cameras"),
        (413, "Body too large"), (415, "Not a model this service reads"), (422, "Invalid field"),
        (429, "Work queue full: retry after Retry-After seconds"))
}
ACCEPTED = {202: {"model": Job, "description": "Queued as a job: poll GET /v1/jobs/{id}"}}
NETWORK_FACTS = ("encoding", "depth", "width", "parameters", "samples_per_ray")  # NeRF describe() keys
UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["file"], "properties": {
        "file": {"type": "string", "format": "binary", "description": "3DGS PLY or NeRF checkpoint"},
        "cameras": {"type": "string", "description": "Training cameras as JSON (transforms.json or a list of frames)"},
        "name": {"type": "string", "description": "Display name (default: the file name)"},
    }}}}}}


@dataclass
class ServiceState:
    settings: Settings
    store: ModelStore
    cache: RendererCache
    jobs: JobManager | None = None

    def model(self, model_id: str, field: str | None = None) -> ModelRecord:
        record = self.store.get(model_id)
        if record is None:
            raise not_found("model", model_id, field)
        return record

    def job(self, job_id: str) -> JobRecord:
        job = self.jobs.get(job_id)
        if job is None:
            raise not_found("job", job_id)
        return job

    async def run(self, job_id: str, kind: str, work: Work, estimate: float, run_async: bool) -> Any:
        """Queue the work; answer 202 with the job when asked or when it is big, else wait for it."""
        try:
            job = self.jobs.submit(job_id, kind, work, estimate)
        except QueueFull as exc:
            raise ServiceError(429, "queue_full", f"the work queue is full ({exc}); retry later", None,
                               {"Retry-After": str(self.settings.retry_after)}) from None
        if run_async or estimate > self.settings.async_threshold:
            return JSONResponse(job.to_schema().model_dump(mode="json"), status_code=202,
                                headers={"Location": f"/v1/jobs/{job.id}"})
        await asyncio.wrap_future(job.done)
        if job.state == "succeeded":
            return job.result
        if job.state == "cancelled":
            raise ServiceError(409, "job_cancelled", f"job '{job.id}' was cancelled before it finished")
        raise job.error

    def ingest(self, upload: Upload, kind: str) -> ModelRecord:
        """Load the uploaded file fully (worker thread), then move it into the store."""
        cameras = None
        if upload.cameras is not None:  # the cheap check first
            cameras = parse_cameras(parse_camera_json(upload.cameras), RenderSize(), self.settings,
                                    field="cameras", cap=self.settings.max_training_cameras)
        renderer = load_model(upload.path)
        cameras = cameras if cameras is not None else renderer.training_cameras
        frames = None if not cameras else [c.to_frame() for c in cameras]
        name = upload.name or upload.filename or f"model{FAMILIES[kind].extension}"
        # The stored cameras are the truth about training cameras, not what the file carried.
        facts = {k: v for k, v in renderer.describe().items() if k != "has_training_cameras"}
        record = self.store.add(upload.path, name=name, kind=renderer.kind, size_bytes=upload.size,
                                sha256=upload.sha256, num_units=renderer.num_units, describe=facts,
                                training_frames=frames)
        self.cache.put(record.id, renderer)
        return record


def service_state(request: Request) -> ServiceState:
    return request.app.state.service


Service = Annotated[ServiceState, Depends(service_state)]


def model_info(record: ModelRecord) -> ModelInfo:
    facts = record.describe
    bounds = facts.get("bounds")
    network = {k: facts[k] for k in NETWORK_FACTS if k in facts} or None
    return ModelInfo(
        id=record.id, name=record.name, kind=record.kind, num_units=record.num_units,
        sh_degree=facts.get("sh_degree") if isinstance(facts.get("sh_degree"), int) else None,
        network=network,
        bounds=bounds if isinstance(bounds, dict) and all(isinstance(v, list) for v in bounds.values()) else None,
        size_bytes=record.size_bytes, sha256=record.sha256, created_at=record.created_at,
        has_training_cameras=bool(record.training_frames),
        num_training_cameras=len(record.training_frames or []),
        has_calibration=record.calibration is not None,
        calibration=None if record.calibration is None else Calibration(**record.calibration),
        details=facts)


# ----------------------------------------------------------------------------- routes

root = APIRouter()
v1 = APIRouter(prefix="/v1", responses=ERRORS)


@root.get("/health", response_model=Health, tags=["health"])
async def health() -> Health:
    return Health(version=phd_core.__version__)


@v1.post("/models", status_code=201, response_model=ModelInfo, tags=["models"], openapi_extra=UPLOAD_BODY)
async def upload_model(request: Request, svc: Service) -> JSONResponse:
    """Upload a model (3DGS PLY or NeRF checkpoint) with optional training cameras."""
    temp = svc.store.new_temp_path()
    try:
        upload = await receive_upload(request, temp, svc.settings.max_camera_json_bytes)
        kind = sniff_kind(upload.head)
        record = await asyncio.to_thread(svc.ingest, upload, kind)
    finally:
        temp.unlink(missing_ok=True)  # gone already after a successful move into the store
    info = model_info(record)
    return JSONResponse(info.model_dump(mode="json"), status_code=201, headers={"Location": f"/v1/models/{record.id}"})


@v1.get("/models", response_model=ModelList, tags=["models"])
async def list_models(svc: Service) -> ModelList:
    records = await asyncio.to_thread(svc.store.list)
    return ModelList(models=[model_info(r) for r in records])


@v1.get("/models/{model_id}", response_model=ModelInfo, tags=["models"])
async def get_model(model_id: str, svc: Service) -> ModelInfo:
    return model_info(svc.model(model_id))


@v1.delete("/models/{model_id}", status_code=204, tags=["models"])
async def delete_model(model_id: str, svc: Service) -> Response:
    if not await asyncio.to_thread(svc.store.delete, model_id):
        raise not_found("model", model_id)
    svc.cache.evict(model_id)
    return Response(status_code=204)


@v1.post("/models/{model_id}/calibrate", response_model=Calibration, responses=ACCEPTED, tags=["work"])
async def calibrate(model_id: str, svc: Service, body: CalibrateRequest | None = None) -> Any:
    """PH-Dropout calibration (Algorithm 1) on the training cameras; stored with the model."""
    body = body or CalibrateRequest()
    record = svc.model(model_id)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(calibrate_job, record, body, svc.settings, svc.store, svc.cache)
    return await svc.run(job_id, "calibrate", work, estimate, body.run_async)


@v1.post("/models/{model_id}/rank", response_model=RankResult, responses=ACCEPTED, tags=["work"])
async def rank(model_id: str, body: RankRequest, svc: Service) -> Any:
    """Rank candidate poses by sigma_max, most uncertain first (next-best view)."""
    record = svc.model(model_id)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(rank_job, record, body, svc.settings, svc.cache, _artifact_url(job_id))
    return await svc.run(job_id, "rank", work, estimate, body.run_async)


@v1.post("/select", response_model=SelectResult, responses=ACCEPTED, tags=["work"])
async def select(body: SelectRequest, svc: Service) -> Any:
    """Per view, the model with the lower mean zeta (ensemble selection)."""
    record_a, record_b = svc.model(body.model_a, "model_a"), svc.model(body.model_b, "model_b")
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(select_job, record_a, record_b, body, svc.settings, svc.cache,
                                             _artifact_url(job_id))
    return await svc.run(job_id, "select", work, estimate, body.run_async)


@v1.get("/jobs/{job_id}", response_model=Job, tags=["jobs"])
async def get_job(job_id: str, svc: Service) -> Job:
    return svc.job(job_id).to_schema()


@v1.delete("/jobs/{job_id}", response_model=Job, tags=["jobs"])
async def cancel_job(job_id: str, svc: Service) -> Job:
    """Cancel: a queued job stops at once, a running one at its next view."""
    svc.job(job_id)
    return svc.jobs.cancel(job_id).to_schema()


@v1.get("/jobs/{job_id}/artifacts/{name}", tags=["jobs"], response_class=Response,
        responses={200: {"content": {"image/png": {}}}})
async def get_artifact(job_id: str, name: str, svc: Service) -> Response:
    data = svc.job(job_id).artifacts.get(name)
    if data is None:
        raise ServiceError(404, "artifact_not_found", f"job '{job_id}' has no artefact '{name}'", "name")
    return Response(data, media_type="image/png")


def _artifact_url(job_id: str):
    return lambda name: f"/v1/jobs/{job_id}/artifacts/{name}"


# ----------------------------------------------------------------------------- errors

def _error(status: int, code: str, message: str, field: str | None = None,
           headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message, "field": field}}, status_code=status,
                        headers=headers)


def _field_from_loc(loc: tuple) -> str | None:
    """('body', 'cameras', 0, 'w') -> 'cameras[0].w'."""
    parts = [p for p in loc if p not in ("body", "path", "query")]
    field = ""
    for part in parts:
        if isinstance(part, int):
            field += f"[{part}]"
        elif not str(part).startswith(("list[", "dict[", "function-")):  # union branch labels
            field += f".{part}" if field else str(part)
    return field or None


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        return _error(exc.status, exc.code, exc.message, exc.field, exc.headers)

    @app.exception_handler(InputError)
    async def input_error(_: Request, exc: InputError) -> JSONResponse:
        known = from_exception(exc)
        return _error(known.status, known.code, known.message, known.field)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        first = errors[0] if errors else {"loc": (), "msg": "invalid request", "type": ""}
        if first.get("type") == "json_invalid":
            return _error(400, "invalid_json", f"the body is not valid JSON: {first.get('ctx', {}).get('error', '')}")
        field = _field_from_loc(tuple(first.get("loc", ())))
        message = first.get("msg", "invalid value")
        if first.get("type") == "missing" and field is None:
            message = "a JSON request body is required"
        more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
        return _error(422, "invalid_input", f"{field or 'body'}: {message}{more}", field)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        codes = {404: "not_found", 405: "method_not_allowed"}
        return _error(exc.status_code, codes.get(exc.status_code, "http_error"), str(exc.detail),
                      headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def unexpected(_: Request, exc: Exception) -> JSONResponse:
        # Starlette logs the traceback; the user gets the shape, not the stack.
        return _error(500, "internal_error", f"unexpected {type(exc).__name__}; see the server log")


# ----------------------------------------------------------------------------- the app

def create_app(settings: Settings | None = None) -> FastAPI:
    """The service on `settings.data_dir` (swept of unfinished uploads before serving)."""
    settings = settings or Settings.from_env()
    store = ModelStore(settings.data_dir)
    swept = store.sweep()
    if swept:
        log.warning("removed %d unfinished upload(s) from %s", len(swept), settings.data_dir)
    state = ServiceState(settings=settings, store=store, cache=RendererCache(store, settings.cache_size))

    @asynccontextmanager
    async def lifespan(_: FastAPI):
        state.jobs = JobManager(settings.workers, settings.queue_size, settings.job_retention)
        try:
            yield
        finally:
            await asyncio.to_thread(state.jobs.shutdown)

    app = FastAPI(title="PH-Dropout service", version=phd_core.__version__, lifespan=lifespan,
                  description="Post hoc epistemic uncertainty for trained Gaussian Splatting and NeRF models: "
                              "next-best-view ranking and per-view model selection.")
    app.state.service = state
    install_error_handlers(app)
    app.include_router(root)
    app.include_router(v1)
    app.add_middleware(Guard, settings=settings)
    return app
