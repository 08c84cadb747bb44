"""The REST API: thin routes over `phd_core`, versioned under /v1.

`create_app(settings)` builds the FastAPI app from the routers in `service.routes` (one module
per resource) and the state in `service.deps`. Routes check requests (parsing a thousand
cameras takes a few hundred ms, so on a thread) and hand the work to the bounded worker
pool (`service.jobs`); nothing heavy runs on the event loop. Every
error, FastAPI's own included, answers with `{"error": {"code", "message", "field"}}`.

    GET    /health                          liveness and version (never needs the API key)
    GET    /ui/, /docs, /redoc              the web page and the API's documentation (local files only)
    POST   /v1/models                       upload a model (multipart: file, cameras, name; or a folder's
                                            files / a zip archive: service.folders)
    GET    /v1/models                       list models
    GET    /v1/models/{id}                  one model
    DELETE /v1/models/{id}                  delete it (file, metadata and calibration)
    POST   /v1/models/{id}/poses            ranked poses as a capture tool's files (as `phd rank --export`)
    POST   /v1/models/{id}/calibrate        PH-Dropout calibration -> r_drop, stored with the model
    POST   /v1/models/{id}/rank             candidate poses in the order to capture them
    POST   /v1/select                       per view, which of two models to trust
    GET    /v1/models/{id}/scene            the splats as points for the page's 3D view (a binary)
    POST   /v1/models/{id}/explain          per point: coverage, fragility, what a pick newly sees
    POST   /v1/captures                     photos (or a video) in: structure-from-motion as a job (service.loop)
    GET    /v1/captures, /v1/captures/{id}  captures: rounds, photos, models, the poses asked for
    DELETE /v1/captures/{id}                delete a capture (its folder; its models stay as models)
    POST   /v1/captures/{id}/photos         photos added: registered into its reconstruction, a new round
    POST   /v1/captures/{id}/train          a model trained on it (warm start), calibrated, measured
    POST   /v1/captures/{id}/next           the next views to capture, ranked with its latest model
    GET    /v1/jobs/{id}                    state, progress, result of a job
    DELETE /v1/jobs/{id}                    cancel a job
    GET    /v1/jobs/{id}/artifacts/{name}   a PNG a job produced (heat map, selected image)
    GET    /metrics                         Prometheus metrics (admin key; PHD_METRICS=false: none)
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException

import phd_core
from phd_core.allocator import bounded_heap, keep_freed_memory, one_arena
from phd_core.errors import InputError
from phd_core.executors import make_executor
from phd_core.renderers import FAMILIES

from .budget import MemoryLedger
from .captures import CaptureStore
from .errors import ServiceError, error_body, from_exception, json_problem
from .guard import Guard
from .jobs import JobManager
from .jobstore import JobStore
from .keys import KeyRing
from .metrics import Counting
from .routes import ROUTERS, metrics
from .settings import Settings
from .state import ServiceState
from .store import DB_NAME, SCHEMA_VERSION, ModelStore
from .work import model_loader

log = logging.getLogger("phd.service")


# ----------------------------------------------------------------------------- errors

def _error(status: int, code: str, message: str, field: str | None = None,
           headers: dict[str, str] | None = None) -> Response:
    return Response(error_body(code, message, field), status, headers, media_type="application/json")


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
    async def service_error(_: Request, exc: ServiceError) -> Response:
        return _error(exc.status, exc.code, exc.message, exc.field, exc.headers)

    @app.exception_handler(InputError)
    async def input_error(_: Request, exc: InputError) -> Response:
        known = from_exception(exc)
        assert known is not None  # from_exception answers every InputError
        return _error(known.status, known.code, known.message, known.field)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> Response:
        errors = exc.errors()
        first: dict[str, Any] = errors[0] if errors else {"loc": (), "msg": "invalid request", "type": ""}
        if first.get("type") == "json_invalid":
            return _error(400, "invalid_json", f"the body is not valid JSON: {first.get('ctx', {}).get('error', '')}")
        field = _field_from_loc(tuple(first.get("loc", ())))
        message = first.get("msg", "invalid value")
        if first.get("type") == "missing" and field is None:
            message = "a JSON request body is required"
        more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
        return _error(422, "invalid_input", f"{field or 'body'}: {message}{more}", field)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> Response:
        problem = json_problem(exc.__cause__)   # FastAPI's 400 for a body json.loads refused other than by syntax
        if exc.status_code == 400 and problem is not None:
            return _error(400, "invalid_json", f"the body is not valid JSON: {problem}")
        codes = {404: "not_found", 405: "method_not_allowed"}
        return _error(exc.status_code, codes.get(exc.status_code, "http_error"), str(exc.detail),
                      headers=getattr(exc, "headers", None))

    # Exceptions no handler answers become a JSON 500 in service.guard, which keeps the connection.


# ----------------------------------------------------------------------------- the app

def create_app(settings: Settings | None = None) -> FastAPI:
    """The service on `settings.data_dir` (swept of unfinished uploads before serving)."""
    settings = settings or Settings.from_env()
    keep_freed_memory()     # what the `phd` command sets (phd_core.allocator); bounded_heap then narrows it
    one_arena()             # workers and request threads reuse each other's freed memory (phd_core.allocator)
    bounded_heap()          # large blocks are unmapped when freed: resident memory follows the live tensors
    store = ModelStore(settings.data_dir)
    if store.migrated_from is not None:
        log.warning("store in %s migrated from schema version %d to %d (the database before: %s.v%d.bak)",
                    settings.data_dir, store.migrated_from, SCHEMA_VERSION, DB_NAME, store.migrated_from)
    swept = store.sweep()
    if swept:
        log.warning("removed %d unfinished upload(s) from %s", len(swept), settings.data_dir)
    keys = KeyRing(settings.api_key, settings.keys_file)
    job_store = JobStore(store, settings.job_retention)
    interrupted = job_store.recover()
    if interrupted:
        log.warning("%d job(s) were unfinished at the last shutdown: marked failed (interrupted)", interrupted)
    captures = CaptureStore(store)
    undone = captures.recover()
    if undone:
        log.warning("removed %d unfinished capture folder(s) or photo upload(s)", len(undone))
    state = ServiceState(settings=settings, store=store, job_store=job_store, captures=captures,
                         ledger=MemoryLedger(settings.memory_budget_bytes, settings.cache_size, model_loader(store)),
                         executor=make_executor(settings.executor, settings.executor_address))

    @asynccontextmanager
    async def lifespan(_: FastAPI):
        await asyncio.to_thread(state.executor.connect)   # a cluster: fail at start-up, not at the first job
        state.jobs = JobManager(settings.workers, settings.queue_size, settings.job_retention,
                                on_change=state.persist_job)
        try:
            yield
        finally:
            await asyncio.to_thread(state.jobs.shutdown)
            store.close()

    app = FastAPI(title="PH-Dropout service", version=phd_core.__version__, lifespan=lifespan,
                  docs_url=None, redoc_url=None,      # served from local files by routes.page
                  description=f"Post hoc epistemic uncertainty for trained models ({', '.join(FAMILIES)}): "
                              "next-best-view ranking and per-view model selection.")
    app.state.service = state
    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    if settings.metrics:
        state.metrics.watch(settings, store, job_store, state.ledger, lambda: state.jobs.waiting())
        app.include_router(metrics.router)
    app.add_middleware(Guard, settings=settings, keys=keys)
    app.add_middleware(Counting, metrics=state.metrics)    # outside the guard: its answers are counted too
    if settings.cors_origins:  # outermost: preflights are answered before the key check
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "Content-Type"], expose_headers=["Location", "Retry-After"],
                           max_age=600)
    return app
