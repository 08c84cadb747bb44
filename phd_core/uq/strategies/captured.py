"""What a model's captured views saw, computed once and kept beside the model.

The coverage strategies (the default among them) count every captured view as seen before
they pick, and what a view saw takes a full render of the model from its camera. The model and
its captured poses do not change between ranks, so `captured_seen` keeps each view's `Seen`
(element ids and visible shares: 12 bytes an element on disk) in one `ModelCache` entry beside
the model (the CLI's cache folder beside the file; the service's beside the stored model, deleted
with it). A view is found by its camera's exact pose, intrinsics and size, so:

- a rank whose captured poses are all stored renders none of them;
- a rank whose poses extend the stored set (a rig's captures since) renders only the new ones
  and stores the larger set, so asking again after each batch costs what changed;
- a rank with the model's own captured set (its training cameras) stores that set in place of
  any other that does not hold it, so the default rank is the one served however the first
  rank asked;
- any other set is served from the store where it can and rendered where it cannot, and the
  stored set stays as it was.

The renderer's settings that change what a view sees (family, tile, near plane, grid) are stored
with the views; other settings start the entry afresh.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, Sequence

import torch
from torch import Tensor

from ...io.cache import ModelCache
from ...renderers.splats.maths import LOG_T_MIN
from ...renderers.visibility import ELEMENTS_PER_PIXEL, ReportsVisibility, Seen
from ...scene import Camera

KIND = "captured-coverage"
PARAMS = {"format": 1}       # the entry's layout; a new layout is a new entry


def camera_key(camera: Camera) -> str:
    """Names a camera by its exact pose, intrinsics and size."""
    return hashlib.sha256(json.dumps(camera.to_frame(), sort_keys=True).encode()).hexdigest()[:32]


def renderer_settings(renderer: object) -> dict[str, Any]:
    """What besides the model file's bytes decides what a view sees: the renderer's settings,
    the visibility pass's own constants, and where the splats were placed on loading (a trainer
    folder's frame depends on the capture found beside it and on the loader's code, not only on
    the folder's bytes: a hash of the means, about 10 ms a million splats)."""
    means = getattr(getattr(renderer, "model", None), "means", None)
    placed = (hashlib.sha256(means.detach().contiguous().numpy().tobytes()).hexdigest()[:16]
              if isinstance(means, Tensor) else None)
    return {"kind": getattr(renderer, "kind", type(renderer).__name__),
            **{name: getattr(renderer, name) for name in ("tile", "near", "use_grid") if hasattr(renderer, name)},
            "placed": placed, "elements_per_pixel": ELEMENTS_PER_PIXEL, "log_t_min": LOG_T_MIN}


def _text(value: Any) -> Tensor:
    return torch.tensor(list(json.dumps(value).encode()), dtype=torch.uint8)


def _untext(tensor: Tensor) -> Any:
    return json.loads(bytes(tensor.tolist()).decode())


class CapturedStore:
    """The stored views of one model (a `ModelCache` entry, and a small index of it for memory plans);
    `default`: the model's own captured set (its training cameras), the one to keep."""

    def __init__(self, cache: ModelCache, default: Sequence[Camera] | None = None):
        self.cache = cache
        self.default = {camera_key(camera) for camera in default or []}

    def keeps(self, stored: set[str], asked: set[str]) -> bool:
        """Whether a rank asking for `asked` replaces the `stored` set with the views it has: when
        it extends it, or holds the default set that `stored` lacks (module docstring)."""
        if not asked or asked == stored:
            return False
        return stored <= asked or (bool(self.default) and self.default <= asked and not self.default <= stored)

    def index(self) -> dict[str, int]:
        """{camera key: elements} of the stored views, without reading them ({} when none)."""
        found = self.cache.load_json(KIND, PARAMS)
        views = found.get("views") if isinstance(found, dict) else None
        return {str(k): int(v) for k, v in views.items()} if isinstance(views, dict) else {}

    def load(self, settings: dict[str, Any]) -> dict[str, tuple[Tensor, Tensor]]:
        """{camera key: (elements [K] long, visible share [K] float64)} stored with these settings."""
        entry = self.cache.load_tensors(KIND, PARAMS)
        try:
            if entry is None or _untext(entry["settings"]) != settings:
                return {}
            keys, counts = _untext(entry["keys"]), entry["counts"].tolist()
            elements, shares = entry["elements"].long(), entry["share"]
            if len(keys) != len(counts) or sum(counts) != len(elements) or len(shares) != len(elements):
                return {}
        except (KeyError, ValueError, TypeError, AttributeError, UnicodeDecodeError):
            return {}
        return dict(zip(keys, zip(elements.split(counts), shares.split(counts))))

    def save(self, settings: dict[str, Any], views: dict[str, tuple[Tensor, Tensor]]) -> bool:
        """Store these views (in place of any before): the tensors, then their index."""
        counts = [len(elements) for elements, _ in views.values()]
        stored = self.cache.save_tensors(KIND, PARAMS, {
            "settings": _text(settings), "keys": _text(list(views)), "counts": torch.tensor(counts),
            "elements": torch.cat([e.int() for e, _ in views.values()]) if views else torch.zeros(0, dtype=torch.int32),
            "share": torch.cat([s for _, s in views.values()]) if views else torch.zeros(0, dtype=torch.float64)})
        return stored and self.cache.save_json(KIND, PARAMS, {"views": dict(zip(views, counts))})


def captured_seen(renderer: ReportsVisibility, cameras: Sequence[Camera],
                  store: CapturedStore | None = None) -> list[Seen]:
    """What each captured camera saw of the model: from `store` where it holds the camera, else
    one render of the full model (module docstring: which sets are stored)."""
    if store is None:
        return [renderer.visibility(renderer.prepare(camera)).seen() for camera in cameras]
    settings = renderer_settings(renderer)
    stored = store.load(settings)
    keys = [camera_key(camera) for camera in cameras]
    views = dict(stored)
    for key, camera in zip(keys, cameras):
        if key not in views:
            seen = renderer.visibility(renderer.prepare(camera)).seen()
            views[key] = (seen.elements, seen.visible_share)
    if store.keeps(set(stored), set(keys)):
        store.save(settings, {key: views[key] for key in dict.fromkeys(keys)})
    return [Seen(camera, *views[key]) for key, camera in zip(keys, cameras)]
