"""What a model's captured views saw, computed once and kept beside the model.

The coverage strategies (the default among them) count every captured view as seen before
they pick, and what a view saw takes a full render of the model from its camera. The model and
its captured poses do not change between ranks, so `captured_seen` keeps each view's `Seen`
(element ids and visible shares: 12 bytes an element on disk) as its own `ModelCache` entry beside
the model (the CLI's cache folder beside the file; the service's beside the stored model, deleted
with it), with one small index of every stored view's element count for memory plans. A view is
found by its camera's exact pose, intrinsics and size, so:

- a rank whose captured poses are all stored renders none of them;
- a rank whose poses extend the stored set, or hold the model's own captured set (its training
  cameras) and more (a rig's captures since), renders only the new ones and stores them, so
  asking again after each batch costs what changed;
- a rank with the model's own captured set stores it beside any other stored first, so the
  default rank is the one served however the first rank asked;
- any other set is served from the store where it can and rendered where it cannot, and
  nothing is added.

A stored view is never removed (only with the model): a rank planned on the index (the service
plans its memory before the job runs) finds every view the plan counted as stored, whatever
other ranks stored meanwhile. The index is written after the views it names, so it never names a
view that is not there; a view it misses (a crash between the two, or two ranks writing it at
once) is only planned as rendered and found when read.

The renderer's settings that change what a view sees (family, tile, near plane, grid) are stored
with each view; a view stored under other settings is rendered again and replaced.
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
FORMAT = 2                   # the entries' layout (1: every view in one entry); a new layout is a new entry


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
    """The stored views of one model (an entry per view, and an index of them for memory plans);
    `default`: the model's own captured set (its training cameras), the one to keep."""

    def __init__(self, cache: ModelCache, default: Sequence[Camera] | None = None):
        self.cache = cache
        self.default = {camera_key(camera) for camera in default or []}

    def keeps(self, stored: set[str], asked: set[str]) -> bool:
        """Whether a rank asking for `asked` stores the views it has that `stored` lacks: when it
        extends the stored set or holds the default set (module docstring)."""
        if asked <= stored:
            return False
        return stored <= asked or (bool(self.default) and self.default <= asked)

    def index(self) -> dict[str, int]:
        """{camera key: elements} of the stored views, without reading them ({} when none)."""
        found = self.cache.load_json(KIND, {"format": FORMAT})
        views = found.get("views") if isinstance(found, dict) else None
        return {str(k): int(v) for k, v in views.items()} if isinstance(views, dict) else {}

    def load(self, settings: dict[str, Any], keys: Sequence[str]) -> dict[str, tuple[Tensor, Tensor]]:
        """{camera key: (elements [K] long, visible share [K] float64)} of the views among `keys`
        stored with these settings."""
        views = {}
        for key in dict.fromkeys(keys):
            entry = self.cache.load_tensors(KIND, {"format": FORMAT, "view": key})
            try:
                if entry is None or _untext(entry["settings"]) != settings:
                    continue
                elements, share = entry["elements"].long(), entry["share"]
            except (KeyError, ValueError, TypeError, AttributeError, UnicodeDecodeError):
                continue
            if elements.ndim == 1 and share.shape == elements.shape:
                views[key] = (elements, share)
        return views

    def save(self, settings: dict[str, Any], views: dict[str, tuple[Tensor, Tensor]]) -> bool:
        """Store these views, each beside the others, then add them to the index (read again just
        before, so views another rank indexed meanwhile stay named)."""
        for key, (elements, share) in views.items():
            if not self.cache.save_tensors(KIND, {"format": FORMAT, "view": key}, {
                    "settings": _text(settings), "elements": elements.int(), "share": share}):
                return False
        counts = {**self.index(), **{key: len(elements) for key, (elements, _) in views.items()}}
        return self.cache.save_json(KIND, {"format": FORMAT}, {"views": counts})


def captured_seen(renderer: ReportsVisibility, cameras: Sequence[Camera],
                  store: CapturedStore | None = None) -> list[Seen]:
    """What each captured camera saw of the model: from `store` where it holds the camera, else
    one render of the full model (module docstring: which sets are stored)."""
    if store is None:
        return [renderer.visibility(renderer.prepare(camera)).seen() for camera in cameras]
    settings = renderer_settings(renderer)
    keys = [camera_key(camera) for camera in cameras]
    views = store.load(settings, keys)
    indexed = store.index()
    fresh = {}
    for key, camera in zip(keys, cameras):
        if key not in views and key not in fresh:
            seen = renderer.visibility(renderer.prepare(camera)).seen()
            fresh[key] = (seen.elements, seen.visible_share)
    # A stored view rendered again (under other settings, or unreadable) is replaced; with the
    # policy's consent the new views are added too, and those read but missing from the index.
    added = ({**{k: v for k, v in views.items() if k not in indexed}, **fresh}
             if store.keeps(set(indexed), set(keys)) else {k: v for k, v in fresh.items() if k in indexed})
    if added:
        store.save(settings, added)
    views.update(fresh)
    return [Seen(camera, *views[key]) for key, camera in zip(keys, cameras)]
