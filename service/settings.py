"""Service settings: where data lives, how much work runs at once, and every input cap.

Each cap is a setting because what is "too large" depends on the machine the service runs
on. `Settings.from_env()` reads `PHD_*` environment variables (see `ENV_VARS`); the CLI
(`phd serve`) overrides host, port, data dir and workers from its flags.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path

APP_NAME = "ph-dropout-service"


def default_data_dir() -> Path:
    """The user's data directory for this application (XDG on Linux)."""
    home = Path.home()
    if sys.platform == "darwin":
        base = home / "Library" / "Application Support"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA", home / "AppData" / "Local"))
    else:
        base = Path(os.environ.get("XDG_DATA_HOME") or home / ".local" / "share")
    return base / APP_NAME


@dataclass(frozen=True)
class Settings:
    data_dir: Path = field(default_factory=default_data_dir)
    api_key: str | None = None            # when set, every route but /health needs Bearer <key>
    workers: int = 1                      # threads running PH-Dropout work
    queue_size: int = 8                   # jobs waiting for a worker; past it: 429
    retry_after: int = 5                  # seconds, sent with 429
    cache_size: int = 4                   # loaded renderers kept in memory (LRU)
    job_retention: int = 256              # finished jobs (and their artefacts) kept in memory
    max_upload_bytes: int = 1 << 30       # model upload cap (413 past it)
    max_camera_json_bytes: int = 16 << 20  # training-camera JSON part of an upload
    max_json_bytes: int = 32 << 20        # any other request body
    max_frame_size: int = 4096            # width/height a camera frame may declare
    max_image_size: int = 800             # width/height actually rendered (after downscale)
    max_candidates: int = 1000            # cameras per rank/select request
    max_training_cameras: int = 1000      # cameras used for calibration
    max_samples: int = 256                # dropout samples N per request
    async_threshold: float = 2e7          # estimated rendered pixels (views * N * H * W) above which
                                          # a request becomes a 202 job

    def __post_init__(self) -> None:
        object.__setattr__(self, "data_dir", Path(self.data_dir).expanduser())
        for f in fields(self):
            if f.name in ("data_dir", "api_key"):
                continue
            value = getattr(self, f.name)
            if not value > 0:
                raise ValueError(f"setting {f.name} must be positive, got {value}")
        if self.api_key == "":
            object.__setattr__(self, "api_key", None)

    @classmethod
    def from_env(cls, **overrides) -> "Settings":
        """Defaults, then `PHD_<NAME>` environment variables, then `overrides` (None = unset)."""
        values: dict = {}
        for f in fields(cls):
            raw = os.environ.get(ENV_VARS[f.name])
            if raw is None or raw == "":
                continue
            if f.name == "data_dir" or f.name == "api_key":
                values[f.name] = raw
            elif f.name == "async_threshold":
                values[f.name] = float(raw)
            else:
                values[f.name] = int(raw)
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)


ENV_VARS = {f.name: f"PHD_{f.name.upper()}" for f in fields(Settings)}
