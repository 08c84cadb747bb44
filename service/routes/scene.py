"""/v1/models/{id}/scene and /explain: what the page's 3D view draws (service.explain)."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Query, Response

from phd_core.renderers.points import DEFAULT_POINT_CAP

from ..deps import ACCEPTED, ERRORS, Caller, Service
from ..explain import explain_job, load_scene
from ..schemas import ExplainRequest, ExplainResult

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["scene"])
MAX_POINT_CAP = 2_000_000


@router.get("/models/{model_id}/scene", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "The scene binary (format in service/explain.py)"}})
async def scene(model_id: str, svc: Service, who: Caller,
                cap: int = Query(DEFAULT_POINT_CAP, ge=1, le=MAX_POINT_CAP,
                                 description="Points at most: a seeded draw by opacity and size.")) -> Response:
    """The model's splats as points (positions, sizes, colours and opacity), at most `cap`."""
    record = svc.model(model_id, who)
    data = await asyncio.to_thread(load_scene, record, cap, svc.ledger, svc.settings)
    return Response(data, media_type="application/octet-stream", headers={"Cache-Control": "no-cache"})


@router.post("/models/{model_id}/explain", response_model=ExplainResult, responses=ACCEPTED)
async def explain(model_id: str, body: ExplainRequest, svc: Service, who: Caller) -> Any:
    """Per splat of the scene's points: coverage by the captured views, PH-Dropout fragility and
    what `pick` would newly see (phd_core.uq.explain)."""
    record = svc.model(model_id, who)
    job_id = svc.jobs.new_id()
    work, estimate = await asyncio.to_thread(explain_job, record, body, svc.settings, svc.ledger, svc.executor)
    return await svc.run(job_id, "explain", work, estimate, body.run_async, who)
