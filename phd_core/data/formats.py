"""The capture-format registry: each format says whether a path holds it and loads it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..registry import Registry
from .frames import Dataset


@dataclass(frozen=True)
class DataFormat:
    name: str
    locate: Callable[[Path, str], Path | None]      # (path, split) -> the file to load, or None: not this format
    load: Callable[..., Dataset]                    # (located file, split, **loading options) -> Dataset


FORMATS: Registry[DataFormat] = Registry("capture format")   # sniffed in registration order
