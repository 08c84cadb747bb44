"""What every route depends on: the service's state (settings, store, renderer cache, jobs;
`service.state`) and the OpenAPI metadata shared by the /v1 routers."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Request

from .keys import OPEN, Principal
from .schemas import ErrorResponse, Job
from .state import ServiceState

ERRORS: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse, "description": text} for status, text in (
        (401, "Missing or wrong API key"), (404, "Unknown id"), (409, "No calibration / training cameras"),
        (413, "Body too large"), (415, "Not a model this service reads"), (422, "Invalid field"),
        (429, "Work queue full: retry after Retry-After seconds"))
}
ACCEPTED: dict[int | str, dict[str, Any]] = {
    202: {"model": Job, "description": "Queued as a job: poll GET /v1/jobs/{id}"}}


def service_state(request: Request) -> ServiceState:
    return request.app.state.service


def caller(request: Request) -> Principal:
    """Who is calling (set by service.guard from the Authorization header)."""
    return request.scope.get("state", {}).get("principal") or OPEN


Service = Annotated[ServiceState, Depends(service_state)]
Caller = Annotated[Principal, Depends(caller)]
