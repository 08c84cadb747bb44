"""GET /health: liveness and version (never needs the API key)."""

from __future__ import annotations

from fastapi import APIRouter

import phd_core

from ..schemas import Health

router = APIRouter()


@router.get("/health", response_model=Health, tags=["health"])
async def health() -> Health:
    return Health(version=phd_core.__version__)
