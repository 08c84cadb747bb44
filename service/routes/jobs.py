"""/v1/jobs: state, progress and results of jobs, cancelling, and their PNG artefacts."""

from __future__ import annotations

from fastapi import APIRouter, Response

from ..deps import ERRORS, Service
from ..errors import ServiceError
from ..schemas import Job

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["jobs"])


@router.get("/jobs/{job_id}", response_model=Job)
async def get_job(job_id: str, svc: Service) -> Job:
    return svc.job(job_id).to_schema()


@router.delete("/jobs/{job_id}", response_model=Job)
async def cancel_job(job_id: str, svc: Service) -> Job:
    """Cancel: a queued job stops at once, a running one at its next view."""
    svc.job(job_id)
    return svc.jobs.cancel(job_id).to_schema()


@router.get("/jobs/{job_id}/artifacts/{name}", response_class=Response,
        responses={200: {"content": {"image/png": {}}}})
async def get_artifact(job_id: str, name: str, svc: Service) -> Response:
    data = svc.job(job_id).artifacts.get(name)
    if data is None:
        raise ServiceError(404, "artifact_not_found", f"job '{job_id}' has no artefact '{name}'", "name")
    return Response(data, media_type="image/png")
