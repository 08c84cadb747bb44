"""Service settings: where data lives, how much work runs at once, and every input cap.

Each cap is a setting because what is "too large" depends on the machine the service runs
on. pydantic-settings reads every field from a `PHD_<NAME>` environment variable (keyword
arguments win over the environment, the environment over the defaults); the CLI (`phd
serve`) overrides the data dir, workers and queue size from its flags.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pydantic import Field, PositiveFloat, PositiveInt, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from phd_core.executors import EXECUTORS

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


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="PHD_", frozen=True, extra="forbid")

    data_dir: Path = Field(default_factory=default_data_dir)
    api_key: str | None = None                 # when set, every route but /health needs Bearer <key>
    workers: PositiveInt = 1                   # threads running PH-Dropout work
    queue_size: PositiveInt = 8                # jobs waiting for a worker; past it: 429
    retry_after: PositiveInt = 5               # seconds, sent with 429
    cache_size: PositiveInt = 4                # idle models kept in memory (LRU; evicted sooner when the
                                               # memory budget needs their room)
    job_retention: PositiveInt = 256           # finished jobs (and their artefacts) kept in memory
    max_upload_bytes: PositiveInt = 1 << 30    # model upload cap (413 past it)
    max_camera_json_bytes: PositiveInt = 16 << 20  # training-camera JSON part of an upload
    max_json_bytes: PositiveInt = 32 << 20     # any other request body
    max_frame_size: PositiveInt = 4096         # width/height a camera frame may declare
    max_image_size: PositiveInt = 800          # width/height actually rendered (after downscale)
    max_candidates: PositiveInt = 1000         # cameras per rank/select request
    max_training_cameras: PositiveInt = 1000   # cameras used for calibration
    max_samples: PositiveInt = 256             # dropout samples N per request
    async_threshold: PositiveFloat = 2e7       # estimated rendered pixels (views * N * H * W) above which
                                               # a request becomes a 202 job
    memory_budget_bytes: PositiveInt = 4 << 30  # estimated memory of the models in memory, running work and
                                               # upload parses together (service.budget); one request above it: 413
    upload_wait: PositiveFloat = 30.0          # seconds an upload parse waits for budget before 429
    keys_file: Path | None = None              # JSON {"name": "key", ...}: per-key model ownership (docs/service.md)
    cors_origins: list[str] = []               # origins a browser page may call the API from (none by default)
    header_timeout: PositiveFloat = 10.0       # seconds a client may take to send its request headers
    body_timeout: PositiveFloat = 30.0         # seconds a client may pause between body chunks
    min_body_rate: PositiveFloat = 1024.0      # bytes per second a body must keep up: it may take body_timeout
                                               # seconds plus one second per min_body_rate bytes received
    executor: str = "local"                    # where jobs' rendering runs: a name in phd_core.executors
                                               # (local: the worker threads; ray: a Ray cluster, docs/scale-out.md)
    executor_address: str | None = None        # the cluster for it (ray: auto, local, host:6379, ray://host:10001)

    @field_validator("data_dir")
    @classmethod
    def _expand_user(cls, path: Path) -> Path:
        return path.expanduser()

    @field_validator("api_key")
    @classmethod
    def _empty_key_is_none(cls, key: str | None) -> str | None:
        return key or None

    @field_validator("executor")
    @classmethod
    def _known_executor(cls, name: str) -> str:
        if name not in EXECUTORS:
            raise ValueError(EXECUTORS.unknown(name))
        return name

    @classmethod
    def from_env(cls, **overrides) -> "Settings":
        """Defaults, then `PHD_<NAME>` environment variables, then the `overrides` that are not None."""
        return cls(**{k: v for k, v in overrides.items() if v is not None})
