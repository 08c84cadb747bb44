"""The work: calibrate a model, rank candidate poses, select between two models."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter

from ..deps import ACCEPTED, ERRORS, Caller, Service
from ..schemas import CalibrateRequest, Calibration, RankRequest, RankResult, SelectRequest, SelectResult
from ..work import calibrate_job, rank_job, select_job

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["work"])


@router.post("/models/{model_id}/calibrate", response_model=Calibration, responses=ACCEPTED)
async def calibrate(model_id: str, svc: Service, who: Caller, body: CalibrateRequest | None = None) -> Any:
    """PH-Dropout calibration (Algorithm 1) on the training cameras; stored with the model."""
    body = body or CalibrateRequest()
    record = svc.model(model_id, who)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(calibrate_job, record, body, svc.settings, svc.store, svc.ledger,
                                             svc.executor)
    return await svc.run(job_id, "calibrate", work, estimate, body.run_async, who)


@router.post("/models/{model_id}/rank", response_model=RankResult, responses=ACCEPTED)
async def rank(model_id: str, body: RankRequest, svc: Service, who: Caller) -> Any:
    """Candidate poses in the order to capture them (next-best view; strategy in the body, docs/nbv.md)."""
    record = svc.model(model_id, who)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(rank_job, record, body, svc.settings, artifact_url(job_id),
                                             svc.ledger, svc.executor, svc.store)
    return await svc.run(job_id, "rank", work, estimate, body.run_async, who)


@router.post("/select", response_model=SelectResult, responses=ACCEPTED)
async def select(body: SelectRequest, svc: Service, who: Caller) -> Any:
    """Per view, which of two models to trust (ensemble selection; rule in the body)."""
    record_a, record_b = svc.model(body.model_a, who, "model_a"), svc.model(body.model_b, who, "model_b")
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(select_job, record_a, record_b, body, svc.settings,
                                             artifact_url(job_id), svc.ledger, svc.executor)
    return await svc.run(job_id, "select", work, estimate, body.run_async, who)


def artifact_url(job_id: str):
    return lambda name: f"/v1/jobs/{job_id}/artifacts/{name}"
