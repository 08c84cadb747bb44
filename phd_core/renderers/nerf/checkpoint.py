"""Checkpoints: safetensors files (tensors that cannot execute code on load) with the config
and the capture the model was trained on (`provenance.TrainedOn`) in the header and the
training cameras as JSON frames."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from ...errors import InputError
from ...io import write_bytes_atomic
from ...scene import Camera, cameras_from_json
from ..provenance import TrainedOn
from .config import NeRFConfig
from .field import RadianceField
from .renderer import NeRFRenderer

CHECKPOINT_FORMAT = "phd-nerf"
CHECKPOINT_VERSION = "1"
CAMERAS_TENSOR = "training_cameras_json"  # uint8 JSON bytes: [frame, ...] from Camera.to_frame()
MAX_HEADER_BYTES = 100 << 20


# --------------------------------------------------------------------------- checkpoints

def save_nerf(renderer_or_model: NeRFRenderer | RadianceField, path: str | Path,
              training_cameras: list[Camera] | None = None) -> None:
    """Write a checkpoint atomically (temp file + os.replace).

    Training cameras come from the renderer unless given.
    """
    write_bytes_atomic(path, nerf_bytes(renderer_or_model, training_cameras))


def nerf_bytes(renderer_or_model: NeRFRenderer | RadianceField, training_cameras: list[Camera] | None = None) -> bytes:
    """The checkpoint as bytes: safetensors with our metadata in the header."""
    trained_on = None
    if isinstance(renderer_or_model, NeRFRenderer):
        model = renderer_or_model.model
        training_cameras = training_cameras if training_cameras is not None else renderer_or_model.training_cameras
        trained_on = renderer_or_model.trained_on
    else:
        model = renderer_or_model
    tensors = {name: t.detach().contiguous() for name, t in model.state_dict().items()}
    if training_cameras is not None:
        frames = json.dumps([camera.to_frame() for camera in training_cameras]).encode()
        tensors[CAMERAS_TENSOR] = torch.frombuffer(bytearray(frames), dtype=torch.uint8)
    metadata = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
                "config": json.dumps(model.config.to_dict())}
    if trained_on is not None:
        metadata["trained_on"] = json.dumps(trained_on.fields())
    return st_save(tensors, metadata=metadata)


def _header(data: bytes) -> dict | None:
    """The parsed safetensors header if `data` holds all of it, else None."""
    if len(data) < 8:
        return None
    (size,) = struct.unpack("<Q", data[:8])
    if size > MAX_HEADER_BYTES or len(data) < 8 + size:
        return None
    try:
        header = json.loads(data[8:8 + size])
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):   # not JSON, or nested past the decoder
        return None
    return header if isinstance(header, dict) else None


def is_nerf_checkpoint(head: bytes) -> bool:
    """True if `head` (the first bytes of a file; 4 KiB is plenty) starts like our checkpoint:
    a safetensors header whose metadata says format "phd-nerf".

    The config and the tensor list are small, so the header of a default model is about
    2 KB. When `head` cuts the header short, the format marker is looked up in what it holds.
    """
    if len(head) < 9 or head[8:9] != b"{":
        return False
    (size,) = struct.unpack("<Q", head[:8])
    if size > MAX_HEADER_BYTES:
        return False
    header = _header(head)
    if header is None:
        return b'"format":"phd-nerf"' in head[8:8 + size]
    meta = header.get("__metadata__")
    return isinstance(meta, dict) and meta.get("format") == CHECKPOINT_FORMAT


def load_nerf(path: str | Path, **renderer_options: Any) -> NeRFRenderer:
    """Load a checkpoint file (see `load_nerf_bytes`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError("model", f"cannot read {path}: {exc.strerror or exc}") from None
    return load_nerf_bytes(data, path.name, **renderer_options)


def load_nerf_bytes(data: bytes, name: str = "model", **renderer_options: Any) -> NeRFRenderer:
    """Validate and load a checkpoint held in memory; no code runs on load.

    Every failure is an `InputError(field="model")` saying what is wrong: not a
    safetensors file, not ours, truncated or tampered (tensor missing, wrong shape or
    dtype, non-finite values), a config out of range, or unreadable training cameras or
    capture record (checkpoints written before the record have none).
    """
    def bad(reason: str) -> InputError:
        return InputError("model", f"{name}: {reason}")

    data = bytes(data)
    header = _header(data)
    if header is None and len(data) > 8 and data[8:9] == b"{" and b'"format":"phd-nerf"' in data:
        raise bad("truncated or corrupt safetensors header")
    if header is None or not is_nerf_checkpoint(data):
        raise bad("not a phd-nerf checkpoint (expected a safetensors file with format 'phd-nerf')")
    meta = header["__metadata__"]
    if meta.get("version") != CHECKPOINT_VERSION:
        raise bad(f"unsupported checkpoint version {meta.get('version')!r} (expected {CHECKPOINT_VERSION})")
    try:
        values = json.loads(meta.get("config", ""))
    except json.JSONDecodeError as exc:
        raise bad(f"config is not valid JSON ({exc.msg})") from None
    except RecursionError:
        raise bad("config nests deeper than the JSON decoder reads") from None
    try:
        config = NeRFConfig.from_dict(values)
    except (InputError, TypeError) as exc:
        raise bad(f"config: {exc}") from None
    try:
        tensors = st_load(data)
    except Exception as exc:  # safetensors raises its own error types for every malformed file
        raise bad(f"truncated or corrupt tensor data ({str(exc).splitlines()[0]})") from None

    model = RadianceField(config)
    expected = model.state_dict()
    for key, ref in expected.items():
        if key not in tensors:
            raise bad(f"tensor {key!r} is missing")
        got = tensors[key]
        if got.shape != ref.shape or got.dtype != ref.dtype:
            raise bad(f"tensor {key!r} has shape {list(got.shape)} {got.dtype}, expected {list(ref.shape)} {ref.dtype}")
        if got.dtype.is_floating_point and key != "grid.density" and not torch.isfinite(got).all():
            raise bad(f"tensor {key!r} holds NaN or infinite values")
    if torch.isnan(tensors["grid.density"]).any():
        raise bad("tensor 'grid.density' holds NaN values")
    unexpected = sorted(set(tensors) - set(expected) - {CAMERAS_TENSOR})
    if unexpected:
        raise bad(f"unexpected tensors {unexpected}")
    model.load_state_dict({k: tensors[k] for k in expected})

    cameras = None
    if CAMERAS_TENSOR in tensors:
        raw = tensors[CAMERAS_TENSOR]
        try:
            frames = json.loads(bytes(raw.numpy().tobytes()).decode())
            cameras = cameras_from_json(frames)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise bad(f"training cameras are not valid JSON ({exc})") from None
        except InputError as exc:
            raise bad(f"training cameras: {exc}") from None
    try:
        trained_on = TrainedOn.from_fields(json.loads(meta.get("trained_on", "{}")))
    except (json.JSONDecodeError, RecursionError, InputError) as exc:
        raise bad(f"the record of its training capture is unreadable ({exc})") from None
    return NeRFRenderer(model, cameras, trained_on=trained_on, **renderer_options)
