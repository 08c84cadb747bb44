"""GET /health: liveness, version and whether the other routes need a key (never needs the API key)."""

from __future__ import annotations

from fastapi import APIRouter

import phd_core

from ..deps import Service
from ..schemas import Health

router = APIRouter()


@router.get("/health", response_model=Health, tags=["health"])
async def health(svc: Service) -> Health:
    keyed = svc.settings.api_key is not None or svc.settings.keys_file is not None
    return Health(version=phd_core.__version__, key_required=keyed)
