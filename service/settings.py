"""Service settings: where data lives, how much work runs at once, and every input cap.

Each cap is a setting because what is "too large" depends on the machine the service runs
on. pydantic-settings reads every field from a `PHD_<NAME>` environment variable (keyword
arguments win over the environment, the environment over the defaults); the CLI (`phd
serve`) overrides the data dir, workers, queue size and executor from its flags. Each
setting is described once, in its field; docs/service.md's table is `settings_table()`
(`python -m service.settings` prints it) and a test keeps the two the same.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pydantic import Field, NonNegativeInt, PositiveFloat, PositiveInt, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from phd_core.executors import EXECUTORS

APP_NAME = "ph-dropout-service"


def default_data_dir() -> Path:
    """`$XDG_DATA_HOME/ph-dropout-service` (`~/.local/share/...`) on Linux; the platform's user data dir elsewhere."""
    home = Path.home()
    if sys.platform == "darwin":
        base = home / "Library" / "Application Support"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA", home / "AppData" / "Local"))
    else:
        base = Path(os.environ.get("XDG_DATA_HOME") or home / ".local" / "share")
    return base / APP_NAME


class Settings(BaseSettings):
    """Every setting, described once: docs/service.md's table is `settings_table()`."""

    model_config = SettingsConfigDict(env_prefix="PHD_", frozen=True, extra="forbid")

    data_dir: Path = Field(default_factory=default_data_dir,
                           description="models and metadata (`phd serve --data-dir`)")
    api_key: str | None = Field(
        None, description="bearer token required on every route but `/health` and the docs (unset: auth off)")
    workers: PositiveInt = Field(1, description="threads running PH-Dropout work (`phd serve --workers`)")
    queue_size: PositiveInt = Field(
        8, description="jobs waiting for a worker; past it: 429 (`phd serve --queue-size`)")
    retry_after: PositiveInt = Field(5, description="seconds, sent with 429")
    cache_size: PositiveInt = Field(
        4, description="idle models kept in memory (LRU; evicted sooner when the memory budget needs their room)")
    job_retention: PositiveInt = Field(
        256, description="finished jobs (and their artefacts) kept, in memory and on disk")
    keep_free_bytes: NonNegativeInt = Field(
        256 << 20, description="free space kept on the data directory's disk: an upload that would leave less is "
                               "refused (507) before or as it streams, so job results and heat maps still fit")
    max_upload_bytes: PositiveInt = Field(1 << 30, description="model upload cap (413 past it)")
    max_camera_json_bytes: PositiveInt = Field(16 << 20, description="training-camera JSON part of an upload")
    max_json_bytes: PositiveInt = Field(32 << 20, description="any other request body")
    max_frame_size: PositiveInt = Field(4096, description="width/height a camera frame may declare")
    max_image_size: PositiveInt = Field(800, description="width/height actually rendered (after downscale)")
    max_candidates: PositiveInt = Field(1000, description="cameras per rank/select request")
    max_training_cameras: PositiveInt = Field(1000, description="cameras per calibration / upload")
    max_samples: PositiveInt = Field(256, description="dropout samples N per request")
    max_capture_photos: PositiveInt = Field(300, description="photos a capture may hold (a video is sampled to at "
                                            "most this many frames)")
    capture_max_size: PositiveInt = Field(1600, description="a capture's photos larger than this many pixels on their "
                                          "longer side are downscaled to it before structure-from-motion")
    async_threshold: PositiveFloat = Field(
        2e7, description="estimated rendered pixels (views * N * H * W) above which a request becomes a 202 job")
    memory_budget_bytes: PositiveInt = Field(
        4 << 30, description="estimated memory of the models in memory, running work and upload parses together "
                             "(service.budget); one request above it: 413")
    upload_wait: PositiveFloat = Field(30.0, description="seconds an upload parse waits for budget before 429")
    keys_file: Path | None = Field(
        None, description='JSON `{"name": "key"}`: named keys, each owning its models and jobs')
    metrics: bool = Field(
        True, description="serve `GET /metrics` (Prometheus text format) to the admin key (`PHD_API_KEY`; to anyone "
                          "when no key is set); false: no such route")
    cors_origins: list[str] = Field(
        [], description="JSON list of origins whose pages may call the API (none by default)")
    header_timeout: PositiveFloat = Field(10.0, description="seconds a client may take to send its request headers")
    body_timeout: PositiveFloat = Field(30.0, description="seconds a client may pause between body chunks")
    min_body_rate: PositiveFloat = Field(
        1024.0, description="bytes per second a body must keep up: it may take `PHD_BODY_TIMEOUT` seconds plus one "
                            "second per this many bytes received")
    executor: str = Field(
        "local", description="where jobs' rendering runs: a name in phd_core.executors (`local`: the worker threads; "
                             "`ray`: a Ray cluster, docs/scale-out.md; `phd serve --ray`)")
    executor_address: str | None = Field(
        None, description="the cluster for it (ray: `auto`, `local`, `host:6379`, `ray://host:10001`; "
                          "`phd serve --ray ADDRESS`)")

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


def shown_default(name: str) -> str:
    """A setting's default as docs/service.md shows it: sizes in MiB/GiB, unset for None, and
    for a computed default the first line of its function's docstring."""
    field = Settings.model_fields[name]
    if field.default_factory is not None:
        doc = field.default_factory.__doc__
        assert doc is not None, f"{name}'s default function needs a docstring to be shown"
        return doc.split("\n")[0].rstrip(".")
    value = field.default
    if value is None:
        return "unset"
    if name.endswith("_bytes"):
        return f"{value >> 30} GiB" if value % (1 << 30) == 0 else f"{value >> 20} MiB"
    if isinstance(value, float):
        return f"{value:.0e}".replace("e+0", "e") if value >= 1e6 else f"{value:g}"
    return f"`{value}`" if isinstance(value, (str, list)) else str(value)


def settings_table() -> str:
    """The markdown table of every setting: environment variable, default, meaning."""
    rows = ["| variable | default | meaning |", "|---|---|---|"]
    rows += [f"| `PHD_{name.upper()}` | {shown_default(name)} | {field.description} |"
             for name, field in Settings.model_fields.items()]
    return "\n".join(rows)


if __name__ == "__main__":
    print(settings_table())
