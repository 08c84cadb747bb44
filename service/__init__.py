"""The PH-Dropout REST service (FastAPI): `from service.app import create_app`.

Importing this package imports nothing heavy, so the Python client can share
`service.schemas` (pure pydantic) without pulling in FastAPI or torch.
"""

from typing import Any


def __getattr__(name: str) -> Any:
    if name == "create_app":
        from .app import create_app

        return create_app
    raise AttributeError(name)
