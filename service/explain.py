"""What the page's 3D view draws: a model's splats as points (a compact binary), and the
explain job that colours them by coverage, fragility and novelty (`phd_core.uq.explain`).

The scene binary, little-endian:

    b"PHD3", uint32 n, n bytes of JSON (padded with spaces to a multiple of 4), then the
    arrays the JSON's `layout` lists by name, type, offset (from the start) and length:
    positions float32 [P, 3], sigma float32 [P], colours uint8 [P, 4] (RGB and opacity).

The JSON also says the model's splat count (`total`), the points sent (`count`) and the cap,
the capture's up direction (`phd_core.scene.capture_up`, as GET /cameras says it) and the
points' bounds. The explain job's values are one byte per
point of the same draw (same model, same cap), in the same order.
"""

from __future__ import annotations

import base64
import json
import math
import struct

import numpy as np
import torch

from phd_core import uq
from phd_core.executors import LOCAL, Executor
from phd_core.renderers import Renderer
from phd_core.renderers.points import ScenePoints, importance, point_subset, scene_points, splat_model
from phd_core.renderers.visibility import visibility_bytes
from phd_core.uq import Progress
from phd_core.uq.explain import EXPLAIN_UNIT_BYTES, Explanation, explain

from .budget import MemoryLedger
from .errors import busy, invalid
from .jobs import Work
from .plans import Bounded, Renders
from .requests import (
    check_samples,
    job_signal,
    parse_cameras,
    pixels,
    render_size,
    stored_cameras,
    stored_ratio,
    stored_up,
)
from .schemas import ExplainRequest, ExplainResult
from .settings import Settings
from .store import ModelRecord

MAGIC = b"PHD3"
POINT_BYTES = 12 + 4 + 4            # what one point costs in the binary
DRAW_UNIT_BYTES = 40                # the draw: importance, uniforms and keys (float64) per splat, and the ids
NO_VALUE = 255                      # an explained quantity's byte for "no value"
FRAGILITY_QUANTILE = 0.99           # the fragility (and novelty) drawn as the top colour: one hot splat does not
                                    # wash out the rest
COVERAGE_FULL = 3.0                 # views' worth of unhidden sight drawn as the top colour: enough to place a splat
                                    # (two views triangulate it), whatever the number of training views


# ----------------------------------------------------------------------------- the points

def scene_reserve(record: ModelRecord, cap: int) -> int:
    """The bytes a scene request holds beside its model: the draw and the binary."""
    count = min(cap, record.num_units)
    return DRAW_UNIT_BYTES * record.num_units + 2 * POINT_BYTES * count


def scene_bytes(record: ModelRecord, renderer: Renderer, cap: int) -> bytes:
    """The scene binary of a loaded model (module docstring)."""
    points = scene_points(renderer, cap)
    up, _ = stored_up(record)
    arrays = [("positions", "float32", points.positions.numpy()), ("sigma", "float32", points.sigma.numpy()),
              ("colours", "uint8", points.colours.numpy())]
    layout: list[dict[str, object]] = []
    header = {"total": points.total, "count": len(points.ids), "cap": cap, "up": up, "kind": record.kind,
              "bounds": _bounds(points), "layout": layout}
    # The offsets depend on the header's length, which depends on the offsets' digits: lay out
    # with a generous header first, then fix the padding.
    start = 8 + 4 * math.ceil((len(json.dumps(header)) + 64 * len(arrays) + 64) / 4)
    offset = start
    for name, kind, array in arrays:
        layout.append({"name": name, "type": kind, "offset": offset, "length": int(array.size)})
        offset += array.nbytes
    text = json.dumps(header).encode()
    assert len(text) <= start - 8            # the room left for it above
    text += b" " * (start - 8 - len(text))
    return MAGIC + struct.pack("<I", len(text)) + text + b"".join(a.astype(a.dtype.newbyteorder("<")).tobytes()
                                                                   for _, _, a in arrays)


