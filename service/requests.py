"""Request checks shared by every endpoint that takes cameras or work settings (calibrate, rank,
select, explain, a capture's next views): cameras parsed and sized within the caps, the number
of dropout samples, the dropout ratio and signal a job uses. Each failure is a 422 (or 409)
naming the field the user wrote."""

from __future__ import annotations

from typing import Any

from phd_core.data.inria import cameras_from_entries, is_inria_cameras
from phd_core.errors import InputError
from phd_core.renderers import DEFAULT_SIGNAL
from phd_core.scene import Camera, cameras_from_json, capture_up

from .errors import ServiceError, invalid
from .schemas import RenderSize
from .settings import Settings
from .store import ModelRecord

FRAME_KEYS = {"fx": "fl_x", "fy": "fl_y", "width": "w", "height": "h"}  # Camera attribute -> frame key


def _camera_field(prefix: str, library_field: str) -> str:
    """'frames[3].fx' from the library -> 'cameras[3].fl_x', the key the user wrote."""
    if library_field.startswith("frames"):
        path, _, key = library_field[len("frames"):].rpartition(".")
        return f"{prefix}{path}.{FRAME_KEYS.get(key, key)}" if path else prefix + key
    return f"{prefix}.{library_field}"


def read_cameras(source: Any, size: RenderSize, settings: Settings, *, field: str, cap: int) -> list[Camera]:
    """Validated cameras at their own size (frames without w/h take the request's width x
    height), or a 422 naming the frame and key."""
    frames = source.get("frames") if isinstance(source, dict) else source
    if isinstance(frames, list) and len(frames) > cap:
        raise invalid(field, f"{len(frames)} cameras exceed the cap of {cap} per request")
    if (size.width is None) != (size.height is None):
        raise invalid("width" if size.width is None else "height", "give width and height together")
    try:
        if is_inria_cameras(source):     # the reference 3DGS trainer's cameras.json, as is
            return cameras_from_entries(source, settings.max_frame_size, file="frames")
        return cameras_from_json(source, width=size.width, height=size.height, max_size=settings.max_frame_size)
    except InputError as exc:
        raise invalid(_camera_field(field, exc.field), exc.reason) from None


def render_size(cameras: list[Camera], size: RenderSize, settings: Settings, *, field: str) -> list[Camera]:
    """The cameras at the requested render size (width x height, else 1/downscale), each
    within the render cap, or a 422 naming the field to change."""
    try:
        if size.width is not None:
            # A width without a height reaches resized, whose check answers 422 naming height.
            cameras = [c.resized(size.width, size.height) for c in cameras]  # type: ignore[arg-type]
        elif size.downscale is not None:
            cameras = [c.scaled(size.downscale) for c in cameras]
    except InputError as exc:
        raise invalid(exc.field if exc.field in ("downscale", "width", "height") else field, exc.reason) from None
    for i, camera in enumerate(cameras):
        if max(camera.width, camera.height) > settings.max_image_size:
            raise invalid(f"{field}[{i}]", f"renders at {camera.width}x{camera.height}, above the cap of "
                          f"{settings.max_image_size} pixels per side (lower the resolution with downscale "
                          "or width/height)")
    return cameras


def parse_cameras(source: Any, size: RenderSize, settings: Settings, *, field: str, cap: int) -> list[Camera]:
    """Validated cameras at the requested render size, or a 422 naming the frame and key."""
    return render_size(read_cameras(source, size, settings, field=field, cap=cap), size, settings, field=field)


def stored_cameras(record: ModelRecord) -> list[Camera]:
    """The training cameras stored with a model (validated at upload), [] when there are none."""
    return cameras_from_json(record.training_frames) if record.training_frames else []


def stored_up(record: ModelRecord) -> tuple[list[float], str]:
    """The model's up and how it was found: as found at upload (`capture_up` on its training
    cameras and opaque splats); for a model stored before that, from its cameras alone."""
    up, rule = record.describe.get("up"), record.describe.get("up_rule")
    if isinstance(up, list) and isinstance(rule, str):
        return up, rule
    found = capture_up(stored_cameras(record))
    return found.vector.tolist(), found.rule


def check_samples(samples: int | None, settings: Settings, default: int) -> int:
    samples = default if samples is None else samples
    if samples > settings.max_samples:
        raise invalid("samples", f"{samples} samples exceed the cap of {settings.max_samples}")
    return samples


def stored_ratio(record: ModelRecord, field: str, given: float | None) -> tuple[float, str]:
    """The dropout ratio to use: the request's, else the stored calibration's, else 409."""
    if given is not None:
        return given, "request"
    if record.calibration is None:
        raise ServiceError(409, "not_calibrated", f"model '{record.id}' has no calibration: calibrate it "
                           f"(POST /v1/models/{record.id}/calibrate) or give {field}", field)
    return float(record.calibration["r_drop"]), "calibration"


def job_signal(given: str | None, ratios: list[tuple[ModelRecord, str]]) -> str:
    """What a job measures zeta on: the request's signal, else that of the stored calibrations
    whose r_drop it uses (ratios: (record, ratio source) per model), else the default. An r_drop
    calibrated on another signal than the request's is a 409 naming `signal`."""
    used = {record.id: record.calibration.get("signal", DEFAULT_SIGNAL) for record, source in ratios
            if source == "calibration" and record.calibration is not None}
    signal = given if given is not None else next(iter(used.values()), DEFAULT_SIGNAL)
    for model_id, calibrated in used.items():
        if calibrated != signal:
            raise ServiceError(409, "signal_mismatch", f"model '{model_id}' was calibrated on the {calibrated} "
                               f"signal, not {signal}: calibrate it with signal '{signal}', give the dropout "
                               "ratio, or use its signal", "signal")
    return signal


def pixels(cameras: list[Camera]) -> int:
    return sum(c.width * c.height for c in cameras)
