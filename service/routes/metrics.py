"""GET /metrics: the service's Prometheus metrics (service.metrics), for the admin key only.
The app includes this router only when `PHD_METRICS` is on."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..deps import Caller, Service
from ..errors import ServiceError

router = APIRouter()   # not in ROUTERS: service.app includes it when PHD_METRICS is on


@router.get("/metrics", tags=["health"], response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}})
async def metrics(svc: Service, who: Caller) -> Response:
    """Queue, jobs, durations, memory, bytes stored, error answers and uploads (docs/service.md, Metrics)."""
    if not who.admin:
        raise ServiceError(403, "forbidden", "the metrics are for the admin key (PHD_API_KEY), not a named key",
                           "Authorization")
    text = await asyncio.to_thread(generate_latest, svc.metrics.registry)    # reads the store and the data dir
    return Response(text, media_type=CONTENT_TYPE_LATEST)