def _bounds(points: ScenePoints) -> dict[str, list[float]]:
    if len(points.ids) == 0:
        return {"min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}
    return {"min": points.positions.amin(0).tolist(), "max": points.positions.amax(0).tolist()}


def load_scene(record: ModelRecord, cap: int, ledger: MemoryLedger, settings: Settings) -> bytes:
    """The scene binary, with the model in memory (loaded if it is not, waiting for room at
    most `upload_wait`: a 429 after that)."""
    try:
        with ledger.models({record.id: record.size_bytes}, scene_reserve(record, cap),
                           timeout=settings.upload_wait) as renderers:
            return scene_bytes(record, renderers[record.id], cap)
    except TimeoutError:
        raise busy("model_id", settings.retry_after) from None


# ----------------------------------------------------------------------------- the explain job

def quantize(values: torch.Tensor, scale: float) -> bytes:
    """Bytes 0-254 linear over [0, scale] (clamped), NO_VALUE where a value is NaN."""
    q = (values / scale if scale > 0 else torch.zeros_like(values)).clamp(0.0, 1.0) * (NO_VALUE - 1)
    q = torch.where(torch.isnan(values), torch.full_like(values, NO_VALUE), q.round())
    return q.to(torch.uint8).numpy().tobytes()


def explanation_values(result: Explanation, ids: torch.Tensor) -> tuple[dict[str, float], dict[str, str]]:
    """The scales and base64 bytes of each quantity at the points `ids`."""
    fragile = result.fragility[~torch.isnan(result.fragility)]
    quantities = {"coverage": (result.coverage, COVERAGE_FULL),
                  "fragility": (result.fragility, float(np.quantile(fragile.numpy(), FRAGILITY_QUANTILE))
                                if len(fragile) else 0.0)}
    if result.novelty is not None:
        # What the pick newly sees is often a small share of a splat (the captured views saw most of
        # it): drawn to the share it reaches, so what #1 adds shows; 0 when it adds nothing.
        novel = result.novelty[result.novelty > 0]
        quantities["novelty"] = (result.novelty, float(np.quantile(novel.numpy(), FRAGILITY_QUANTILE))
                                 if len(novel) else 0.0)
    scales = {name: scale for name, (_, scale) in quantities.items()}
    values = {name: base64.b64encode(quantize(v[ids], scale)).decode("ascii")
              for name, (v, scale) in quantities.items()}
    return scales, values


def explain_job(record: ModelRecord, body: ExplainRequest, settings: Settings, ledger: MemoryLedger,
                executor: Executor = LOCAL) -> tuple[Work, float]:
    captured = (render_size(stored_cameras(record), body, settings, field="captured") if body.captured is None else
                parse_cameras(body.captured, body, settings, field="captured", cap=settings.max_training_cameras))
    if not captured:
        raise invalid("captured", "the model has no training cameras: upload it with its cameras, or give "
                      "the poses already captured")
    pick = None if body.pick is None else parse_cameras([body.pick], body, settings, field="pick", cap=1)[0]
    samples = check_samples(body.samples, settings, uq.DEFAULT_SAMPLES)
    ratio, source = stored_ratio(record, "dropout_ratio", body.dropout_ratio)
    signal = job_signal(body.signal, [(record, source)])
    views = captured + ([pick] if pick is not None else [])
    largest = max(views, key=lambda c: c.width * c.height)
    kept = EXPLAIN_UNIT_BYTES * record.num_units + visibility_bytes(record.num_units, largest) \
        + scene_reserve(record, body.cap)
    renders = Renders([(record, "model_id", views)], samples, kept_bytes=kept, kept_field="downscale",
                      visibility=True, signal=signal)
    renders.plan(settings)

    def work(renderers: dict[str, Renderer], progress: Progress) -> tuple[ExplainResult, dict[str, bytes]]:
        renderer = renderers[record.id]
        ids = point_subset(importance(splat_model(renderer)), body.cap)
        result = explain(renderer, captured, ratio=ratio, samples=samples, seed=body.seed, pick=pick,
                         signal=signal, progress=progress, executor=executor)
        scales, values = explanation_values(result, ids)
        return ExplainResult(model_id=record.id, dropout_ratio=ratio, ratio_source=source, signal=signal,
                             samples=samples, seed=body.seed, width=captured[0].width, height=captured[0].height,
                             num_views=len(captured), total=renderer.num_units, count=len(ids), cap=body.cap,
                             scales=scales, values=values,
                             unseen_share=float((result.coverage == 0).double().mean())), {}

    return Bounded(renders, settings, ledger, work), float(pixels(views) * (samples + 1))

