"""/v1/jobs: state, progress and results of jobs, cancelling, and their PNG artefacts."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Response

from ..deps import ERRORS, Caller, Service
from ..errors import ServiceError
from ..schemas import Job

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["jobs"])


@router.get("/jobs/{job_id}", response_model=Job)
async def get_job(job_id: str, svc: Service, who: Caller) -> Job:
    return svc.job(job_id, who)


@router.delete("/jobs/{job_id}", response_model=Job)
async def cancel_job(job_id: str, svc: Service, who: Caller) -> Job:
    """Cancel: a queued job stops at once, a running one at its next view."""
    job = svc.job(job_id, who)
    live = svc.jobs.cancel(job_id)          # None: finished before the last restart, nothing to cancel
    return job if live is None else live.to_schema()


@router.get("/jobs/{job_id}/artifacts/{name}", response_class=Response,
        responses={200: {"content": {"image/png": {}}}})
async def get_artifact(job_id: str, name: str, svc: Service, who: Caller) -> Response:
    data = await asyncio.to_thread(svc.artifact, job_id, name, who)
    if data is None:
        raise ServiceError(404, "artifact_not_found", f"job '{job_id}' has no artefact '{name}'", "name")
    return Response(data, media_type="image/png")
