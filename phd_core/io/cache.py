"""Results derived from a model file, kept beside it and keyed by what the file holds.

The CLI calibrates a model once and ranks it many times; what the calibration found (and
what the captured views saw, which the default strategy needs at every rank) does not change
while the model does not. `ModelCache` keeps such results in a folder beside the model,
`<model>.phd-cache/` (for a trainer's output folder, `<folder>/.phd-cache/`), one file per
entry named after a hash of the model's bytes, the kind of result and the settings that made
it: a changed model, or other settings, simply miss. Writes are atomic; a cache that cannot
be written (a read-only folder) is skipped with the reason, never an error.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
from torch import Tensor

from .files import write_bytes_atomic, write_json_atomic

CHUNK = 1 << 20  # bytes hashed at a time


def content_digest(path: str | Path) -> str:
    """sha256 hex of a file's bytes, or of a folder's files (relative paths and bytes, sorted;
    the cache folder itself left out). A digest is remembered by (size, mtime) in the cache
    folder, so a 700 MB PLY is hashed once, not at every command."""
    path = Path(path)
    files = [path] if path.is_file() else sorted(
        p for p in path.rglob("*") if p.is_file() and ModelCache.FOLDER_NAME not in p.relative_to(path).parts)
    h = hashlib.sha256()
    for f in files:
        if f is not path:
            h.update(str(f.relative_to(path)).encode() + b"\0")
        with open(f, "rb") as fh:
            while block := fh.read(CHUNK):
                h.update(block)
    return h.hexdigest()


def _stamp(path: Path) -> list[int]:
    """What says a file (or a folder's files) may have changed: sizes and mtimes in ns."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()
                                                 and ModelCache.FOLDER_NAME not in p.relative_to(path).parts)
    return [v for f in files for v in (f.stat().st_size, f.stat().st_mtime_ns)]


class ModelCache:
    """Entries derived from one model (a file or a trainer's folder), beside it."""

    FOLDER_NAME = ".phd-cache"

    def __init__(self, model: str | Path, digest: str | None = None) -> None:
        """digest: the model's sha256 when the caller knows it already (the service's store)."""
        self.model = Path(model)
        self.dir = (self.model / self.FOLDER_NAME if self.model.is_dir()
                    else self.model.with_name(self.model.name + ".phd-cache"))
        self._digest: str | None = digest
        self.skipped: str | None = None  # why the last write did not happen, if it did not

    @property
    def digest(self) -> str:
        """The model's content digest, re-hashed only when its sizes or mtimes changed."""
        if self._digest is None:
            stamp, memo = _stamp(self.model), self.dir / "digest.json"
            try:
                known = json.loads(memo.read_text())
                if known.get("stamp") == stamp:
                    self._digest = str(known["sha256"])
            except (OSError, ValueError, KeyError, AttributeError):
                pass
            if self._digest is None:
                self._digest = content_digest(self.model)
                self._write(lambda: write_json_atomic(memo, {"stamp": stamp, "sha256": self._digest}))
        return self._digest

    def path(self, kind: str, params: Mapping[str, Any], suffix: str) -> Path:
        """The entry's file: kind, then a hash of the model digest and the settings (sorted JSON)."""
        key = json.dumps({"model": self.digest, "params": params}, sort_keys=True, default=str)
        return self.dir / f"{kind}-{hashlib.sha256(key.encode()).hexdigest()[:24]}{suffix}"

    def load_json(self, kind: str, params: Mapping[str, Any]) -> Any | None:
        """The entry, or None when there is none (or it cannot be read)."""
        try:
            return json.loads(self.path(kind, params, ".json").read_text())
        except (OSError, ValueError):
            return None

    def save_json(self, kind: str, params: Mapping[str, Any], obj: Any) -> bool:
        """Store an entry; False (and `skipped` says why) when the folder cannot be written."""
        target = self.path(kind, params, ".json")
        return self._write(lambda: write_json_atomic(target, obj))

    def load_tensors(self, kind: str, params: Mapping[str, Any]) -> dict[str, Tensor] | None:
        """The entry's tensors (loaded with weights_only: plain tensors only), or None."""
        try:
            data = self.path(kind, params, ".pt").read_bytes()
            out = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        except (OSError, RuntimeError, ValueError, EOFError):
            return None
        return out if isinstance(out, dict) else None

    def save_tensors(self, kind: str, params: Mapping[str, Any], tensors: Mapping[str, Tensor]) -> bool:
        """Store named tensors; False (and `skipped` says why) when the folder cannot be written."""
        target = self.path(kind, params, ".pt")
        buf = io.BytesIO()
        torch.save(dict(tensors), buf)
        return self._write(lambda: write_bytes_atomic(target, buf.getvalue()))

    def _write(self, write: Callable[[], None]) -> bool:
        if not self.model.exists():     # deleted while its result was computed: leave no folder behind
            self.skipped = f"cache not written: {self.model} no longer exists"
            return False
        try:
            os.makedirs(self.dir, exist_ok=True)
            write()
        except OSError as e:
            self.skipped = f"cache not written in {self.dir}: {e.strerror or e}"
            return False
        self.skipped = None
        return True


# ----------------------------------------------------------------------------- calibrations

CALIBRATION = "calibration"    # the entry kind of a calibration (`phd calibrate`, `rank`, `uq`, `select`)


def cameras_digest(frames: list[dict[str, Any]]) -> str:
    """sha256 of the frames a calibration ran on (sorted JSON): the `cameras` of its settings."""
    return hashlib.sha256(json.dumps(frames, sort_keys=True).encode()).hexdigest()


def calibration_entries(cache_dir: Path, model_sha256: str) -> tuple[list[dict[str, Any]], int]:
    """The calibration entries in a cache folder made for the model whose file has `model_sha256`
    (the `model_sha256` each entry records), and how many others it holds (another model's, or
    written before entries recorded it). Unreadable entries count as others."""
    mine, others = [], 0
    for path in sorted(cache_dir.glob(CALIBRATION + "-*.json")):
        try:
            entry = json.loads(path.read_text())
        except (OSError, ValueError):
            entry = None
        if isinstance(entry, dict) and entry.get("model_sha256") == model_sha256:
            mine.append(entry)
        else:
            others += 1
    return mine, others


def matching_calibration(entries: list[dict[str, Any]], frames: list[dict[str, Any]],
                         background: Any) -> dict[str, Any] | None:
    """The newest entry calibrated on exactly these training cameras over this background (its
    settings say both): r_drop depends on them, so an entry for others is not this model's."""
    digest = cameras_digest(frames)
    fits = [e for e in entries if isinstance(e.get("settings"), dict) and e["settings"].get("cameras") == digest
            and e["settings"].get("background") == background]
    return max(fits, key=lambda e: str(e.get("created_at", ""))) if fits else None
